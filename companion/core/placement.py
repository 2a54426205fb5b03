"""Where a course lies in an autopilot's local frame (pure).

PX4 reports its pose in its own local NED frame (origin where its estimator started, north up). A
course is defined in its own frame (start at the origin heading north, ground at z = 0). A
:class:`CoursePlacement` maps one onto the other with a translation and a rotation about the vertical,
so a course can be flown wherever the vehicle happens to be: the SITL harness places the course under
the vehicle, sitting on the ground, before take-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.pose import Pose


def wrap_pi(angle_rad: float) -> float:
    """``angle_rad`` wrapped to [-pi, pi)."""
    return (float(angle_rad) + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class CoursePlacement:
    """The course frame inside the autopilot's local frame.

    Attributes:
        origin_ned_m: the course origin (the ground under the course start) in the autopilot's local
            NED frame, metres.
        yaw_rad: the course's north axis as a heading in the autopilot's frame, radians clockwise
            from north.
    """

    origin_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_rad: float = 0.0

    @classmethod
    def under(cls, position_ned_m: np.ndarray, yaw_rad: float) -> CoursePlacement:
        """The placement that puts the course start under a vehicle sitting on the ground at
        ``position_ned_m`` (float ``(3,)`` local NED, metres) heading ``yaw_rad``: the course's ground
        is at the vehicle's height, its north axis along the vehicle's heading."""
        p = np.asarray(position_ned_m, dtype=np.float64).reshape(3)
        return cls((float(p[0]), float(p[1]), float(p[2])), wrap_pi(yaw_rad))

    def _rot(self) -> np.ndarray:
        # course-from-local: rotate by -yaw about the down axis.
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float64)

    def position_in_course(self, position_ned_m: np.ndarray) -> np.ndarray:
        """Local NED positions, float ``(..., 3)`` metres, in the course frame (same shape)."""
        p = np.asarray(position_ned_m, dtype=np.float64)
        return (p - np.asarray(self.origin_ned_m)) @ self._rot().T

    def vector_in_course(self, vector_ned: np.ndarray) -> np.ndarray:
        """Local NED vectors (velocities), float ``(..., 3)``, in the course frame (rotation only)."""
        return np.asarray(vector_ned, dtype=np.float64) @ self._rot().T

    def position_in_local(self, position_course_m: np.ndarray) -> np.ndarray:
        """Course-frame positions, float ``(..., 3)`` metres, in the autopilot's local NED frame."""
        return np.asarray(position_course_m, dtype=np.float64) @ self._rot() + np.asarray(self.origin_ned_m)

    def pose_in_course(self, position_ned_m: np.ndarray, attitude_rad: np.ndarray) -> Pose:
        """The vehicle's pose in the course frame from its local position (float ``(3,)`` NED metres)
        and attitude (float ``(3,)`` roll, pitch, yaw radians). Exact: a rotation about the vertical
        only changes the Z-Y-X yaw."""
        p = self.position_in_course(position_ned_m)
        roll, pitch, yaw = (float(a) for a in np.asarray(attitude_rad, dtype=np.float64).reshape(3))
        return Pose((float(p[0]), float(p[1]), float(p[2])), wrap_pi(yaw - self.yaw_rad), pitch, roll)
