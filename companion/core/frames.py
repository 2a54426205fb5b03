"""Frame rotations and positions for the progress watchdog and the goal (pure; no state)."""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np

T = TypeVar("T", float, np.ndarray)


def ned_to_body_horizontal(north: T, east: T, yaw_rad: float) -> tuple[T, T]:
    """A horizontal NED vector (north, east: floats, or float arrays of one shape; any unit) in the
    body frame of a vehicle heading ``yaw_rad`` (radians from north, clockwise): (forward, right),
    same unit and shape. Yaw only: roll and pitch are left out, as for PX4's body-frame velocity
    setpoints."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return c * north + s * east, -s * north + c * east


def finite_position(position_ned_m: object) -> np.ndarray | None:
    """A float64 ``(3,)`` copy of a NED position in metres when it is one and finite, else None."""
    if position_ned_m is None:
        return None
    try:
        p = np.asarray(position_ned_m, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    return p.copy() if np.all(np.isfinite(p)) else None
