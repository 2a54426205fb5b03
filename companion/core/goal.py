"""Where the vehicle is going: the operator's goal, and where it lies from the vehicle (pure).

A goal is asked for (:class:`GoalSpec`, from ``engage`` or ``goto``) in one of three ways:

* ``course``: the heading the vehicle had when it was engaged (the default): there is nothing to
  arrive at, the vehicle flies on along it (the local planner aims at a point far along it);
* ``point``: a point in the autopilot's local frame, north and east metres;
* ``bearing``: a bearing (degrees clockwise from north, or from the vehicle's heading) and a distance,
  from where the vehicle is when the goal is set.

:func:`resolve_goal` turns a spec into a :class:`Goal` from the vehicle's position and heading at
that moment: a point in the local frame, or none (the course). The goal is horizontal: the local
planner keeps the altitude the vehicle was engaged at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

GoalKind = Literal["course", "point", "bearing"]


@dataclass(frozen=True)
class GoalSpec:
    """A goal as asked for (see the module doc).

    Attributes:
        kind: ``course``, ``point`` or ``bearing``.
        north_m, east_m: the point, local NED metres (``point``).
        bearing_deg: degrees clockwise from north, or from the heading with ``from_heading``
            (``bearing``).
        distance_m: how far along that bearing, metres (``bearing``; > 0).
        from_heading: ``bearing_deg`` is relative to the vehicle's heading when the goal is set.
    """

    kind: GoalKind = "course"
    north_m: float = 0.0
    east_m: float = 0.0
    bearing_deg: float = 0.0
    distance_m: float = 0.0
    from_heading: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("course", "point", "bearing"):
            raise ValueError(f"goal kind must be course, point or bearing, got {self.kind!r}")
        for name in ("north_m", "east_m", "bearing_deg", "distance_m"):
            if not math.isfinite(float(getattr(self, name))):
                raise ValueError(f"goal {name} must be finite, got {getattr(self, name)!r}")
        if self.kind == "bearing" and not self.distance_m > 0.0:
            raise ValueError(f"goal distance_m must be > 0, got {self.distance_m!r}")

    def describe(self) -> str:
        """One line, e.g. ``point N 12.0 m, E -3.0 m``."""
        if self.kind == "point":
            return f"point N {self.north_m:.1f} m, E {self.east_m:+.1f} m"
        if self.kind == "bearing":
            ref = "from the heading" if self.from_heading else "from north"
            return f"{self.distance_m:.1f} m at {self.bearing_deg:.0f} deg {ref}"
        return "the course at engagement (heading and line)"


#: The default goal: the heading and line at engagement.
COURSE = GoalSpec()


@dataclass(frozen=True)
class Goal:
    """A goal placed in the local frame.

    Attributes:
        spec: what was asked for.
        point_ned_m: float ``(3,)`` NED metres (its down is the vehicle's when the goal was set), or
            None for the course at engagement.
    """

    spec: GoalSpec
    point_ned_m: np.ndarray | None

    @property
    def is_point(self) -> bool:
        return self.point_ned_m is not None

    def distance_m(self, position_ned_m: object) -> float | None:
        """Horizontal distance from ``position_ned_m`` (float ``(3,)`` NED metres) to the point, metres;
        None for the course goal or without a finite position."""
        if self.point_ned_m is None or position_ned_m is None:
            return None
        p = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        d = math.hypot(float(self.point_ned_m[0] - p[0]), float(self.point_ned_m[1] - p[1]))
        return d if math.isfinite(d) else None

    def bearing_rad(self, position_ned_m: object) -> float | None:
        """Bearing from ``position_ned_m`` to the point, radians clockwise from north in [-pi, pi);
        None for the course goal, without a finite position, or at the point itself."""
        if self.point_ned_m is None or position_ned_m is None:
            return None
        p = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        dn, de = float(self.point_ned_m[0] - p[0]), float(self.point_ned_m[1] - p[1])
        if not (math.isfinite(dn) and math.isfinite(de)) or math.hypot(dn, de) < 1e-9:
            return None
        return math.atan2(de, dn)


def resolve_goal(spec: GoalSpec, position_ned_m: object, yaw_rad: float | None) -> Goal:
    """Place ``spec`` in the local frame from the vehicle's position (float ``(3,)`` NED metres) and
    heading (radians) now. A ``bearing`` goal needs both (and a ``from_heading`` one the heading);
    without them, and for ``course``, the goal is the course (no point)."""
    p = None
    if position_ned_m is not None:
        arr = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        if arr.shape == (3,) and np.all(np.isfinite(arr)):
            p = arr
    if spec.kind == "point":
        down = float(p[2]) if p is not None else 0.0
        return Goal(spec, np.array([spec.north_m, spec.east_m, down], dtype=np.float64))
    if spec.kind == "bearing" and p is not None:
        bearing = math.radians(spec.bearing_deg)
        if spec.from_heading:
            if yaw_rad is None or not math.isfinite(yaw_rad):
                return Goal(spec, None)
            bearing += yaw_rad
        return Goal(
            spec,
            np.array([p[0] + spec.distance_m * math.cos(bearing), p[1] + spec.distance_m * math.sin(bearing), p[2]]),
        )
    return Goal(spec, None)
