"""The service's decision logic as a pure state machine: what to command, and when to enter or leave offboard.

No asyncio, no ZeroMQ, no MAVSDK, no clock: the shell calls :meth:`Supervisor.step` at the setpoint
rate (and whenever a frame result or a request arrives) with the time, the newest frame result, the
vehicle's state and the pending requests, and carries out what it returns: a setpoint to hand to the
vehicle link (or ``None``: hand nothing), and actions (enter offboard, leave it to Hold, stop the
setpoint stream).

States (:class:`State`)::

    passive ──engage──▶ engaging ──offboard confirmed──▶ engaged ◀──resume/expiry── paused / override
       ▲                   │ refused / timeout / pilot          │ frames stale (0.5 s)
       │                   ▼                                    ▼
       └──────────── disengaged(reason) ◀── pilot leaves ── degraded ──frames > 5 s──▶ failsafe
                                             offboard                                  (Hold)

* **passive**: the start. Nothing is sent to the vehicle. ``engage`` (or ``autostart`` once at start)
  moves to *engaging* when the vehicle is connected, armed (if required), not already in offboard, and
  frames are fresh.
* **engaging**: zero setpoints for ``offboard_prestream_s`` (PX4 refuses offboard without a stream),
  then START_OFFBOARD; *engaged* once the vehicle reports OFFBOARD. Refused, not confirmed within
  ``engage_timeout_s``, frames going stale, or a pilot's mode change: *disengaged*.
* **engaged**: the setpoint of the newest decision (:func:`~companion.core.command.setpoint_for`:
  zero on BRAKE; with the ``command`` course-hold gains set, steering back to the heading and altitude
  the vehicle had when it was engaged). **paused**: zero velocity in offboard until ``resume``; or,
  by the progress watchdog (``command.no_progress_timeout_s``; the local planner's: ``planner.no_progress_distance_m``
  at cruise; :class:`~companion.core.command.ProgressWatch`:
  engaged, the vehicle got no farther along the course for that long), a brake's position hold, with
  the guard, until ``resume``. **override**: a manual yaw/pitch/speed for a bounded time, then
  *engaged* again.
* **degraded**: while engaged/paused/override, the newest frame is older than
  ``stale_frame_timeout_s`` (or the camera is gone): zero velocity. Fresh frames return to the activity.
* **failsafe**: the newest frame is older than ``failsafe_timeout_s``: zero velocity and Hold (we own
  offboard, so this fights no one). Also when the vehicle link is lost while commanding: then the
  setpoint stream is stopped without any mode change, so that PX4's own offboard-loss failsafe acts.
  Only an explicit ``engage`` leaves it.
* **engage from the sticks** (``engage_on_offboard_switch``): while passive or disengaged and ready
  (every check of ``engage`` passes), zero setpoints stream so that the autopilot accepts a pilot's
  switch to offboard (PX4 refuses Offboard without a stream); when the vehicle then reports offboard
  the supervisor takes it (*engaged*, no mode command of its own); not ready any more: zero, then the
  stream stops (STOP_SETPOINTS), so the autopilot refuses the switch. Not after a failsafe (only an
  explicit ``engage`` leaves it).
* **disengaged(reason)**: passive, with the reason: an operator's ``disengage`` (we leave offboard to
  Hold first), a refused engage, or **the pilot or PX4 leaving offboard**: then the supervisor stops
  commanding at once, never sends a mode change and never re-engages by itself.

Whenever the supervisor stops commanding it returns a zero setpoint together with STOP_SETPOINTS, so
that the last value MAVSDK holds (and re-sends on its own at 20 Hz until told to stop) is zero; the
link then stops the re-sending without a mode change.

The supervisor knows no autopilot: "offboard" is whatever mode the vehicle link reports as
``in_offboard`` (PX4's OFFBOARD, ArduCopter's GUIDED), "Hold" whatever its ``hold`` selects (PX4's
AUTO.LOITER, ArduCopter's LOITER), and any other mode is the pilot's (or the autopilot's failsafe).

Hold is requested only while the vehicle reports OFFBOARD and the service put it there. While the
vehicle still reports OFFBOARD, Hold is requested again every ``hold_retry_s`` (longer than a heartbeat
period, so a pilot's switch has been seen by then); after ``leave_timeout_s`` the stream is stopped so
that PX4's offboard-loss failsafe acts.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, Union

import numpy as np

from companion.config.core import MemoryConfig
from companion.config.detour import DetourConfig
from companion.config.planner import PlannerConfig
from companion.core.command import NO_PROGRESS_HOLD
from companion.core.course import CourseHold
from companion.core.detour import HistogramRequest, HistogramResult
from companion.core.goal import COURSE, GoalSpec
from companion.core.memory import ObstacleMemory, ViewLimits
from companion.core.planner.stack import LocalStack
from companion.core.pose import Pose
from companion.core.types import ZERO_SETPOINT, Decision, DecisionKind, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.config.core import CommandConfig
    from companion.interfaces import VehicleState


#: Vehicle poses kept to place a frame's points from the pose it was captured at (20 Hz: 3 s).
_POSE_HISTORY = 64
#: A frame's points go into the memory only with a pose this near its capture time, seconds.
_POSE_MATCH_S = 0.2


class State(str, enum.Enum):
    """What the service is doing (health's ``state``)."""

    PASSIVE = "passive"
    ENGAGING = "engaging"
    ENGAGED = "engaged"
    DEGRADED = "degraded"
    FAILSAFE = "failsafe"
    PAUSED = "paused"
    OVERRIDE = "override"
    DISENGAGED = "disengaged"


class Action(str, enum.Enum):
    """What the shell must do on the vehicle link, besides handing over the setpoint."""

    START_OFFBOARD = "start_offboard"  #: request offboard mode (a setpoint has been streamed first)
    HOLD = "hold"  #: leave offboard to Hold (only ever while we own offboard)
    STOP_SETPOINTS = "stop_setpoints"  #: stop streaming (and MAVSDK's re-sending) WITHOUT a mode change


# ---------------------------------------------------------------------------------------------- requests


@dataclass(frozen=True)
class Engage:
    """Operator: take control (enter offboard), flying toward ``goal`` (:mod:`companion.core.goal`;
    default: the heading and line at engagement)."""

    goal: GoalSpec = COURSE


@dataclass(frozen=True)
class Goto:
    """Operator, while engaged: a new goal (:class:`~companion.core.goal.GoalSpec`), from where the
    vehicle is now. Ends a hold of the progress watchdog, a dead end or a goal reached (automatic
    again); refused while not engaged (engage with a goal instead)."""

    goal: GoalSpec


@dataclass(frozen=True)
class Disengage:
    """Operator: give control back (leave offboard to Hold if we are in it)."""


@dataclass(frozen=True)
class Pause:
    """Operator: hover in offboard (zero velocity) until resumed."""


@dataclass(frozen=True)
class Resume:
    """Operator: back to automatic (ends a pause or an override)."""


@dataclass(frozen=True)
class Override:
    """Operator: fly this for ``duration_s`` seconds, then automatic again.

    Attributes:
        yaw: in [-1, 1] (+ turns right), scaled by ``command.max_yaw_rate_deg_s``.
        pitch: in [-1, 1] (+ climbs), scaled by ``command.max_vertical_speed_m_s``.
        speed_fraction: in [0, 1], share of ``command.cruise_speed_m_s``.
        duration_s: > 0, at most ``service.override_max_duration_s``.
    """

    yaw: float
    pitch: float
    speed_fraction: float
    duration_s: float


@dataclass(frozen=True)
class Shutdown:
    """The service is stopping: leave offboard to Hold if we own it, then stop streaming."""


@dataclass(frozen=True)
class ActionResult:
    """The shell's report of how an :class:`Action` went (``ok`` False with the error's message)."""

    action: Action
    ok: bool
    message: str = ""


Request = Union[Engage, Goto, Disengage, Pause, Resume, Override, Shutdown, ActionResult]


@dataclass(frozen=True)
class Reply:
    """The answer to one operator request (ActionResults get none)."""

    request: Request
    ok: bool
    message: str


class FrameOutcome(Protocol):
    """What the supervisor needs from a frame result (:class:`~companion.core.pipeline.FrameResult`)."""

    timestamp_s: float
    decision: Decision


@dataclass(frozen=True)
class StepOutput:
    """What one :meth:`Supervisor.step` decided.

    Attributes:
        setpoint: hand this to the vehicle link now; ``None``: hand nothing (not commanding).
        actions: to carry out after the setpoint, in order.
        state: the state after this step.
        reason: one line saying why the service is in this state.
        replies: one per operator request, in order.
        changed: state or reason differ from before the step.
        frame_age_s: age of the newest frame result at ``now_s`` (inf without one), seconds.
        histogram_request: the detour layer waits for this histogram (a supervisor built with
            ``defer_histogram``): compute it off the control loop
            (:func:`~companion.core.detour.compute_histogram`) and hand the result to a later
            :meth:`Supervisor.step`; None: none wanted.
    """

    setpoint: VelocitySetpoint | None
    actions: tuple[Action, ...]
    state: State
    reason: str
    replies: tuple[Reply, ...]
    changed: bool
    frame_age_s: float
    histogram_request: HistogramRequest | None = None


@dataclass(frozen=True)
class SupervisorConfig:
    """The timing and limits the supervisor applies (seconds unless named otherwise)."""

    command: CommandConfig
    offboard_prestream_s: float = 0.5
    engage_timeout_s: float = 3.0
    hold_retry_s: float = 2.0
    leave_timeout_s: float = 10.0
    require_armed_to_engage: bool = True
    override_max_duration_s: float = 10.0
    override_respects_brake: bool = True
    autostart: bool = False
    engage_on_offboard_switch: bool = False
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    detour: DetourConfig = field(default_factory=DetourConfig)
    prefer_right: bool = True  # a detour's tie goes right (controller.preferred_yaw_side)
    local: CompanionConfig | None = None  # planner.kind "local": the whole config the local stack flies by

    @classmethod
    def from_config(cls, cfg: CompanionConfig) -> SupervisorConfig:
        v, s = cfg.vehicle, cfg.service
        return cls(
            command=cfg.command,
            offboard_prestream_s=v.offboard_prestream_s,
            engage_timeout_s=v.engage_timeout_s,
            hold_retry_s=v.hold_retry_s,
            leave_timeout_s=v.leave_timeout_s,
            require_armed_to_engage=v.require_armed_to_engage,
            override_max_duration_s=s.override_max_duration_s,
            override_respects_brake=s.override_respects_brake,
            autostart=s.autostart,
            engage_on_offboard_switch=v.engage_on_offboard_switch,
            memory=cfg.memory,
            detour=cfg.detour,
            prefer_right=cfg.controller.preferred_yaw_side == "right",
            local=cfg if cfg.planner.kind == "local" else None,
        )


@dataclass
class _Engaging:
    since_s: float
    mode_at_request: str
    start_sent_s: float | None = None
    start_pending: bool = False


@dataclass
class _Leaving:
    since_s: float
    what: str  # why we leave, e.g. "operator disengage"
    start_sent_s: float | None  # an offboard start we asked for that may still take effect
    start_pending: bool
    last_hold_s: float | None = None
    holds: int = 0


@dataclass
class _Memory:
    """Everything the supervisor remembers between steps (mutable, private)."""

    state: State = State.PASSIVE
    reason: str = "started passive: waiting for an engage request"
    activity: State = State.ENGAGED  # engaged / paused / override, while commanding
    streaming: bool = False  # we have handed setpoints and not stopped the stream since
    ready: bool = False  # streaming zero while passive so that a pilot's offboard switch is accepted
    by_switch: bool = False  # the current engagement came from the pilot's offboard switch
    owns_offboard: bool = False  # the vehicle is in offboard because we put it there
    engaging: _Engaging | None = None
    leaving: _Leaving | None = None
    override: Override | None = None
    override_until_s: float = 0.0
    autostart_pending: bool = False
    shutting_down: bool = False
    course: CourseHold = field(default_factory=CourseHold)  # course hold's timers, latches and progress clock
    obstacles: ObstacleMemory = field(default_factory=ObstacleMemory)  # near points seen (the guard)
    stalled: bool = False  # paused by the progress watchdog, a dead end or the goal reached (not by the operator)
    stall_reason: str = ""  # why, as it was when it stalled (the watchdog's clock is reset right after)
    goal: GoalSpec = COURSE  # the goal of the engage under way (applied when offboard is confirmed)
    poses: deque[tuple[float, Pose]] = field(default_factory=lambda: deque(maxlen=_POSE_HISTORY))  # (time s, pose)
    last_frame_s: float | None = None  # capture time of the newest frame put in the memory
    view_limits: ViewLimits | None = None  # what the rig measures, from the frames
    guarding: int = 0  # remembered points (one per sector) that shaped the last engaged setpoint
    local: LocalStack | None = None  # the local planner's map and state for the flight under way
    actions: list[Action] = field(default_factory=list)


_COMMANDING = (State.ENGAGED, State.DEGRADED, State.PAUSED, State.OVERRIDE)
_ENGAGED_BY_SWITCH = "engaged by the pilot's offboard switch: avoiding obstacles"


class Supervisor:
    """The service's state machine (see the module doc). Pure: every input is an argument.

    Args:
        cfg: the limits and timings.
        defer_histogram: the detour layer's histograms (tens of milliseconds with a full memory) are
            left to the caller: :attr:`StepOutput.histogram_request` asks for one, and its result comes
            back through :meth:`step`'s ``histogram`` (the service: off its control loop). False:
            computed at once, inside the step.
    """

    def __init__(self, cfg: SupervisorConfig, defer_histogram: bool = False) -> None:
        self._cfg = cfg
        self._m = _Memory(autostart_pending=cfg.autostart, course=CourseHold(defer_histogram))

    # ------------------------------------------------------------------------------------ queries

    @property
    def config(self) -> SupervisorConfig:
        return self._cfg

    @property
    def state(self) -> State:
        return self._m.state

    @property
    def reason(self) -> str:
        return self._m.reason

    @property
    def engaged(self) -> bool:
        """True while the service commands the vehicle in offboard (engaged, degraded, paused, override)."""
        return self._commanding()

    @property
    def streaming(self) -> bool:
        """True while setpoints are being handed to the link (and MAVSDK re-sends the last one)."""
        return self._m.streaming

    @property
    def owns_offboard(self) -> bool:
        return self._m.owns_offboard

    @property
    def finished(self) -> bool:
        """After :class:`Shutdown`: True once nothing is streamed and offboard is no longer ours."""
        m = self._m
        return m.shutting_down and not m.streaming and m.leaving is None and m.engaging is None

    def override_status(self, now_s: float) -> dict[str, float] | None:
        """The active override (yaw, pitch, speed fraction, seconds left), or None."""
        m = self._m
        if m.override is None or not self._commanding():
            return None
        return {
            "yaw": m.override.yaw,
            "pitch": m.override.pitch,
            "speed_fraction": m.override.speed_fraction,
            "remaining_s": max(0.0, m.override_until_s - now_s),
        }

    # ------------------------------------------------------------------------------------ update

    def goal_status(self, position_ned_m: object) -> dict[str, object]:
        """The goal for the health message (:meth:`~companion.core.course.CourseHold.goal_status`:
        kind, distance and bearing from ``position_ned_m``, reached, the detour layer's phase)."""
        return self._m.course.goal_status(position_ned_m)

    def planner_status(self) -> dict[str, object] | None:
        """The local planner's last tick for the health message
        (:meth:`~companion.core.planner.stack.LocalStack.status`); None when no local stack flies
        (the rule stack, or not engaged since start)."""
        return None if self._m.local is None else self._m.local.status()

    def memory_status(self) -> dict[str, float | int]:
        """The rule stack's obstacle memory for the health message (the local planner keeps its own
        map: all 0 then): ``points`` remembered (5 cm cubes),
        ``guarding``: how many (one per 45° sector) pushed the last engaged setpoint, ``seen_past``:
        how many the detour layer's map leaves out because the camera has seen past them
        (:meth:`~companion.core.memory.ObstacleMemory.see_through`), ``guard_cleared``: how many no
        longer guard either (seen past for ``memory.guard_clear_after_s`` in a row),
        ``unseen_drift_m_s``: the drift toward what the centre sees that the velocity estimate does
        not show, which the last setpoint countered (0: none; ``command.unseen_closing_range_m``),
        ``track_counter_m_s``: the motion of the reported position its reported velocity does not
        explain, which the last setpoint countered (0: none; ``command.track_counter_fraction``)."""
        return {
            "points": len(self._m.obstacles),
            "guarding": self._m.guarding,
            "seen_past": self._m.obstacles.seen_past_count(self._cfg.memory),
            "guard_cleared": self._m.obstacles.guard_cleared_count(self._cfg.memory),
            "unseen_drift_m_s": self._m.course.unseen_drift_m_s,
            "track_counter_m_s": self._m.course.track_counter_m_s,
        }

    def reconfigure(self, cfg: SupervisorConfig) -> None:
        """Swap the limits and timings; the state is kept (autostart is consumed only at start). A
        local planner in flight flies by the new settings from the next tick."""
        self._cfg = cfg
        if self._m.local is not None and cfg.local is not None:
            self._m.local.reconfigure(cfg.local)

    def step(
        self,
        now_s: float,
        latest: FrameOutcome | None,
        vehicle: VehicleState,
        requests: Sequence[Request] = (),
        camera_ok: bool = True,
        histogram: HistogramResult | None = None,
    ) -> StepOutput:
        """Advance to ``now_s`` and decide.

        Args:
            now_s: the shell's monotonic time, seconds (the clock of the frame timestamps).
            latest: the newest frame result (its ``timestamp_s`` is the capture time), or None.
            vehicle: the vehicle's latest state.
            requests: operator requests and action results received since the last step.
            camera_ok: False while the camera is gone (reconnecting): frames count as stale at once.
            histogram: the result of an earlier step's ``histogram_request`` (used only when it
                answers the detour layer's latest request; any other is dropped), or None.
        """
        m = self._m
        before = (m.state, m.reason)
        if histogram is not None:
            m.course.detour.offer(histogram)
        m.actions = []
        age_s = math.inf if latest is None else max(0.0, now_s - latest.timestamp_s)
        if not math.isfinite(age_s):
            age_s = math.inf
        fresh = camera_ok and age_s <= self._cfg.command.stale_frame_timeout_s
        if latest is None:
            m.course.observe(None, None, vehicle.position_ned_m)
        else:
            m.course.observe(latest.decision, latest.timestamp_s, vehicle.position_ned_m)

        for r in requests:
            if isinstance(r, ActionResult):
                self._on_action_result(now_s, r)
        self._observe_vehicle(now_s, vehicle)
        self._remember(now_s, latest, vehicle)
        replies = tuple(
            self._on_request(now_s, r, vehicle, fresh, age_s, camera_ok)
            for r in requests
            if not isinstance(r, ActionResult)
        )
        if m.autostart_pending and m.state is State.PASSIVE and not m.shutting_down:
            if self._engage_refusal(vehicle, fresh, age_s, camera_ok) is None:
                m.autostart_pending = False
                self._begin_engage(now_s, vehicle, "autostart")
        if self._cfg.engage_on_offboard_switch or m.ready:
            self._offboard_switch(now_s, vehicle, fresh, age_s, camera_ok)
        self._advance(now_s, vehicle, fresh, age_s, camera_ok)
        setpoint = self._output(now_s, latest, age_s, vehicle)
        return StepOutput(
            setpoint=setpoint,
            actions=tuple(m.actions),
            state=m.state,
            reason=m.reason,
            replies=replies,
            changed=(m.state, m.reason) != before,
            frame_age_s=age_s,
            histogram_request=m.course.detour.pending_request,
        )

    # ------------------------------------------------------------------------------------ internals

    def _remember(self, now_s: float, latest: FrameOutcome | None, v: VehicleState) -> None:
        """Keep the vehicle's recent poses, and put a new frame's near points in the obstacle memory
        from the pose nearest its capture time (none within :data:`_POSE_MATCH_S`: not put)."""
        m = self._m
        pose = _pose_of(v)
        if pose is not None:
            t = v.position_timestamp_s if v.position_timestamp_s is not None else now_s
            if not m.poses or t > m.poses[-1][0]:
                m.poses.append((float(t), pose))
        points = getattr(latest, "near_points_cam_m", None)
        blocks, geometry = getattr(latest, "near_blocks", None), getattr(latest, "geometry", None)
        if latest is None or (points is None and blocks is None) or latest.timestamp_s == m.last_frame_s:
            return
        m.last_frame_s = latest.timestamp_s
        m.view_limits = getattr(latest, "view_limits", None)
        if not m.poses:
            return
        t_seen, seen_from = min(m.poses, key=lambda tp: abs(tp[0] - latest.timestamp_s))
        if abs(t_seen - latest.timestamp_s) <= _POSE_MATCH_S:
            if self._cfg.memory.duration_s > 0.0 and points is not None and self._cfg.local is None:
                # The rule stack's memory (the local planner keeps its own map); with the viewpoint,
                # so that the memory can trust points seen from two places (detours).
                m.obstacles.add_frame(points, seen_from, latest.timestamp_s, self._cfg.memory, getattr(latest, "far_view", None))
            # The local planner's map takes every frame, whatever the obstacle memory's setting.
            if m.local is not None and blocks is not None and geometry is not None:
                m.local.add_frame(blocks, geometry, self._cfg.memory.block_px, seen_from, latest.timestamp_s)

    def _commanding(self) -> bool:
        m = self._m
        return m.owns_offboard and m.leaving is None and m.state in _COMMANDING

    def _set(self, state: State, reason: str) -> None:
        self._m.state = state
        self._m.reason = reason

    def _stop_stream(self) -> None:
        """Stop commanding: a final zero (see _output) and STOP_SETPOINTS; forget offboard."""
        m = self._m
        if m.streaming:
            m.actions.append(Action.STOP_SETPOINTS)
        m.streaming = False
        m.ready = False
        m.owns_offboard = False
        m.engaging = None
        m.leaving = None
        m.override = None

    def _on_action_result(self, now_s: float, r: ActionResult) -> None:
        m = self._m
        if r.action is not Action.START_OFFBOARD:
            return  # HOLD: retried from the vehicle's mode; STOP_SETPOINTS: nothing to follow up
        if m.engaging is not None:
            m.engaging.start_pending = False
            if not r.ok:
                self._stop_stream()
                self._set(State.DISENGAGED, f"offboard start refused: {r.message or 'no reason given'}")
        elif m.leaving is not None:
            m.leaving.start_pending = False
            if not r.ok:
                m.leaving.start_sent_s = None  # it will not take effect

    def _observe_vehicle(self, now_s: float, v: VehicleState) -> None:
        m = self._m
        if not v.connected:
            if m.streaming and (m.engaging is not None or m.owns_offboard or m.leaving is not None):
                # We cannot see the mode any more, so no mode change is sent blind: stop the stream so
                # that PX4's own offboard-loss failsafe acts if it is still in offboard.
                self._stop_stream()
                self._set(
                    State.FAILSAFE,
                    "vehicle link lost while commanding: setpoints stopped so that the autopilot's own failsafe acts",
                )
            return
        if m.owns_offboard and not v.in_offboard:
            if m.leaving is not None and m.leaving.holds > 0:
                what = m.leaving.what
                self._stop_stream()  # our Hold took (or the pilot moved at the same time): done
                self._set(m.state, f"{what}: left offboard (vehicle in {v.flight_mode})")
                return
            was = m.state.value
            self._stop_stream()
            self._set(
                State.DISENGAGED,
                f"vehicle left OFFBOARD for {v.flight_mode} while {was} (pilot or autopilot failsafe); "
                "not commanding, not re-engaging",
            )
            return
        e = m.engaging
        if e is not None:
            if not v.in_offboard and v.flight_mode != e.mode_at_request:
                # The pilot moved the switch while we were engaging: never fight it. (The link names
                # the offboard mode: PX4's OFFBOARD, ArduCopter's GUIDED.)
                self._stop_stream()
                self._set(State.DISENGAGED, f"pilot changed the mode to {v.flight_mode} during engage; not engaging")
            elif v.in_offboard and e.start_sent_s is not None:
                m.engaging = None
                m.owns_offboard = True
                m.activity = State.ENGAGED
                m.stalled = False
                # Course hold (when its gains are set) steers back to the heading, line and altitude of now.
                m.course.engage(v.position_ned_m, _finite_or_none(v.attitude_rad, 2), m.goal)
                self._engage_local(v, m.goal)
                self._set(State.ENGAGED, "engaged: avoiding obstacles")
        elif m.leaving is not None and v.in_offboard and m.leaving.start_sent_s is not None:
            m.owns_offboard = True  # the start we asked for took effect after all: ours to leave

    def _offboard_switch(self, now_s: float, v: VehicleState, fresh: bool, age_s: float, camera_ok: bool) -> None:
        """Engage from the sticks (``engage_on_offboard_switch``): while ready, stream zero so that the
        autopilot accepts a pilot's switch to offboard; when the vehicle then reports offboard, take it
        (every check of ``engage`` again); when no longer ready, stop the stream (zero first)."""
        m = self._m
        if m.engaging is not None or m.leaving is not None or m.owns_offboard:
            m.ready = False
            return
        idle = m.state in (State.PASSIVE, State.DISENGAGED) and not m.shutting_down
        refusal = self._engage_refusal(v, fresh, age_s, camera_ok, offboard_ok=True) if idle else "not idle"
        if not self._cfg.engage_on_offboard_switch:
            refusal = "engage_on_offboard_switch is off"
        if m.ready and v.in_offboard:
            if refusal is None:
                m.ready = False
                m.owns_offboard = True
                m.activity = State.ENGAGED
                m.stalled = False
                m.override = None
                m.by_switch = True
                m.course.engage(v.position_ned_m, _finite_or_none(v.attitude_rad, 2))
                self._engage_local(v, COURSE)
                self._set(State.ENGAGED, _ENGAGED_BY_SWITCH)
            else:
                # Switched while the service cannot fly: stop streaming so that the autopilot's own
                # offboard-loss failsafe gives the vehicle back.
                self._stop_stream()
                self._set(State.DISENGAGED, f"offboard switch refused: {refusal}; setpoints stopped")
            return
        if m.ready and refusal is not None:
            self._stop_stream()  # no longer ready: PX4 must refuse a switch to offboard now
            return
        if not m.ready and refusal is None and not v.in_offboard and Action.STOP_SETPOINTS not in m.actions:
            m.ready = True
            m.streaming = True

    @property
    def ready(self) -> bool:
        """True while zero setpoints stream so that a pilot's offboard switch engages (``engage_on_offboard_switch``)."""
        return self._m.ready

    def _engage_refusal(
        self, v: VehicleState, fresh: bool, age_s: float, camera_ok: bool, offboard_ok: bool = False
    ) -> str | None:
        """Why an engage is refused now (None: it is not); ``offboard_ok``: the vehicle may already be in
        offboard (a pilot's switch onto the stream the service offers while ready)."""
        m = self._m
        if m.shutting_down:
            return "the service is shutting down"
        if m.state in (State.ENGAGING, *_COMMANDING):
            return f"already {m.state.value}"
        if m.leaving is not None:
            return "still leaving offboard (waiting for Hold)"
        if not v.connected:
            return "no vehicle: the autopilot's heartbeat is not being received"
        if v.flight_mode == "UNKNOWN":
            return "the vehicle's flight mode is not known yet"
        if self._cfg.require_armed_to_engage and not v.armed:
            return "vehicle is disarmed (the service never arms it)"
        if v.in_offboard and not offboard_ok:
            return "vehicle is already in OFFBOARD under another controller; switch to a manual mode first"
        if not fresh:
            if not camera_ok:
                return "camera is not delivering frames"
            if math.isinf(age_s):
                return "no frame processed yet"
            return f"newest frame is {age_s:.2f} s old (> {self._cfg.command.stale_frame_timeout_s:g} s)"
        return None

    def _begin_engage(self, now_s: float, v: VehicleState, why: str) -> None:
        m = self._m
        m.engaging = _Engaging(since_s=now_s, mode_at_request=v.flight_mode)
        m.streaming = True
        m.ready = False
        m.by_switch = False
        m.owns_offboard = False
        m.override = None
        self._set(State.ENGAGING, f"{why}: streaming zero setpoints before requesting offboard")

    def _begin_leave(self, now_s: float, state: State, what: str) -> None:
        """Stop commanding because of ``what``; leave offboard to Hold if it is (or may become) ours."""
        m = self._m
        e = m.engaging
        m.override = None
        m.engaging = None
        if e is not None and e.start_sent_s is None:
            self._stop_stream()  # offboard was never requested: nothing to leave
            self._set(state, what)
            return
        if m.leaving is None:
            m.leaving = _Leaving(
                since_s=now_s,
                what=what,
                start_sent_s=e.start_sent_s if e is not None else None,
                start_pending=e.start_pending if e is not None else False,
            )
        else:
            m.leaving.what = what
        self._set(state, f"{what}: leaving offboard to Hold")

    def _on_request(
        self, now_s: float, r: Request, v: VehicleState, fresh: bool, age_s: float, camera_ok: bool
    ) -> Reply:
        m = self._m
        cfg = self._cfg
        if isinstance(r, Engage):
            refusal = self._engage_refusal(v, fresh, age_s, camera_ok)
            if refusal is not None:
                return Reply(r, False, f"engage refused: {refusal}")
            m.autostart_pending = False
            m.goal = r.goal
            self._begin_engage(now_s, v, "engage requested")
            return Reply(r, True, f"engaging, goal: {r.goal.describe()}")
        if isinstance(r, Goto):
            if not self._commanding():
                return Reply(r, False, f"goto refused: not engaged ({m.state.value}); engage with a goal instead")
            m.goal = r.goal
            heading = _finite_or_none(v.attitude_rad, 2)
            m.course.set_goal(r.goal, v.position_ned_m, heading)
            if m.local is not None and v.position_ned_m is not None and heading is not None:
                m.local.set_goal(np.asarray(v.position_ned_m, dtype=np.float64), heading, r.goal)
            if m.stalled:
                m.activity = State.ENGAGED  # a hold of the watchdog, a dead end or the goal: automatic again
                m.stalled = False
            return Reply(r, True, f"goal: {r.goal.describe()}")
        if isinstance(r, Disengage):
            if m.engaging is not None or self._commanding():
                self._begin_leave(now_s, State.DISENGAGED, "operator disengage")
                return Reply(r, True, "disengaging")
            if m.state is State.FAILSAFE:
                self._set(State.DISENGAGED, f"operator disengage after failsafe ({m.reason})")
                return Reply(r, True, "disengaged")
            m.autostart_pending = False
            return Reply(r, True, f"not engaged ({m.state.value})")
        if isinstance(r, Pause):
            if not self._commanding():
                return Reply(r, False, f"pause refused: not engaged ({m.state.value})")
            m.activity = State.PAUSED
            m.stalled = False
            m.override = None
            return Reply(r, True, "paused: zero velocity in offboard until resume")
        if isinstance(r, Resume):
            if not self._commanding():
                return Reply(r, False, f"resume refused: not engaged ({m.state.value})")
            was = m.activity
            m.activity = State.ENGAGED
            m.stalled = False
            m.override = None
            m.course.resume()  # forget a hold of the watchdog, a dead end or the goal reached: look again
            if m.local is not None:
                m.local.resume()
            return Reply(r, True, "automatic" if was is not State.ENGAGED else "already automatic")
        if isinstance(r, Override):
            if not self._commanding():
                return Reply(r, False, f"override refused: not engaged ({m.state.value})")
            if not fresh:
                return Reply(r, False, f"override refused: frames are stale ({age_s:.2f} s); the way ahead is unknown")
            values = (r.yaw, r.pitch, r.speed_fraction, r.duration_s)
            if not all(math.isfinite(x) for x in values):
                return Reply(r, False, "override refused: yaw, pitch, speed and duration_s must be finite")
            if not (-1.0 <= r.yaw <= 1.0 and -1.0 <= r.pitch <= 1.0 and 0.0 <= r.speed_fraction <= 1.0):
                return Reply(r, False, "override refused: yaw and pitch must be in [-1, 1], speed in [0, 1]")
            if not 0.0 < r.duration_s <= cfg.override_max_duration_s:
                return Reply(
                    r,
                    False,
                    f"override refused: duration_s {r.duration_s:g} must be in (0, "
                    f"{cfg.override_max_duration_s:g}] (service.override_max_duration_s)",
                )
            m.activity = State.OVERRIDE
            m.override = r
            m.override_until_s = now_s + r.duration_s
            return Reply(r, True, f"override for {r.duration_s:g} s")
        if isinstance(r, Shutdown):
            m.shutting_down = True
            m.autostart_pending = False
            if m.engaging is not None or self._commanding() or m.leaving is not None:
                self._begin_leave(now_s, State.DISENGAGED, "shutdown")
            elif m.streaming:
                self._stop_stream()
            return Reply(r, True, "shutting down")
        return Reply(r, False, f"unknown request {type(r).__name__}")

    def _advance(self, now_s: float, v: VehicleState, fresh: bool, age_s: float, camera_ok: bool) -> None:
        """Timers: prestream, engage timeout, staleness and failsafe, override expiry, leaving."""
        if self._m.engaging is not None:
            self._advance_engaging(now_s, v, fresh)
        if self._commanding():
            self._advance_commanding(now_s, v, fresh, age_s, camera_ok)
        if self._m.leaving is not None:
            self._advance_leaving(now_s, v)

    def _advance_engaging(self, now_s: float, v: VehicleState, fresh: bool) -> None:
        """Engaging: prestream, then request offboard; give up on stale frames or no confirmation."""
        cfg = self._cfg
        e = self._m.engaging
        if not fresh:
            self._begin_leave(now_s, State.DISENGAGED, "frames went stale during engage; not engaging")
        elif e.start_sent_s is None:
            if now_s - e.since_s >= cfg.offboard_prestream_s:
                e.start_sent_s = now_s
                e.start_pending = True
                self._m.actions.append(Action.START_OFFBOARD)
                self._set(State.ENGAGING, "offboard requested: waiting for the autopilot to confirm")
        elif now_s - e.start_sent_s > cfg.engage_timeout_s:
            self._begin_leave(
                now_s,
                State.DISENGAGED,
                f"offboard not confirmed within {cfg.engage_timeout_s:g} s (vehicle in {v.flight_mode}); not engaging",
            )

    def _advance_commanding(self, now_s: float, v: VehicleState, fresh: bool, age_s: float, camera_ok: bool) -> None:
        """In offboard and commanding: the failsafe, override expiry, staleness and the progress watchdog."""
        m = self._m
        cmd = self._cfg.command
        if age_s > cmd.failsafe_timeout_s:
            what = "no frame processed" if math.isinf(age_s) else f"newest frame {age_s:.1f} s old"
            self._begin_leave(now_s, State.FAILSAFE, f"{what} (> failsafe_timeout_s {cmd.failsafe_timeout_s:g} s)")
            return
        if m.activity is State.OVERRIDE and now_s >= m.override_until_s:
            m.activity = State.ENGAGED
            m.override = None
        if not fresh:
            m.course.progress.reset()
            why = (
                "camera lost (reconnecting)"
                if not camera_ok
                else f"frames stale (newest older than {cmd.stale_frame_timeout_s:g} s)"
            )
            self._set(State.DEGRADED, f"{why}: zero velocity")
            return
        if m.activity is State.ENGAGED and (self._holding_reason() is not None or self._no_progress(now_s, v)):
            m.activity = State.PAUSED  # the goal reached, a dead end, or the progress watchdog
            m.stalled = True
            # Before the reset below: it clears the watchdog's why (a regress would read as
            # "no progress for 20 s").
            m.stall_reason = self._stalled_reason()
            if m.local is not None and m.local.holding_reason is None:
                m.local.stop(m.stall_reason)  # the watchdog's hold: the local planner holds the point
        if m.activity is not State.ENGAGED:
            m.course.progress.reset()  # the watchdog times the automatic flight only
        if m.activity is State.PAUSED:
            reason = m.stall_reason if m.stalled else "paused by the operator: zero velocity in offboard"
            self._set(State.PAUSED, reason)
        elif m.activity is State.OVERRIDE:
            self._set(State.OVERRIDE, "manual override (automatic again when it expires)")
        else:
            self._set(State.ENGAGED, _ENGAGED_BY_SWITCH if m.by_switch else "engaged: avoiding obstacles")

    def _advance_leaving(self, now_s: float, v: VehicleState) -> None:
        """Leaving offboard: ask for Hold until confirmed; stop the setpoints when it never is."""
        m = self._m
        cfg = self._cfg
        lv = m.leaving
        if v.in_offboard:
            if lv.last_hold_s is None or now_s - lv.last_hold_s >= cfg.hold_retry_s:
                lv.last_hold_s = now_s
                lv.holds += 1
                m.owns_offboard = True
                m.actions.append(Action.HOLD)
        elif not m.owns_offboard:
            # Not in offboard and never confirmed in it: done once a pending start can no longer
            # take effect.
            start_may_land = lv.start_sent_s is not None and (
                lv.start_pending or now_s - lv.start_sent_s <= cfg.engage_timeout_s
            )
            if not start_may_land:
                self._stop_stream()
        if m.leaving is not None and now_s - lv.since_s > cfg.leave_timeout_s:
            self._stop_stream()
            self._set(
                m.state,
                f"{lv.what}: Hold not confirmed within {cfg.leave_timeout_s:g} s: setpoints stopped so "
                "that the autopilot's own failsafe acts",
            )

    def _output(
        self, now_s: float, latest: FrameOutcome | None, age_s: float, v: VehicleState
    ) -> VelocitySetpoint | None:
        m = self._m
        if Action.STOP_SETPOINTS in m.actions:
            return ZERO_SETPOINT  # the last value MAVSDK holds must be zero before it stops
        if not m.streaming:
            return None
        if m.engaging is not None or m.leaving is not None or not self._commanding():
            return ZERO_SETPOINT
        if m.state is State.ENGAGED and latest is not None:
            return self._engaged_setpoint(now_s, latest, age_s, v)
        if m.state is State.PAUSED and m.stalled and latest is not None:
            return self._engaged_setpoint(now_s, latest, age_s, v, hold=True)
        if m.state is State.OVERRIDE and m.override is not None:
            return self._override_setpoint(m.override, latest)
        return ZERO_SETPOINT  # degraded, paused

    def _no_progress(self, now_s: float, v: VehicleState) -> bool:
        """The progress watchdog (:class:`~companion.core.command.ProgressWatch`) fed the position now.
        Flying back is judged for the rule stack only: the local planner goes round by its own modes,
        and the way round can lead away from the goal for seconds (it stopped PX4 SITL flights that
        were turning along an office's wall); no progress holds either: for
        ``command.no_progress_timeout_s`` (the rule stack), for the time to fly
        ``planner.no_progress_distance_m`` at cruise (the local planner)."""
        planner = self._local_planner_cfg()
        return self._m.course.no_progress(
            v.position_ned_m, now_s, self._cfg.command, regress=self._m.local is None,
            timeout_s=None if planner is None else planner.no_progress_timeout_s,
        )

    def _local_planner_cfg(self) -> PlannerConfig | None:
        """The local planner's settings while it flies, else None (the rule stack)."""
        return self._cfg.local.planner if self._m.local is not None and self._cfg.local is not None else None

    def _holding_reason(self) -> str | None:
        """Why the flying stack holds (the goal reached, a dead end), or None: the local planner's
        when it flies (planner.kind "local"), else the course's."""
        m = self._m
        return m.local.holding_reason if m.local is not None else m.course.holding_reason

    def _stalled_reason(self) -> str:
        cmd = self._cfg.command
        if self._holding_reason() is not None:
            return self._holding_reason()  # the goal reached, or a dead end
        if self._m.course.progress.why == "regress":
            return (
                f"flying back: {cmd.regress_distance_m:g} m farther from the goal than the nearest it has been "
                f"for {cmd.regress_timeout_s:g} s (command.regress_distance_m, regress_timeout_s): "
                "holding position; resume to try again, or take over"
            )
        p = self._local_planner_cfg()
        if p is not None:
            return (
                f"no progress along the course for {p.no_progress_timeout_s:.0f} s (less than {cmd.progress_step_m:g} m "
                f"in the time to fly {p.no_progress_distance_m:g} m at {p.cruise_speed_m_s:g} m/s: "
                "planner.no_progress_distance_m, command.progress_step_m): holding position; resume to try again, or take over"
            )
        return (
            f"no progress along the course for {cmd.no_progress_timeout_s:g} s "
            f"(less than {cmd.progress_step_m:g} m: command.no_progress_timeout_s, progress_step_m): "
            "holding position; resume to try again, or take over"
        )

    def _engaged_setpoint(
        self, now_s: float, latest: FrameOutcome, age_s: float, v: VehicleState, hold: bool = False
    ) -> VelocitySetpoint:
        """The decision's setpoint, with course hold (inert unless its gains are set in ``command``);
        ``hold``: the progress watchdog's hold (:data:`~companion.core.command.NO_PROGRESS_HOLD`)
        instead of the decision."""
        m = self._m
        decision = NO_PROGRESS_HOLD if hold else latest.decision
        heading_now = _finite_or_none(v.attitude_rad, 2)
        refined = getattr(latest, "refined", None)
        if m.local is not None:
            # The local planner (planner.kind "local"): its safety chain ends the setpoint; holding, it
            # holds the point where the hold began (an autopilot told zero velocity creeps on: PX4's
            # velocity integrator, the position estimate's drift). Without a position, velocity and
            # heading there is no plan: zero velocity.
            if heading_now is None or v.position_ned_m is None or v.velocity_ned_m_s is None:
                return ZERO_SETPOINT
            step = m.local.step(
                now_s, age_s, latest.decision, getattr(refined, "depth_m", None),
                np.asarray(v.position_ned_m, dtype=np.float64), np.asarray(v.velocity_ned_m_s, dtype=np.float64), heading_now,
            )
            return step.setpoint
        guard = sides = gap = ahead = None
        if self._cfg.memory.duration_s > 0.0 and v.position_ned_m is not None and heading_now is not None:
            guard, sides, gap, ahead = m.obstacles.hold_inputs(
                v.position_ned_m, heading_now, now_s, self._cfg.memory, m.view_limits
            )
        m.guarding = 0 if guard is None else len(guard)
        return m.course.setpoint(
            decision,
            now_s,
            age_s,
            self._cfg.command,
            position_ned_m=v.position_ned_m,
            yaw_rad=heading_now,
            velocity_ned_m_s=v.velocity_ned_m_s,
            position_time_s=v.position_timestamp_s,
            region_depths_m=getattr(refined, "depth_m", None),
            guard_m=guard,
            remembered_sides=sides,
            gap=gap,
            path_ahead_m=ahead,
            memory_cfg=self._cfg.memory,
            obstacles=m.obstacles if self._cfg.memory.duration_s > 0.0 else None,
            detour_cfg=self._cfg.detour,
            prefer_right=self._cfg.prefer_right,
            planning=not hold,
        )

    def _engage_local(self, v: VehicleState, goal: GoalSpec) -> None:
        """A new local stack for the flight that begins (planner.kind "local"), from the pose now."""
        cfg = self._cfg.local
        heading = _finite_or_none(v.attitude_rad, 2)
        if cfg is None or v.position_ned_m is None or heading is None:
            self._m.local = None if cfg is None else self._m.local
            return
        self._m.local = LocalStack(cfg)
        self._m.local.engage(np.asarray(v.position_ned_m, dtype=np.float64), heading, goal)

    def _override_setpoint(self, o: Override, latest: FrameOutcome | None) -> VelocitySetpoint:
        cmd = self._cfg.command
        forward = cmd.cruise_speed_m_s * o.speed_fraction
        if self._cfg.override_respects_brake and (latest is None or latest.decision.kind is DecisionKind.BRAKE):
            forward = 0.0  # something near ahead: turning and climbing are allowed, going on is not
        return VelocitySetpoint(
            forward_m_s=forward,
            right_m_s=0.0,
            down_m_s=0.0 - o.pitch * cmd.max_vertical_speed_m_s,
            yaw_rate_deg_s=o.yaw * cmd.max_yaw_rate_deg_s,
        )


def _pose_of(v: VehicleState) -> Pose | None:
    """The vehicle's pose when its position and attitude are known and finite."""
    return Pose.from_telemetry(v.position_ned_m, v.attitude_rad)


def _finite_or_none(values: object, index: int) -> float | None:
    """``values[index]`` as a float when ``values`` is an array-like with a finite number there."""
    if values is None:
        return None
    try:
        x = float(values[index])  # type: ignore[index]
    except (TypeError, IndexError, ValueError):
        return None
    return x if math.isfinite(x) else None
