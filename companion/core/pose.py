"""Vehicle pose in the world (NED) and the fixed body -> camera axis permutation."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Camera axes (x right, y down, z forward) expressed in the body frame (FRD), as columns:
#: ``v_body = CAMERA_TO_BODY @ v_cam``. The camera looks along body x.
CAMERA_TO_BODY: np.ndarray = np.array(
    [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=np.float64
)
CAMERA_TO_BODY.setflags(write=False)


def _finite3(name: str, value: object) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Pose:
    """Pose of the vehicle body in the world.

    Attributes:
        position_ned_m: body origin in NED, metres (north, east, down); altitude h is ``z = -h``.
        yaw_rad: heading, positive clockwise seen from above (0 = north, +pi/2 = east).
        pitch_rad: positive nose up.
        roll_rad: positive right wing down.

    The rotation is the aerospace Z-Y-X sequence: ``R_ned_from_body = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
    """

    position_ned_m: tuple[float, float, float]
    yaw_rad: float = 0.0
    pitch_rad: float = 0.0
    roll_rad: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_ned_m", _finite3("position_ned_m", self.position_ned_m))
        for name in ("yaw_rad", "pitch_rad", "roll_rad"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r}")
            object.__setattr__(self, name, value)

    @classmethod
    def from_telemetry(cls, position_ned_m: object, attitude_rad: object) -> Pose | None:
        """The pose from an autopilot's position (NED metres, 3 numbers) and attitude (roll, pitch,
        yaw radians, 3 numbers), as the vehicle link reports them; None when either is missing,
        not 3 numbers or not finite."""
        if position_ned_m is None or attitude_rad is None:
            return None
        try:
            p = np.asarray(position_ned_m, dtype=np.float64).reshape(3)
            a = np.asarray(attitude_rad, dtype=np.float64).reshape(3)
        except (TypeError, ValueError):
            return None
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(a))):
            return None
        return cls((float(p[0]), float(p[1]), float(p[2])), float(a[2]), float(a[1]), float(a[0]))

    @classmethod
    def at(
        cls,
        north_m: float,
        east_m: float,
        altitude_m: float,
        yaw_rad: float = 0.0,
        pitch_rad: float = 0.0,
        roll_rad: float = 0.0,
    ) -> Pose:
        """A pose from north/east position and altitude above the ground (positive up), metres."""
        return cls((north_m, east_m, -altitude_m), yaw_rad, pitch_rad, roll_rad)

    def ned_from_body(self) -> np.ndarray:
        """Rotation matrix float64 ``(3, 3)``: ``v_ned = R @ v_body`` (body FRD)."""
        cy, sy = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        cp, sp = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        cr, sr = math.cos(self.roll_rad), math.sin(self.roll_rad)
        return np.array(
            [
                [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                [-sp, cp * sr, cp * cr],
            ],
            dtype=np.float64,
        )

    def ned_from_camera(self) -> np.ndarray:
        """Rotation matrix float64 ``(3, 3)``: ``v_ned = R @ v_cam`` (camera: x right, y down, z fwd)."""
        return self.ned_from_body() @ CAMERA_TO_BODY
