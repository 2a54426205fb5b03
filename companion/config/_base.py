"""Base model shared by every config section: frozen, unknown keys rejected, defaults validated."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictModel(BaseModel):
    """A frozen pydantic model that rejects unknown keys.

    Frozen so that a config object handed to the pipeline can never change under it: a reload builds a
    whole new model and swaps the reference.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)
