"""The progress watchdog and the goal's bookkeeping for one flight (pure; time is passed in).

The local planner goes round obstacles by its own modes, and a way round can lead away from the goal
for seconds. What it cannot know is that it has been going round for too long: a vehicle circling in
front of something it cannot get past only spends battery near obstacles. So the service (and the
simulator, in the same way) watches the progress toward the goal: when the vehicle has not got
``command.progress_step_m`` nearer its goal in the time it takes to fly
``planner.no_progress_distance_m`` at cruise, the flight holds position with the reason and waits
for the operator (:class:`ProgressWatch`, :class:`GoalProgress`).

Progress is metres growing toward the goal: minus the horizontal distance to a goal point, or the
distance along the course at engagement (the line from where the vehicle was engaged, along the
heading it had then: :func:`along_course_m`), less the height between the vehicle and the goal's
altitude (the altitude when the goal was set, which the planner comes back to). A vehicle that climbed
over something and comes back down to its altitude in front of a door is getting nearer its goal; one
that climbs and comes down again in place gets no nearer than it was.
"""

from __future__ import annotations

import math

import numpy as np

from companion.core.frames import finite_position, ned_to_body_horizontal
from companion.core.goal import COURSE, Goal, GoalSpec, resolve_goal
from companion.core.types import Decision, DecisionKind

#: The decision in force while the progress watchdog holds: a brake, so that every filter that acts on
#: a brake acts on this hold too.
NO_PROGRESS_HOLD = Decision(
    kind=DecisionKind.BRAKE, yaw=0.0, pitch=0.0, speed_fraction=0.0, reason="no progress along the course: holding"
)


def along_course_m(position_ned_m: np.ndarray, origin_ned_m: np.ndarray, heading_rad: float) -> float:
    """How far (metres) a position (float ``(3,)`` NED metres) lies along the course: its horizontal
    component from ``origin_ned_m`` along ``heading_rad`` (radians from north; negative = behind the
    origin)."""
    d = np.asarray(position_ned_m, dtype=np.float64) - np.asarray(origin_ned_m, dtype=np.float64)
    forward, _ = ned_to_body_horizontal(float(d[0]), float(d[1]), heading_rad)
    return forward


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


class ProgressWatch:
    """The progress watchdog's clock: the time since the progress last grew by a step.

    The caller passes the progress (metres, growing toward the goal) and the time; :meth:`update` says
    whether the limit has passed. A progress that is unknown or not finite restarts the clock
    (nothing is judged without it).
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Start again (engage, resume, a new goal: anything that was not the automatic flight)."""
        self._mark_m: float | None = None
        self._since_s: float | None = None

    def update(self, progress_m: float | None, now_s: float, step_m: float, timeout_s: float) -> bool:
        """Feed the progress now (metres; None = unknown) at ``now_s`` seconds; True once it has not
        grown by ``step_m`` metres for more than ``timeout_s`` seconds (always False for a
        ``timeout_s`` of 0: off)."""
        if timeout_s <= 0.0 or progress_m is None or not math.isfinite(progress_m) or not math.isfinite(now_s):
            self.reset()
            return False
        if self._mark_m is None or self._since_s is None or progress_m >= self._mark_m + step_m:
            self._mark_m, self._since_s = float(progress_m), float(now_s)
        return now_s - self._since_s > timeout_s

    def stalled_for_s(self, now_s: float) -> float | None:
        """Seconds since the progress last grew by a step (the clock), or None."""
        return None if self._since_s is None else max(0.0, now_s - self._since_s)

    @property
    def mark_m(self) -> float | None:
        """The progress (metres) the clock last restarted at, or None."""
        return self._mark_m


class GoalProgress:
    """The goal of the flight under way, the course it was set on, and the progress watchdog.

    Built with no course; :meth:`engage` sets it.
    """

    def __init__(self) -> None:
        self.goal = Goal(COURSE, None)
        self.origin_ned_m: np.ndarray | None = None
        self.heading_rad: float | None = None
        self.goal_down_m: float | None = None
        self._engaged_at: tuple[np.ndarray | None, float | None] = (None, None)
        self.watch = ProgressWatch()

    def engage(self, position_ned_m: object, heading_rad: float | None, goal: GoalSpec = COURSE) -> None:
        """The flight starts at ``position_ned_m`` (float ``(3,)`` NED metres) heading ``heading_rad``
        (radians from north) toward ``goal`` (:mod:`companion.core.goal`; default: the heading and
        line now). An unknown or non-finite part stays unknown, and no progress is judged without it."""
        self._engaged_at = (finite_position(position_ned_m), _finite(heading_rad))
        self.set_goal(goal, position_ned_m, heading_rad)

    def set_goal(self, goal: GoalSpec, position_ned_m: object, heading_rad: float | None) -> None:
        """A new goal from the vehicle's position and heading now (the operator's ``goto``): a point's
        progress is its distance, ``course`` goes back to the heading and line at engagement; the
        watchdog starts again."""
        pos = finite_position(position_ned_m)
        self.goal = resolve_goal(goal, pos, _finite(heading_rad))
        self.goal_down_m = None if pos is None else float(pos[2])
        self.origin_ned_m, self.heading_rad = self._engaged_at
        self.watch.reset()

    def resume(self) -> None:
        """Try again after a hold (the operator's ``resume``): the watchdog starts again."""
        self.watch.reset()

    def progress_m(self, position_ned_m: object) -> float | None:
        """How far along toward the goal the vehicle is, metres (growing toward it): minus the
        distance to a goal point, or the distance along the course at engagement, less the height to
        the goal's altitude; None unknown."""
        pos = finite_position(position_ned_m)
        if pos is None:
            return None
        if self.goal.is_point:
            d = self.goal.distance_m(pos)
            if d is None:
                return None
            along = -d
        elif self.origin_ned_m is None or self.heading_rad is None:
            return None
        else:
            along = along_course_m(pos, self.origin_ned_m, self.heading_rad)
        return along - (0.0 if self.goal_down_m is None else abs(float(pos[2]) - self.goal_down_m))

    def no_progress(self, position_ned_m: object, now_s: float, step_m: float, timeout_s: float) -> bool:
        """The watchdog fed the position now: True once the vehicle has got no ``step_m`` metres
        nearer its goal for ``timeout_s`` seconds (0: off)."""
        return self.watch.update(self.progress_m(position_ned_m), now_s, step_m, timeout_s)

    def status(self, position_ned_m: object, reached: bool = False) -> dict[str, object]:
        """For health: the goal (``kind``, ``description``, ``north_m``/``east_m`` of a point), the
        horizontal ``distance_m`` and ``bearing_deg`` (from north) to it from ``position_ned_m`` (for
        the course: null, and the course's heading), and whether it was ``reached``."""
        pos = finite_position(position_ned_m)
        point = self.goal.point_ned_m
        bearing = self.goal.bearing_rad(pos) if point is not None else self.heading_rad
        return {
            "kind": self.goal.spec.kind,
            "description": self.goal.spec.describe(),
            "north_m": None if point is None else float(point[0]),
            "east_m": None if point is None else float(point[1]),
            "distance_m": self.goal.distance_m(pos),
            "bearing_deg": None if bearing is None else math.degrees(bearing),
            "reached": reached,
        }
