"""Course hold's bookkeeping for one flight, shared by the service's supervisor and the simulator.

Course hold brings the vehicle back to the heading, the line and the altitude it was engaged at, once
the way has been clear for a while (:func:`~companion.core.command.setpoint_for` says how). What it
needs between setpoints lives here, once:

* the course: where the vehicle was engaged (the line's origin), its heading and altitude then;
* how long the decisions have been straight and CLEAR, and how far the vehicle has flown since
  (:func:`~companion.core.command.is_straight_clear`), and how long they have not turned
  (:func:`~companion.core.command.is_heading_clear`);
* where the current brake began (:class:`~companion.core.command.BrakeLatch`), where something was
  last overhead (:class:`~companion.core.command.OverheadMemory`) and the progress watchdog's clock
  (:class:`~companion.core.command.ProgressWatch`);
* the goal (:mod:`companion.core.goal`): the course at engagement, or a point. For a point, the
  course is the line from where the goal was set to the point (and, after a detour, from where the
  detour handed back), and progress is getting nearer the point; reaching it (within
  ``command.goal_radius_m``) ends the run in a hold (:attr:`CourseHold.holding_reason`);
* the detour layer (:class:`~companion.core.detour.DetourPlanner`): when the way is blocked it owns
  the setpoint (:func:`~companion.core.command.detour_setpoint`) until it hands back; a dead end is
  a hold too.

One clock: a decision's timers run from the capture time of the first frame that made it (the
``timestamp_s`` of a frame result), and every elapsed time is measured to the time of the setpoint
being made. The service and the simulator both pass those two times, so they wait the same.

Pure: positions, headings and times are passed in; nothing here reads a clock.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from companion.core.command import (
    NO_PROGRESS_HOLD,
    BrakeLatch,
    OverheadMemory,
    ProgressWatch,
    _aim_error_rad,
    above_floor,
    along_course_m,
    clear_of_below,
    detour_setpoint,
    horizontal_distance_m,
    horizontal_velocity_body_m_s,
    is_heading_clear,
    is_straight_clear,
    line_offset_m,
    setpoint_for,
    stoppable_speed_m_s,
)
from companion.core.closing import ClosingWatch, TrackWatch
from companion.core.detour import DetourPlanner, Phase
from companion.core.frames import finite_position
from companion.core.goal import COURSE, Goal, GoalSpec, resolve_goal
from companion.core.memory import apply_guard
from companion.core.types import REGION_INDEX, Decision, DecisionKind, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config.core import CommandConfig, MemoryConfig
    from companion.config.detour import DetourConfig
    from companion.core.memory import Gap, ObstacleMemory


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def forward_within_cruise(sp: VelocitySetpoint, cmd: CommandConfig) -> VelocitySetpoint:
    """``sp`` with its forward speed at most ``cmd.cruise_speed_m_s`` (m/s): the shapers that add to
    a cruising setpoint (the guard's push away from a point behind, the counters) never send the
    vehicle forward faster than the speed the user chose."""
    if sp.forward_m_s <= cmd.cruise_speed_m_s:
        return sp
    return replace(sp, forward_m_s=cmd.cruise_speed_m_s)


class CourseHold:
    """What course hold remembers during one flight (see the module doc).

    Built with no course; :meth:`engage` sets it. The clear timers run from construction on (a
    vehicle engaged after a clear stretch may hold its course at once), the latches and the
    progress clock from :meth:`engage`.

    Args:
        defer_histogram: the detour layer leaves its histograms to the caller
            (:class:`~companion.core.detour.DetourPlanner`'s ``defer``: the service computes them off
            its control loop); False: computed at once (the simulator).
    """

    def __init__(self, defer_histogram: bool = False) -> None:
        self.origin_ned_m: np.ndarray | None = None
        self.heading_rad: float | None = None
        self.altitude_m: float | None = None
        self._clear_since_s: float | None = None
        self._clear_since_ned_m: np.ndarray | None = None
        self._heading_clear_since_s: float | None = None
        self._any_clear_since_s: float | None = None  # CLEAR, turning or not
        self.brake = BrakeLatch()
        self.overhead = OverheadMemory()
        self.progress = ProgressWatch()
        self.goal = Goal(COURSE, None)
        self.detour = DetourPlanner(defer=defer_histogram)
        #: The camera's check on the velocity estimate (``command.unseen_closing_range_m``).
        self.closing = ClosingWatch()
        #: The reported position's motion the reported velocity does not explain
        #: (``command.track_velocity_window_s``).
        self.track = TrackWatch()
        #: The unexplained motion the last setpoint countered, m/s (0: none), for the health message.
        self.track_counter_m_s = 0.0
        #: The unseen drift the last setpoint countered, m/s (0: none), for the health message.
        self.unseen_drift_m_s = 0.0
        self._engaged_at: tuple[np.ndarray | None, float | None] = (None, None)
        #: The side the detour's turn in place has been turning (+1 right, -1 left, 0 none).
        self._turn_sign = 0.0
        #: Why the flight holds now (the goal reached, a dead end), or None: the caller holds (as for
        #: the progress watchdog) until :meth:`resume` or a new goal.
        self.holding_reason: str | None = None

    def engage(self, position_ned_m: object, heading_rad: float | None, goal: GoalSpec = COURSE) -> None:
        """The course starts here: float ``(3,)`` NED metres (the line's origin and, as ``-down``, the
        altitude) and the heading (radians); an unknown or non-finite part stays unknown, and the
        hold that needs it stays off. ``goal``: where to (:mod:`companion.core.goal`; default the
        heading and line now). Forgets any brake, overhead sighting, progress and detour."""
        origin = finite_position(position_ned_m)
        self.origin_ned_m = origin
        self.heading_rad = _finite(heading_rad)
        self.altitude_m = None if origin is None else -float(origin[2])
        self._engaged_at = (origin, self.heading_rad)
        self.brake.reset()
        self.overhead.reset()
        self.closing.reset()
        self.track.reset()
        self.set_goal(goal, position_ned_m, heading_rad)

    def set_goal(self, goal: GoalSpec, position_ned_m: object, heading_rad: float | None) -> None:
        """A new goal, from the vehicle's position and heading now (``goto``). A point's course is the
        line from here to it; ``course`` goes back to the heading and line at engagement. The altitude
        held stays the engagement's. Forgets the progress and any detour or hold."""
        self.goal = resolve_goal(goal, position_ned_m, heading_rad)
        if self.goal.is_point:
            self._anchor_to_goal(position_ned_m)
        else:
            self.origin_ned_m, self.heading_rad = self._engaged_at
        self.progress.reset()
        self.detour.reset()
        self._turn_sign = 0.0
        self.holding_reason = None

    def resume(self) -> None:
        """Try again after a hold (the operator's ``resume``): forget the hold, the progress and any
        detour (its trail is kept)."""
        self.progress.reset()
        self.detour.reset()
        self._turn_sign = 0.0
        self.holding_reason = None

    def _anchor_to_goal(self, position_ned_m: object) -> None:
        """For a goal point: the course becomes the line from ``position_ned_m`` to the point."""
        here = finite_position(position_ned_m)
        bearing = self.goal.bearing_rad(here)
        if here is not None and bearing is not None:
            self.origin_ned_m, self.heading_rad = here, bearing

    def observe(self, decision: Decision | None, decision_time_s: float | None, position_ned_m: object) -> None:
        """The decision in force, made from the frame captured at ``decision_time_s`` (seconds), with
        the vehicle at ``position_ned_m`` (float ``(3,)`` NED metres, or None). Call it before each
        :meth:`setpoint` (and may be called more often: the same decision again changes nothing)."""
        if decision is None or decision_time_s is None or not is_straight_clear(decision):
            self._clear_since_s = None
            self._clear_since_ned_m = None
        elif self._clear_since_s is None:
            self._clear_since_s = float(decision_time_s)
            self._clear_since_ned_m = None if position_ned_m is None else np.array(position_ned_m, dtype=np.float64)
        if decision is None or decision_time_s is None or not is_heading_clear(decision):
            self._heading_clear_since_s = None
        elif self._heading_clear_since_s is None:
            self._heading_clear_since_s = float(decision_time_s)
        if decision is None or decision_time_s is None or decision.kind is not DecisionKind.CLEAR:
            self._any_clear_since_s = None
        elif self._any_clear_since_s is None:
            self._any_clear_since_s = float(decision_time_s)

    def ready(self, position_ned_m: object) -> bool:
        """Whether the course (origin and heading) and the vehicle's position are known."""
        return self.origin_ned_m is not None and self.heading_rad is not None and position_ned_m is not None

    def progress_m(self, position_ned_m: object) -> float | None:
        """How far along toward the goal the vehicle is, metres (growing toward it): minus the
        distance to a goal point, or the distance along the course at engagement; None unknown."""
        if self.goal.is_point:
            d = self.goal.distance_m(finite_position(position_ned_m))
            return None if d is None else -d
        if self.ready(position_ned_m):
            return along_course_m(position_ned_m, self.origin_ned_m, self.heading_rad)
        return None

    def no_progress(
        self, position_ned_m: object, now_s: float, cmd: CommandConfig, regress: bool = True, timeout_s: float | None = None
    ) -> bool:
        """The progress watchdog fed the progress now (:meth:`progress_m`): True once the vehicle has
        got no ``cmd.progress_step_m`` nearer its goal for ``cmd.no_progress_timeout_s``, or (with
        ``regress``) has been flying back for ``cmd.regress_timeout_s``
        (:class:`~companion.core.command.ProgressWatch`, its ``why``). While a detour is under way
        the clock stands still and regress is not judged: a detour is bounded by its own limits
        (``detour.max_time_s``, ``max_distance_m``, and ``max_detours_without_progress`` of them).
        ``timeout_s``: the local planner's watchdog time in place of ``cmd.no_progress_timeout_s``."""
        return self.progress.update(
            self.progress_m(position_ned_m), now_s, cmd, pause=self.detour.active, regress=regress, timeout_s=timeout_s
        )

    def goal_bearing_rad(self, position_ned_m: object, yaw_rad: float | None, cmd: CommandConfig) -> float | None:
        """The direction toward the goal from here, radians from north: the bearing to a goal point,
        or, for the course at engagement, the heading course hold aims at (the course heading turned
        toward the line); None when unknown."""
        pos = finite_position(position_ned_m)
        if self.goal.is_point:
            return self.goal.bearing_rad(pos)
        if self.heading_rad is None or pos is None or self.origin_ned_m is None:
            return None
        offset = line_offset_m(pos, self.origin_ned_m, self.heading_rad)
        aim = _aim_error_rad(0.0, offset, cmd)
        return self.heading_rad + (0.0 if aim is None else aim)

    def goal_status(self, position_ned_m: object) -> dict[str, object]:
        """For health: the goal (``kind``, ``description``, ``north_m``/``east_m`` of a point), the
        horizontal ``distance_m`` and ``bearing_deg`` (from north) to it from ``position_ned_m`` (for
        the course: null, and the course's heading), whether it was ``reached``, and the detour
        layer's ``detour`` status."""
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
            "reached": self.holding_reason is not None and self.holding_reason.startswith("goal reached"),
            "detour": self.detour.status(),
        }

    def setpoint(
        self,
        decision: Decision | None,
        now_s: float,
        since_last_frame_s: float,
        cmd: CommandConfig,
        *,
        position_ned_m: np.ndarray | None,
        yaw_rad: float | None,
        velocity_ned_m_s: np.ndarray | None = None,
        position_time_s: float | None = None,
        region_depths_m: np.ndarray | None = None,
        guard_m: np.ndarray | None = None,
        remembered_sides: tuple[bool, bool] | None = None,
        gap: Gap | None = None,
        path_ahead_m: float | None = None,
        memory_cfg: MemoryConfig | None = None,
        obstacles: ObstacleMemory | None = None,
        detour_cfg: DetourConfig | None = None,
        prefer_right: bool = True,
        planning: bool = True,
    ) -> VelocitySetpoint:
        """The setpoint for ``decision`` at ``now_s`` (seconds, the clock of :meth:`observe`'s times),
        its frame ``since_last_frame_s`` old, with the course hold's inputs from this flight's
        bookkeeping (:func:`~companion.core.command.setpoint_for`), never descending below
        ``cmd.min_altitude_m`` (:func:`~companion.core.command.above_floor`).

        Args:
            position_ned_m: float ``(3,)`` NED metres now, or None.
            yaw_rad: heading now, radians, or None.
            velocity_ned_m_s: float ``(3,)`` NED m/s now, or None (the guard's lean needs it).
            position_time_s: when the autopilot's position and velocity arrived, seconds on
                ``now_s``'s clock (None: ``now_s``); the track counter's samples are timed by it, so
                that telemetry older than the call does not read as motion.
            region_depths_m: float ``(9,)`` refined region depths, metres, NaN unknown, or None.
            guard_m, remembered_sides, gap, path_ahead_m: the obstacle memory's inputs
                (:meth:`~companion.core.memory.ObstacleMemory.hold_inputs`), or None (memory off).
            memory_cfg: the ``[memory]`` config that goes with them.
            obstacles: the obstacle memory itself, for the detour layer and course hold's descent
                (:meth:`~companion.core.memory.ObstacleMemory.clear_below`); None: neither.
            detour_cfg: the ``[detour]`` config (None: no detour).
            prefer_right: a detour's tie goes right (``controller.preferred_yaw_side``).
            planning: False while the caller holds (the watchdog, the goal reached, a dead end): no
                goal check, no detour.
        """
        yaw = _finite(yaw_rad)
        fresh = (
            decision is not None
            and math.isfinite(since_last_frame_s)
            and since_last_frame_s <= cmd.stale_frame_timeout_s
        )
        self._observe_closing(decision, now_s, since_last_frame_s, region_depths_m, yaw, velocity_ned_m_s, cmd)
        self.track.observe(now_s if position_time_s is None else position_time_s, position_ned_m, velocity_ned_m_s)
        unexplained = self.track.unexplained_m_s(now_s, cmd.track_velocity_window_s, cmd.max_track_counter_m_s)
        moving = velocity_ned_m_s
        if unexplained is not None and velocity_ned_m_s is not None:
            moving = np.asarray(velocity_ned_m_s, dtype=np.float64).reshape(-1).copy()
            moving[:2] += unexplained  # how the vehicle moves in the frame the memory lives in
        command = None
        if planning and fresh and self.holding_reason is None:
            command = self._plan(decision, now_s, cmd, position_ned_m, yaw, obstacles, memory_cfg, detour_cfg, prefer_right)
        if self.holding_reason is not None and decision is not None:
            decision = NO_PROGRESS_HOLD  # the goal reached, or a dead end: the brake's holds
        altitude_error = None
        if self.altitude_m is not None and position_ned_m is not None:
            down = float(np.asarray(position_ned_m, dtype=np.float64)[2])
            if math.isfinite(down):
                altitude_error = self.altitude_m + down  # altitude then minus now; positive: climb back
        below_clear = None
        if (
            altitude_error is not None
            and altitude_error < 0.0
            and self.altitude_m is not None
            and position_ned_m is not None
            and obstacles is not None
            and memory_cfg is not None
        ):
            below_clear = obstacles.clear_below(position_ned_m, now_s, memory_cfg, -self.altitude_m)
        clear_since = self._clear_since_s
        # Not straight and CLEAR now (a CLEAR decision still turning, as the release filter lets an
        # escape fade, included): the holds wait from zero. None here would mean "no wait", and
        # turning back in place then fought the escape's last turn.
        clear_for_s = 0.0 if clear_since is None else max(0.0, now_s - clear_since)
        clear_for_m = 0.0 if clear_since is None else horizontal_distance_m(self._clear_since_ned_m, position_ned_m)
        since_up_near = self.overhead.update(region_depths_m, position_ned_m, cmd.hold_clear_depth_m)
        if command is not None and detour_cfg is not None:
            sp = detour_setpoint(
                command,
                decision,
                since_last_frame_s,
                cmd,
                detour_cfg,
                position_ned_m=position_ned_m,
                yaw_rad=yaw,
                brake_offset_body_m=self.brake.offset_body(decision, position_ned_m, yaw),
                brake_heading_error_rad=self.brake.heading_error_rad(yaw),
                guard_m=guard_m,
                guard_cfg=memory_cfg,
                velocity_body_m_s=horizontal_velocity_body_m_s(moving, yaw),
                region_depths_m=region_depths_m,
                turn_sign=self._turn_sign,
                altitude_error_m=altitude_error,
                below_clear=below_clear,
                clear_for_s=clear_for_s,
                clear_for_m=clear_for_m,
                since_up_near_m=since_up_near,
                path_ahead_m=path_ahead_m,
            )
            turning = command.anchor_ned_m is not None and sp.yaw_rate_deg_s != 0.0
            self._turn_sign = math.copysign(1.0, sp.yaw_rate_deg_s) if turning else 0.0
            sp = forward_within_cruise(
                self._counter_drift(sp, decision, now_s, yaw, cmd, fresh, guard_m, memory_cfg, unexplained, region_depths_m), cmd
            )
            return self._vertical_limits(
                sp, now_s, cmd, position_ned_m, velocity_ned_m_s, region_depths_m, obstacles, memory_cfg, fresh
            )
        self._turn_sign = 0.0
        heading_error = line_offset = None
        if self.heading_rad is not None and yaw is not None:
            heading_error = self.heading_rad - yaw  # positive: the course lies to the right
        if self.ready(position_ned_m):
            line_offset = line_offset_m(position_ned_m, self.origin_ned_m, self.heading_rad)
        heading_since = self._heading_clear_since_s
        any_since = self._any_clear_since_s
        sp = setpoint_for(
            decision,
            since_last_frame_s,
            cmd,
            heading_error_rad=heading_error,
            altitude_error_m=altitude_error,
            region_depths_m=region_depths_m,
            clear_for_s=clear_for_s,
            clear_for_m=clear_for_m,
            heading_clear_for_s=0.0 if heading_since is None else max(0.0, now_s - heading_since),
            any_clear_for_s=0.0 if any_since is None else max(0.0, now_s - any_since),
            brake_offset_body_m=self.brake.offset_body(decision, position_ned_m, yaw),
            brake_heading_error_rad=self.brake.heading_error_rad(yaw),
            line_offset_m=line_offset,
            since_up_near_m=since_up_near,
            guard_m=guard_m,
            guard_cfg=memory_cfg,
            remembered_sides=remembered_sides,
            velocity_body_m_s=horizontal_velocity_body_m_s(moving, yaw),
            gap=gap,
            path_ahead_m=path_ahead_m,
            below_clear=below_clear,
        )
        sp = forward_within_cruise(
            self._counter_drift(sp, decision, now_s, yaw, cmd, fresh, guard_m, memory_cfg, unexplained, region_depths_m), cmd
        )
        return self._vertical_limits(
            sp, now_s, cmd, position_ned_m, velocity_ned_m_s, region_depths_m, obstacles, memory_cfg, fresh
        )

    def _observe_closing(
        self,
        decision: Decision | None,
        now_s: float,
        since_last_frame_s: float,
        region_depths_m: np.ndarray | None,
        yaw: float | None,
        velocity_ned_m_s: np.ndarray | None,
        cmd: CommandConfig,
    ) -> None:
        """Feed :attr:`closing` the reported forward speed now and, once per frame, the centre's depth."""
        if cmd.unseen_closing_range_m <= 0.0:
            return
        body = horizontal_velocity_body_m_s(velocity_ned_m_s, yaw)
        self.closing.observe_velocity(now_s, None if body is None else body[0])
        if decision is None or region_depths_m is None or not math.isfinite(since_last_frame_s):
            return
        centre = float(np.asarray(region_depths_m, dtype=np.float64)[REGION_INDEX["center"]])
        self.closing.observe_frame(now_s - since_last_frame_s, centre, yaw, cmd)

    def _counter_drift(
        self,
        sp: VelocitySetpoint,
        decision: Decision | None,
        now_s: float,
        yaw: float | None,
        cmd: CommandConfig,
        fresh: bool,
        guard_m: np.ndarray | None,
        memory_cfg: MemoryConfig | None,
        unexplained_ned_m_s: np.ndarray | None,
        region_depths_m: np.ndarray | None,
    ) -> VelocitySetpoint:
        """``sp`` less the drift the estimate does not show (the vehicle flies the setpoint plus the
        drift), in the body frame at ``yaw``: ``command.track_counter_fraction`` of the reported
        position's unexplained motion (``unexplained_ned_m_s``, north and east m/s, or None), and the
        unseen closing the camera sees beyond it. A stale frame's zero stays zero. The counter backs
        away from what the camera sees, toward what it does not: the guard's slide past a remembered
        point on the counter's own path (``guard_m``, no push again) applies to the counter alone.
        ``sp`` has had the guard already (its push and lean away from a remembered wall included);
        sliding the sum again took that push off too: a point on the far side of a push (a false
        near point that may not push) would cancel both the push away from the wall and the counter,
        and the drift would carry the vehicle into the wall.
        Forward the counter adds nothing while ``decision`` brakes or the centre of
        ``region_depths_m`` cannot be read, never more than the vehicle can stop short of what
        the centre reads (:func:`stoppable_speed_m_s`), and never past ``cmd.cruise_speed_m_s``: the
        brake is absolute, and the unexplained motion may be the estimate's, not the vehicle's. The
        horizontal speed it leaves is at most the cruise (or ``sp``'s own, when that is faster)."""
        self.unseen_drift_m_s = 0.0
        self.track_counter_m_s = 0.0
        if not fresh or yaw is None:
            return sp
        counter = np.zeros(2)  # what the counters add, body forward and right m/s
        countered = (0.0, 0.0)  # the track's counter, body forward and right m/s
        if unexplained_ned_m_s is not None and cmd.track_counter_fraction > 0.0:
            body = horizontal_velocity_body_m_s(cmd.track_counter_fraction * unexplained_ned_m_s, yaw)
            if body is not None:
                countered = body
                counter -= body
                self.track_counter_m_s = float(math.hypot(body[0], body[1]))
        drift = self.closing.drift(now_s, cmd) if cmd.unseen_closing_range_m > 0.0 else None
        if drift is not None:
            speed, heading = drift
            off = heading - yaw  # positive: the drift points to the right of the nose
            # What the track's counter already took off along the drift's heading is not taken twice.
            speed = max(0.0, speed - (countered[0] * math.cos(off) + countered[1] * math.sin(off)))
            self.unseen_drift_m_s = speed
            counter -= (speed * math.cos(off), speed * math.sin(off))
        if not np.any(counter):
            return sp
        if guard_m is not None and memory_cfg is not None and len(guard_m):
            slide_only = np.array(guard_m, dtype=np.float64).reshape(len(guard_m), -1)[:, :3]
            slide_only = np.column_stack([slide_only, np.zeros(len(slide_only))])
            counter[:] = apply_guard(float(counter[0]), float(counter[1]), slide_only, memory_cfg)
        forward, right = sp.forward_m_s + float(counter[0]), sp.right_m_s + float(counter[1])
        if forward > sp.forward_m_s:
            room = min(cmd.cruise_speed_m_s, self._forward_room_m_s(decision, region_depths_m, cmd))
            forward = min(forward, max(sp.forward_m_s, room))
        # Never faster than the cruise (the speed the user chose, within the envelope): the
        # unexplained motion may be the estimate's, not the vehicle's.
        limit = max(cmd.cruise_speed_m_s, math.hypot(sp.forward_m_s, sp.right_m_s))
        speed = math.hypot(forward, right)
        if speed > limit:
            forward, right = forward * limit / speed, right * limit / speed
        if forward == sp.forward_m_s and right == sp.right_m_s:
            return sp
        return replace(sp, forward_m_s=forward, right_m_s=right)

    @staticmethod
    def _forward_room_m_s(decision: Decision | None, region_depths_m: np.ndarray | None, cmd: CommandConfig) -> float:
        """How fast a counter may send the vehicle forward, m/s: not at all while ``decision`` brakes
        or the centre region's depth (``region_depths_m``, float ``(9,)`` metres) is unknown, else
        what it can stop short of."""
        if decision is None or decision.kind is DecisionKind.BRAKE or region_depths_m is None:
            return 0.0
        centre = float(np.asarray(region_depths_m, dtype=np.float64)[REGION_INDEX["center"]])
        return stoppable_speed_m_s(centre, cmd) if math.isfinite(centre) else 0.0

    @staticmethod
    def _vertical_limits(
        sp: VelocitySetpoint,
        now_s: float,
        cmd: CommandConfig,
        position_ned_m: object,
        velocity_ned_m_s: np.ndarray | None,
        region_depths_m: np.ndarray | None,
        obstacles: ObstacleMemory | None,
        memory_cfg: MemoryConfig | None,
        fresh: bool,
    ) -> VelocitySetpoint:
        """Whatever drove ``sp``: a climb back to ``memory.clearance_below_m`` over what is remembered
        below (:func:`~companion.core.command.clear_of_below`), and the floor
        (:func:`~companion.core.command.above_floor`, reckoned ahead by the measured sink
        ``velocity_ned_m_s``); neither climbs on a stale frame's zero."""
        pos = finite_position(position_ned_m)
        if fresh and obstacles is not None and memory_cfg is not None and memory_cfg.clearance_below_m > 0.0 and pos is not None:
            gap = obstacles.gap_below_m(pos, now_s, memory_cfg, -cmd.min_altitude_m)
            sp = clear_of_below(sp, gap, region_depths_m, memory_cfg.clearance_below_m, cmd)
        return above_floor(sp, position_ned_m, cmd, region_depths_m, climb_back=fresh, velocity_ned_m_s=velocity_ned_m_s)

    def _plan(
        self,
        decision: Decision,
        now_s: float,
        cmd: CommandConfig,
        position_ned_m: object,
        yaw: float | None,
        obstacles: ObstacleMemory | None,
        memory_cfg: MemoryConfig | None,
        detour_cfg: DetourConfig | None,
        prefer_right: bool,
    ):
        """The goal check and the detour layer for one setpoint: sets :attr:`holding_reason` when the
        goal is reached or the detour finds a dead end; returns the detour's command, or None."""
        pos = finite_position(position_ned_m)
        d = self.goal.distance_m(pos)
        if d is not None and d <= cmd.goal_radius_m:
            p = self.goal.point_ned_m
            self.holding_reason = (
                f"goal reached ({self.goal.spec.describe()}, within {cmd.goal_radius_m:g} m at N {p[0]:.1f} m, "
                f"E {p[1]:+.1f} m): holding there; goto a new goal, or take over"
            )
            self.detour.reset()
            return None
        if detour_cfg is None or memory_cfg is None:
            return None
        was_active = self.detour.active
        command = self.detour.update(
            now_s,
            decision,
            pos,
            yaw,
            self.goal_bearing_rad(pos, yaw, cmd),
            self.progress.stalled_for_s(now_s),
            obstacles,
            memory_cfg,
            detour_cfg,
            prefer_right,
            goal_distance_m=d,
            stall_mark_m=self.progress.mark_m,
            course_down_m=None if self.altitude_m is None else -self.altitude_m,
            regressing=self.progress.regressing,
            floor_down_m=-cmd.min_altitude_m if cmd.min_altitude_m > 0.0 else None,
        )
        if command is not None and command.phase is Phase.DEAD_END:
            self.holding_reason = (
                f"{command.reason}: holding position; goto another goal, resume to look again, or take over"
            )
            # Hold here, facing as the look round left it: the brake's latch from before the look round
            # turned a PX4 SITL vehicle back through 137 deg for 8 s, and the hold settled only after.
            self.brake.reset()
            return None
        if was_active and command is None and self.goal.is_point:
            self._anchor_to_goal(pos)  # handed back: the course is now the line from here to the goal
        return command
