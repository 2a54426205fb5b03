"""Config of the depth look-up table and the per-region temporal filter (``[lut]``)."""

from __future__ import annotations

from pydantic import Field, field_validator

from companion.config._base import StrictModel


class LutConfig(StrictModel):
    """Depth refinement (paper section VI) and per-region temporal filter."""

    points_m: list[tuple[float, float]] = Field(
        default=[(0.2, 0.2), (40.0, 40.0)],
        min_length=2,
        max_length=256,
        description=(
            "Pairs (computed depth, true depth), metres, both strictly increasing. Depths are mapped "
            "piecewise-linearly and clamped to the table's ends. The default is the identity."
        ),
    )
    median_frames: int = Field(
        default=3,
        ge=1,
        le=9,
        description=(
            "Each region depth is the median of its last this many frames, odd (an unknown region "
            "counts at once and unknown history counts as near). 1 = off (the paper). 3: a false stereo "
            "match that lasts one frame (a weak-texture patch matched far off, read as a near obstacle "
            "in open space) no longer swerves the vehicle, and a near region that drops out to far for "
            "one frame stays near, at the cost of seeing a suddenly appearing obstacle one frame later "
            "(67 ms at 15 Hz)."
        ),
    )
    release_time_constant_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Low-pass time constant for a region depth that grows (an obstacle receding), seconds; "
            "0 = off. A depth that shrinks (an obstacle approaching) is never delayed. Simulator-tuned: "
            "an obstacle leaving the centre keeps the avoidance going a little longer, for margin."
        ),
    )

    @field_validator("median_frames")
    @classmethod
    def _odd_window(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"median_frames must be odd, got {v}")
        return v

    @field_validator("points_m")
    @classmethod
    def _monotone(cls, pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
        for i in range(1, len(pts)):
            (c0, t0), (c1, t1) = pts[i - 1], pts[i]
            if not c1 > c0:
                raise ValueError(
                    f"computed depths must be strictly increasing: point {i} has {c1} m after {c0} m"
                )
            if not t1 > t0:
                raise ValueError(
                    f"true depths must be strictly increasing: point {i} has {t1} m after {t0} m"
                )
        for i, (c, t) in enumerate(pts):
            if c <= 0 or t <= 0:
                raise ValueError(f"depths must be positive: point {i} is ({c}, {t})")
        return pts
