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
* **engaged**: the local stack's setpoint for the newest decision (:class:`~companion.core.flight.Flight`:
  the map, the planner and its safety chain). **paused**: zero velocity in offboard until ``resume``;
  or the planner's hold of the point where it stopped, until ``resume`` or ``goto``: a dead end, the
  goal reached, or the progress watchdog (:mod:`companion.core.progress`: engaged, the vehicle got no
  ``command.progress_step_m`` nearer its goal in the time to fly ``planner.no_progress_distance_m``
  at cruise). **override**: a manual yaw/pitch/speed for a bounded time, then *engaged* again.
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

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from companion.config import CompanionConfig
from companion.core.direct import override_refusal, override_setpoint
from companion.core.flight import Flight
from companion.core.goal import COURSE
from companion.core.supervisor_io import (
    Action,
    ActionResult,
    Disengage,
    Engage,
    FrameOutcome,
    Goto,
    Override,
    Pause,
    Reply,
    Request,
    Resume,
    Shutdown,
    State,
    StepOutput,
    SupervisorConfig,
)
from companion.core.supervisor_state import Engaging, Leaving, Memory
from companion.core.types import ZERO_SETPOINT, VelocitySetpoint

if TYPE_CHECKING:
    from companion.interfaces import VehicleState

_COMMANDING = (State.ENGAGED, State.DEGRADED, State.PAUSED, State.OVERRIDE)
_ENGAGED_BY_SWITCH = "engaged by the pilot's offboard switch: avoiding obstacles"


class Supervisor:
    """The service's state machine (see the module doc). Pure: every input is an argument.

    Args:
        cfg: the limits and timings.
    """

    def __init__(self, cfg: SupervisorConfig) -> None:
        self._cfg = cfg
        self._m = Memory(autostart_pending=cfg.autostart)
        self._flight = Flight(cfg.flight if cfg.flight is not None else CompanionConfig())

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
        """The goal for the health message (:meth:`~companion.core.flight.Flight.goal_status`: kind,
        distance and bearing from ``position_ned_m``, reached)."""
        return self._flight.goal_status(position_ned_m)

    def planner_status(self) -> dict[str, object] | None:
        """The local planner's last tick for the health message
        (:meth:`~companion.core.planner.stack.LocalStack.status`); None before a flight has started."""
        return self._flight.planner_status()

    def reconfigure(self, cfg: SupervisorConfig) -> None:
        """Swap the limits and timings; the state is kept (autostart is consumed only at start). A
        flight under way flies by the new settings from the next tick."""
        self._cfg = cfg
        self._flight.reconfigure(cfg.flight if cfg.flight is not None else CompanionConfig())

    def step(
        self,
        now_s: float,
        latest: FrameOutcome | None,
        vehicle: VehicleState,
        requests: Sequence[Request] = (),
        camera_ok: bool = True,
    ) -> StepOutput:
        """Advance to ``now_s`` and decide.

        Args:
            now_s: the shell's monotonic time, seconds (the clock of the frame timestamps).
            latest: the newest frame result (its ``timestamp_s`` is the capture time), or None.
            vehicle: the vehicle's latest state.
            requests: operator requests and action results received since the last step.
            camera_ok: False while the camera is gone (reconnecting): frames count as stale at once.
        """
        m = self._m
        before = (m.state, m.reason)
        m.actions = []
        age_s = math.inf if latest is None else max(0.0, now_s - latest.timestamp_s)
        if not math.isfinite(age_s):
            age_s = math.inf
        fresh = camera_ok and age_s <= self._cfg.command.stale_frame_timeout_s

        for r in requests:
            if isinstance(r, ActionResult):
                self._on_action_result(now_s, r)
        self._observe_vehicle(now_s, vehicle)
        self._flight.remember(now_s, latest, vehicle)
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
        )

    # ------------------------------------------------------------------------------------ internals

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
                self._flight.engage(v, m.goal)
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
                self._flight.engage(v, COURSE)
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
        m.engaging = Engaging(since_s=now_s, mode_at_request=v.flight_mode)
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
            m.leaving = Leaving(
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
            self._flight.set_goal(v, r.goal)
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
            self._flight.resume()  # forget a hold of the watchdog, a dead end or the goal reached: look again
            return Reply(r, True, "automatic" if was is not State.ENGAGED else "already automatic")
        if isinstance(r, Override):
            if not self._commanding():
                return Reply(r, False, f"override refused: not engaged ({m.state.value})")
            refusal = override_refusal(r, fresh, age_s, cfg.override_max_duration_s)
            if refusal is not None:
                return Reply(r, False, f"override refused: {refusal}")
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
            self._flight.reset_watchdog()
            why = (
                "camera lost (reconnecting)"
                if not camera_ok
                else f"frames stale (newest older than {cmd.stale_frame_timeout_s:g} s)"
            )
            self._set(State.DEGRADED, f"{why}: zero velocity")
            return
        flight = self._flight
        if m.activity is State.ENGAGED and (flight.holding_reason is not None or flight.no_progress(now_s, v)):
            m.activity = State.PAUSED  # the goal reached, a dead end, or the progress watchdog
            m.stalled = True
            m.stall_reason = flight.holding_reason or flight.watchdog_reason()
            flight.stop(m.stall_reason)  # the watchdog's hold: the planner holds the point
        if m.activity is not State.ENGAGED:
            flight.reset_watchdog()  # the watchdog times the automatic flight only
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
        if latest is not None and (m.state is State.ENGAGED or (m.state is State.PAUSED and m.stalled)):
            return self._flight.setpoint(now_s, latest, age_s, v)  # paused by a hold: the planner holds the point
        if m.state is State.OVERRIDE and m.override is not None:
            return override_setpoint(m.override, latest, self._flight.cfg, self._cfg.override_respects_brake)
        return ZERO_SETPOINT  # degraded, paused by the operator
