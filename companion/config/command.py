"""Config of when frames are too old to fly on, and the progress watchdog's step (``[command]``)."""

from __future__ import annotations

from pydantic import Field, model_validator

from companion.config._base import StrictModel


class CommandConfig(StrictModel):
    """When frames are too old to trust, and what counts as progress toward the goal."""

    stale_frame_timeout_s: float = Field(
        default=0.5,
        gt=0.0,
        le=10.0,
        description="A newest frame older than this gives a zero-velocity setpoint (state degraded), seconds.",
    )
    failsafe_timeout_s: float = Field(
        default=5.0,
        gt=0.0,
        le=120.0,
        description="A newest frame older than this makes the service leave offboard to Hold (state failsafe), seconds.",
    )
    progress_step_m: float = Field(
        default=1.0,
        gt=0.0,
        le=50.0,
        description=(
            "Progress watchdog: how much nearer the goal (metres; farther along the course at "
            "engagement, for the course; the height back to the goal's altitude counts too) counts "
            "as progress and restarts the watchdog's time (planner.no_progress_distance_m at cruise)."
        ),
    )

    @model_validator(mode="after")
    def _order(self) -> CommandConfig:
        if self.failsafe_timeout_s <= self.stale_frame_timeout_s:
            raise ValueError(
                f"failsafe_timeout_s ({self.failsafe_timeout_s}) must exceed stale_frame_timeout_s "
                f"({self.stale_frame_timeout_s})"
            )
        return self
