"""Plain data types shared by every stage of the pipeline, the daemon and the simulator.

Conventions used throughout ``companion``:

* Images are NumPy arrays in row-major ``(H, W)`` (grey) or ``(H, W, 3)`` (BGR, OpenCV order), uint8.
  A ZED frame is side by side: ``(H, 2W, 3)``, left eye in columns ``[0, W)``, right eye in ``[W, 2W)``.
* Disparity is float32 ``(H, W)`` in pixels, NaN where no match was accepted (never 0 for "invalid").
* Depth is float32 ``(H, W)`` in metres along the optical axis (z), NaN where disparity is NaN, +inf
  where the match says disparity 0 (farther than the stereo rig can resolve).
* Region depths are float64 ``(9,)`` in metres in :data:`REGION_NAMES` order, NaN for "unknown".
* Body frame (PX4/MAVSDK ``VelocityBodyYawspeed``): x forward, y right, z down; yaw rate positive
  clockwise seen from above (turning right).
* Fuzzy outputs: yaw in [-1, +1] (-1 hard left, +1 hard right), pitch in [-1, +1] (-1 down, +1 up).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from companion.config.regions import REGION_NAMES  # re-exported: the core names the regions by it

REGION_INDEX: dict[str, int] = {name: i for i, name in enumerate(REGION_NAMES)}
N_REGIONS = len(REGION_NAMES)


class DecisionKind(str, enum.Enum):
    """What the controller decided for one frame."""

    CLEAR = "clear"  #: centre far: fly straight on
    AVOID = "avoid"  #: centre (partly) near and an escape direction exists: steer
    BRAKE = "brake"  #: centre near and no escape, or no rule fired: zero velocity, hold position


@dataclass(frozen=True)
class RegionDepths:
    """Per-region robust minimum depth of one frame.

    Attributes:
        depth_m: float64 ``(9,)``, metres, NaN where the region is unknown.
        valid_fraction: float64 ``(9,)``, share of the region's pixels with a valid depth, in [0, 1].
    """

    depth_m: np.ndarray
    valid_fraction: np.ndarray

    @property
    def known(self) -> np.ndarray:
        """bool ``(9,)``: True where the region has a depth."""
        return ~np.isnan(self.depth_m)

    def as_dict(self) -> dict[str, float | None]:
        """Region name -> depth in metres, ``None`` for unknown (JSON-ready)."""
        return {
            name: (None if np.isnan(v) else float(v)) for name, v in zip(REGION_NAMES, self.depth_m)
        }


@dataclass(frozen=True)
class Decision:
    """The controller's verdict for one frame.

    Attributes:
        kind: clear / avoid / brake.
        yaw: in [-1, 1], positive = turn right. 0 when braking.
        pitch: in [-1, 1], positive = climb. 0 when braking.
        speed_fraction: share of the cruise speed to fly forward, in [0, 1]; 0 when braking.
        reason: one human-readable line (which controller or rule decided, or why it braked).
        rule_strengths: rule name -> firing strength in [0, 1], for the rules that fired.
    """

    kind: DecisionKind
    yaw: float
    pitch: float
    speed_fraction: float
    reason: str
    rule_strengths: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class VelocitySetpoint:
    """A body-frame velocity and yaw-rate setpoint, the shape of MAVSDK's ``VelocityBodyYawspeed``.

    Attributes:
        forward_m_s: body x velocity, m/s.
        right_m_s: body y velocity, m/s.
        down_m_s: body z velocity, m/s (positive descends).
        yaw_rate_deg_s: yaw rate, deg/s (positive turns right / clockwise seen from above).
    """

    forward_m_s: float = 0.0
    right_m_s: float = 0.0
    down_m_s: float = 0.0
    yaw_rate_deg_s: float = 0.0

    @property
    def is_zero(self) -> bool:
        return (
            self.forward_m_s == 0.0
            and self.right_m_s == 0.0
            and self.down_m_s == 0.0
            and self.yaw_rate_deg_s == 0.0
        )


ZERO_SETPOINT = VelocitySetpoint()
