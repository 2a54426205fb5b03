"""Config section of the CuPy backend (issue 4)."""

from __future__ import annotations

from pydantic import Field

from companion.config._base import StrictModel


class GpuConfig(StrictModel):
    """GPU backend options."""

    device_id: int = Field(default=0, ge=0, le=64, description="CUDA device ordinal.")
