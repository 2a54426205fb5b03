"""Config section of the closed-loop simulator (issue 3)."""

from __future__ import annotations

from pydantic import Field

from companion.config._base import StrictModel


class SimConfig(StrictModel):
    """Simulator options."""

    camera_rate_hz: float = Field(default=15.0, gt=0.0, le=120.0, description="Simulated camera frame rate, Hz.")
