"""Ground-truth clearance and the outcome of a flight (pure: positions and times are passed in).

**Clearance** at a point = the Euclidean distance from the vehicle's centre to the nearest solid
surface (every obstacle, the ground and a ceiling if the scene has one: exactly
``Scene.distance_to_obstacles_m(p, include_ground=True)``) **minus the collision radius**. It is the
gap between the vehicle's collision sphere and the world: negative = a collision.

**Outcomes** (:class:`Outcome`), checked at every physics step in this order:

* ``collision``: clearance < 0;
* ``goal``: the centre entered the course's goal region;
* ``out_of_bounds``: the centre left the course's bounds;
* ``held``: stopped (speed < ``held_speed_m_s`` and |yaw rate| < 3 deg/s) for ``held_after_s``
  without a collision: the vehicle braked and holds position;
* ``timeout``: the course's time limit passed.

A flight succeeds on ``goal``, or on ``held`` where the course counts holding as success.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from companion.sim.render import Box, Pillar, Scene

if TYPE_CHECKING:
    from companion.sim.courses import Course


#: Held, for a vehicle whose velocity does not tell (PX4's estimate wanders in a hover; the simulator
#: with ``sim.drift_speed_m_s``): every position of the last ``sim.held_after_s`` within this of the
#: newest, metres.
HELD_RADIUS_M = 0.15

class Outcome(str, enum.Enum):
    """How a flight ended."""

    GOAL = "goal"
    COLLISION = "collision"
    HELD = "held"
    TIMEOUT = "timeout"
    OUT_OF_BOUNDS = "out_of_bounds"


class ClearanceField:
    """Fast signed distance from one point to a scene's solids (obstacles, ground, ceiling).

    Vectorised over the obstacles (one NumPy pass per point instead of one per obstacle); equal to
    ``scene.distance_to_obstacles_m(point, include_ground=True)``.

    Args:
        scene: the world.
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        boxes = [o for o in scene.obstacles if isinstance(o, Box)]
        pillars = [o for o in scene.obstacles if isinstance(o, Pillar)]
        self._box_c = np.array([b.centre_ned_m for b in boxes], dtype=np.float64).reshape(-1, 3)
        self._box_r = np.array([b.axes() for b in boxes], dtype=np.float64).reshape(-1, 3, 3)
        self._box_h = 0.5 * np.array([b.size_m for b in boxes], dtype=np.float64).reshape(-1, 3)
        self._pil_c = np.array([p.centre_ned_m for p in pillars], dtype=np.float64).reshape(-1, 3)
        self._pil_r = np.array([p.radius_m for p in pillars], dtype=np.float64)
        self._pil_hh = 0.5 * np.array([p.height_m for p in pillars], dtype=np.float64)
        self._pil_step = np.array([2.0 * math.pi / p.sides for p in pillars], dtype=np.float64)
        self._pil_half_edge = self._pil_r * np.tan(0.5 * self._pil_step)
        self._ground = scene.ground
        self._ceiling_z = None if scene.ceiling_altitude_m is None else -float(scene.ceiling_altitude_m)

    def distance_m(self, point_ned_m: np.ndarray) -> float:
        """Signed distance from ``point_ned_m`` (float ``(3,)`` NED metres) to the nearest solid surface,
        metres (negative inside an obstacle or below the ground); +inf when there is nothing."""
        p = np.asarray(point_ned_m, dtype=np.float64)
        best = math.inf
        if self._box_c.shape[0]:
            local = np.einsum("nij,nj->ni", self._box_r, p - self._box_c)
            q = np.abs(local) - self._box_h
            outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
            inside = np.minimum(q.max(axis=1), 0.0)
            best = min(best, float((outside + inside).min()))
        if self._pil_c.shape[0]:
            rel = p - self._pil_c
            ang = np.arctan2(rel[:, 1], rel[:, 0])
            phi = np.round(ang / self._pil_step) * self._pil_step
            rho = np.hypot(rel[:, 0], rel[:, 1])
            px = rho * np.cos(ang - phi)
            py = np.abs(rho * np.sin(ang - phi))
            out_x = px - self._pil_r
            d2 = np.where((out_x > 0.0) & (py > self._pil_half_edge), np.hypot(out_x, py - self._pil_half_edge), out_x)
            dz = np.abs(rel[:, 2]) - self._pil_hh
            outside = np.hypot(np.maximum(d2, 0.0), np.maximum(dz, 0.0))
            inside = np.minimum(np.maximum(d2, dz), 0.0)
            best = min(best, float((outside + inside).min()))
        if self._ground:
            best = min(best, float(-p[2]))
        if self._ceiling_z is not None:
            best = min(best, float(p[2] - self._ceiling_z))
        return best


def is_success(outcome: Outcome, hold_is_success: bool) -> bool:
    """Goal reached, or held safely where the course counts that as success."""
    return outcome is Outcome.GOAL or (outcome is Outcome.HELD and hold_is_success)


#: |yaw rate| below which a stopped vehicle counts as holding (not turning on the spot), deg/s.
HELD_YAW_RATE_DEG_S = 3.0


class Judge:
    """The verdict on a flight, fed one position sample at a time (the kinematic simulator feeds every
    physics step; the PX4 SITL harness feeds PX4's own position telemetry).

    Checks, in the order of the module docstring, at every :meth:`update`: collision, goal, out of
    bounds, held, timeout. Keeps the minimum clearance (and where it was) and the path length.

    Args:
        course: the course, in its own frame (positions given to :meth:`update` must be too).
        collision_radius_m: radius of the vehicle's collision sphere, metres.
        held_speed_m_s: below this speed (and |yaw rate| < 3 deg/s) the vehicle counts as stopped.
        held_after_s: stopped this long = held.
        start_position_ned_m: float ``(3,)`` NED metres, the first sample (clearance is checked there).
        start_time_s: time of that sample, seconds (the course's time limit counts from it).
        held_radius_m: if set, "stopped" means instead: every sample of the last ``held_after_s``
            lies within this distance of the newest one (for measured positions, whose velocity
            estimate is too noisy for ``held_speed_m_s``: PX4's hover wanders at up to 0.2 m/s).
    """

    def __init__(
        self,
        course: Course,
        collision_radius_m: float,
        held_speed_m_s: float,
        held_after_s: float,
        start_position_ned_m: np.ndarray,
        start_time_s: float = 0.0,
        held_radius_m: float | None = None,
    ) -> None:
        self.course = course
        self.held_radius_m = held_radius_m
        self._recent: deque[tuple[float, np.ndarray]] = deque()
        self.radius_m = float(collision_radius_m)
        self.held_speed_m_s = float(held_speed_m_s)
        self.held_after_s = float(held_after_s)
        self.start_time_s = float(start_time_s)
        self._field = ClearanceField(course.scene)
        self.position_ned_m = np.array(start_position_ned_m, dtype=np.float64).reshape(3)
        self.clearance_m = self._field.distance_m(self.position_ned_m) - self.radius_m
        self.min_clearance_m = self.clearance_m
        self.min_clearance_at_ned_m = self.position_ned_m.copy()
        self.path_length_m = 0.0
        self.outcome: Outcome | None = None
        self.reason = ""
        self._stopped_since: float | None = None

    def update(self, time_s: float, position_ned_m: np.ndarray, speed_m_s: float, yaw_rate_rad_s: float) -> Outcome | None:
        """Take one sample (time in seconds, float ``(3,)`` NED metres in the course frame, ground speed
        m/s, yaw rate rad/s); returns the outcome once the flight is decided (and keeps returning it)."""
        if self.outcome is not None:
            return self.outcome
        pos = np.array(position_ned_m, dtype=np.float64).reshape(3)
        self.path_length_m += float(np.linalg.norm(pos - self.position_ned_m))
        self.position_ned_m = pos
        clearance = self._field.distance_m(pos) - self.radius_m
        self.clearance_m = clearance
        if clearance < self.min_clearance_m:
            self.min_clearance_m, self.min_clearance_at_ned_m = clearance, pos.copy()
        t = float(time_s)
        if self.held_radius_m is not None:
            if abs(math.degrees(yaw_rate_rad_s)) >= HELD_YAW_RATE_DEG_S:
                # Turning in place (a detour's look round) is not holding, drift or not: the window
                # of samples starts again after the turn.
                self._recent.clear()
                self._stopped_since = None
            else:
                self._stopped_since = self._stopped_in_place_since(t, pos)
        elif speed_m_s < self.held_speed_m_s and abs(math.degrees(yaw_rate_rad_s)) < HELD_YAW_RATE_DEG_S:
            self._stopped_since = t if self._stopped_since is None else self._stopped_since
        else:
            self._stopped_since = None
        course = self.course
        if clearance < 0.0:
            self.outcome = Outcome.COLLISION
            self.reason = (
                f"collision at t = {t:.2f} s at north {pos[0]:.2f} m, east {pos[1]:+.2f} m, altitude {-pos[2]:.2f} m"
            )
        elif course.in_goal(pos):
            self.outcome = Outcome.GOAL
            self.reason = f"goal reached at t = {t:.2f} s"
        elif not course.in_bounds(pos):
            self.outcome = Outcome.OUT_OF_BOUNDS
            self.reason = f"left the course bounds at t = {t:.2f} s at north {pos[0]:.2f} m, east {pos[1]:+.2f} m"
        elif self._stopped_since is not None and t - self._stopped_since >= self.held_after_s:
            self.outcome = Outcome.HELD
            self.reason = (
                f"held safely: stopped since t = {self._stopped_since:.2f} s at north {pos[0]:.2f} m "
                f"(clearance {clearance:.2f} m)"
            )
        elif t - self.start_time_s >= course.time_limit_s:
            self.outcome = Outcome.TIMEOUT
            self.reason = f"time limit {course.time_limit_s:.0f} s reached at north {pos[0]:.2f} m"
        return self.outcome

    def _stopped_in_place_since(self, t: float, pos: np.ndarray) -> float | None:
        """The start of the window of samples within ``held_radius_m`` of ``pos``, if it covers
        ``held_after_s``; else None."""
        assert self.held_radius_m is not None
        self._recent.append((t, pos))
        while self._recent and t - self._recent[0][0] > self.held_after_s + 1.0:
            self._recent.popleft()
        since = t
        for ts, p in reversed(self._recent):
            if float(np.linalg.norm(p - pos)) > self.held_radius_m:
                break
            since = ts
        return since if t - since >= self.held_after_s else None

    @property
    def success(self) -> bool:
        """Decided, and a success for this course."""
        return self.outcome is not None and is_success(self.outcome, self.course.hold_is_success)
