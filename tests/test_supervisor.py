"""The service's state machine, exhaustively, without asyncio: time, frames and the vehicle are arguments.

The frames show open space (a wall 30 m away across the whole view) and the vehicle hovers at 1.5 m
facing north, so that the local stack the supervisor flies has space seen free to fly into."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import CompanionConfig
from companion.core.geometry import StereoGeometry
from companion.core.supervisor import (
    Action,
    ActionResult,
    Disengage,
    Engage,
    Override,
    Pause,
    Resume,
    Shutdown,
    State,
    StepOutput,
    Supervisor,
    SupervisorConfig,
)
from companion.core.types import ZERO_SETPOINT, Decision, DecisionKind
from companion.interfaces import VehicleState

CLEAR = Decision(DecisionKind.CLEAR, yaw=0.0, pitch=0.0, speed_fraction=1.0, reason="clear")
AVOID = Decision(DecisionKind.AVOID, yaw=-0.5, pitch=0.25, speed_fraction=0.5, reason="avoid")
BRAKE = Decision(DecisionKind.BRAKE, yaw=0.0, pitch=0.0, speed_fraction=0.0, reason="brake")


GEOM = StereoGeometry.ideal(336, 188, 90.0, 0.12)
#: The block image (4 px blocks) of a wall 30 m away across the whole view: open space ahead.
OPEN = np.full((47, 84), GEOM.focal_baseline_px_m / 30.0, dtype=np.float32)


@dataclass(frozen=True)
class Result:
    """The parts of a frame result the supervisor reads."""

    timestamp_s: float
    decision: Decision
    near_blocks: np.ndarray = field(default_factory=lambda: OPEN)
    geometry: StereoGeometry = GEOM


def vehicle(mode: str = "POSCTL", *, connected: bool = True, armed: bool = True) -> VehicleState:
    """A vehicle hovering at 1.5 m at the origin, facing north, in ``mode``."""
    return VehicleState(
        connected=connected, armed=armed, flight_mode=mode, in_offboard=mode == "OFFBOARD",
        position_ned_m=np.array([0.0, 0.0, -1.5]), velocity_ned_m_s=np.zeros(3), attitude_rad=np.zeros(3),
    )


def default_config(**overrides) -> SupervisorConfig:
    cfg = SupervisorConfig.from_config(CompanionConfig())
    return replace(cfg, **overrides)


class Harness:
    """Drives a Supervisor at 20 Hz with fresh frames and a PX4-like vehicle unless told otherwise."""

    def __init__(self, cfg: SupervisorConfig | None = None) -> None:
        self.cfg = cfg or default_config()
        self.sup = Supervisor(self.cfg)
        self.now = 100.0
        self.frame: Result | None = Result(self.now, CLEAR)
        self.vehicle = vehicle()
        self.camera_ok = True
        self.outputs: list[StepOutput] = []

    def step(self, *requests, dt: float = 0.05, fresh_frame: bool = True) -> StepOutput:
        self.now += dt
        if fresh_frame and self.frame is not None:
            self.frame = Result(self.now - 0.02, self.frame.decision)
        out = self.sup.step(self.now, self.frame, self.vehicle, requests, camera_ok=self.camera_ok)
        self.outputs.append(out)
        return out

    def run(self, seconds: float, **kw) -> list[StepOutput]:
        n = int(round(seconds / 0.05))
        return [self.step(**kw) for _ in range(n)]

    def actions(self) -> list[Action]:
        return [a for o in self.outputs for a in o.actions]

    def engage(self) -> None:
        """Engage fully: request, prestream, offboard start acked, vehicle in OFFBOARD."""
        out = self.step(Engage())
        assert out.replies[0].ok, out.replies[0].message
        for _ in range(40):
            out = self.step()
            if Action.START_OFFBOARD in out.actions:
                break
        else:
            raise AssertionError("no START_OFFBOARD")
        self.vehicle = vehicle("OFFBOARD")
        out = self.step(ActionResult(Action.START_OFFBOARD, True))
        assert out.state is State.ENGAGED, out.reason
        # A few frames into the new flight's map: space seen free ahead, flown into.
        assert self.run(0.3)[-1].setpoint.forward_m_s > 0.0


# ---------------------------------------------------------------------------------------------- passive


def test_starts_passive_and_sends_nothing() -> None:
    h = Harness()
    outs = h.run(2.0)
    assert all(o.state is State.PASSIVE and o.setpoint is None and not o.actions for o in outs)
    assert not h.sup.engaged


def test_passive_never_engages_by_itself_even_when_everything_is_ready() -> None:
    h = Harness()
    h.vehicle = vehicle("POSCTL")
    outs = h.run(10.0)
    assert {o.state for o in outs} == {State.PASSIVE}
    assert not h.actions()


@pytest.mark.parametrize(
    ("setup", "expected"),
    [
        (lambda h: setattr(h, "vehicle", vehicle(connected=False)), "no vehicle"),
        (lambda h: setattr(h, "vehicle", vehicle(armed=False)), "disarmed"),
        (lambda h: setattr(h, "vehicle", vehicle("OFFBOARD")), "already in OFFBOARD"),
        (lambda h: setattr(h, "vehicle", vehicle("UNKNOWN")), "flight mode is not known"),
        (lambda h: setattr(h, "frame", None), "no frame processed yet"),
        (lambda h: setattr(h, "camera_ok", False), "camera is not delivering"),
    ],
)
def test_engage_refusals_say_why(setup, expected: str) -> None:
    h = Harness()
    setup(h)
    out = h.step(Engage())
    assert not out.replies[0].ok
    assert expected in out.replies[0].message
    assert out.state is State.PASSIVE and out.setpoint is None and not out.actions


def test_engage_refused_on_a_stale_frame() -> None:
    h = Harness()
    h.frame = Result(h.now - 0.7, CLEAR)
    out = h.step(Engage(), fresh_frame=False)
    assert not out.replies[0].ok and "old" in out.replies[0].message


def test_disarmed_engage_allowed_when_not_required() -> None:
    h = Harness(default_config(require_armed_to_engage=False))
    h.vehicle = vehicle(armed=False)
    assert h.step(Engage()).replies[0].ok


# ---------------------------------------------------------------------------------------------- engage


def test_engage_streams_zero_before_offboard_start_then_commands() -> None:
    h = Harness()
    out = h.step(Engage())
    assert out.state is State.ENGAGING and out.setpoint == ZERO_SETPOINT and not out.actions
    prestream = h.run(h.cfg.offboard_prestream_s - 0.1)
    assert all(o.setpoint == ZERO_SETPOINT and not o.actions for o in prestream)
    outs = h.run(0.2)
    starts = [o for o in outs if Action.START_OFFBOARD in o.actions]
    assert len(starts) == 1 and starts[0].setpoint == ZERO_SETPOINT
    # Waiting for the autopilot: still zero, no second start.
    outs = h.run(1.0)
    assert all(o.state is State.ENGAGING and o.setpoint == ZERO_SETPOINT for o in outs)
    assert h.actions().count(Action.START_OFFBOARD) == 1
    h.vehicle = vehicle("OFFBOARD")
    out = h.step(ActionResult(Action.START_OFFBOARD, True))
    assert out.state is State.ENGAGED and out.changed and h.sup.engaged
    assert out.setpoint is not None
    out = h.run(0.3)[-1]
    assert out.state is State.ENGAGED and out.setpoint.forward_m_s > 0.0  # the local stack's setpoint


def test_engaged_flies_the_local_stack_and_a_brake_stops_it() -> None:
    h = Harness()
    h.engage()
    out = h.step()
    assert 0.0 < out.setpoint.forward_m_s <= CompanionConfig().planner.cruise_speed_m_s
    status = h.sup.planner_status()
    assert status is not None and status["mode"] == "cruise", status
    h.frame = Result(h.now, BRAKE)
    out = h.step()
    assert out.state is State.ENGAGED and out.setpoint.forward_m_s <= 0.0
    assert "brake_hold" in h.sup.planner_status()["limited_by"]


def test_without_a_position_the_engaged_vehicle_is_told_zero_until_one_is_known() -> None:
    """No plan without a position, a velocity and a heading: zero velocity; the flight starts from the
    pose once it is known."""
    h = Harness()
    h.vehicle = replace(vehicle(), position_ned_m=None)
    h.step(Engage())
    h.run(0.6)
    h.vehicle = replace(vehicle("OFFBOARD"), position_ned_m=None)
    out = h.step(ActionResult(Action.START_OFFBOARD, True))
    assert out.state is State.ENGAGED
    assert all(o.setpoint == ZERO_SETPOINT for o in h.run(0.5))
    assert h.sup.planner_status() is None
    h.vehicle = vehicle("OFFBOARD")
    assert h.run(0.5)[-1].setpoint.forward_m_s > 0.0


def test_engaged_streams_every_step() -> None:
    h = Harness()
    h.engage()
    outs = h.run(3.0)
    assert all(o.setpoint is not None for o in outs)
    assert not any(o.actions for o in outs)


def test_offboard_start_refused_disengages_and_stops_the_stream() -> None:
    h = Harness()
    h.step(Engage())
    h.run(0.6)
    out = h.step(ActionResult(Action.START_OFFBOARD, False, "denied"))
    assert out.state is State.DISENGAGED and "refused: denied" in out.reason
    assert out.actions == (Action.STOP_SETPOINTS,) and out.setpoint == ZERO_SETPOINT
    assert all(o.setpoint is None for o in h.run(1.0))
    assert Action.HOLD not in h.actions()


def test_offboard_not_confirmed_times_out_without_a_mode_change() -> None:
    h = Harness()
    h.step(Engage())
    h.run(0.6)
    h.step(ActionResult(Action.START_OFFBOARD, True))  # acked, but the heartbeat never says OFFBOARD
    outs = h.run(h.cfg.engage_timeout_s + 0.5)
    assert outs[-1].state is State.DISENGAGED and "not confirmed" in outs[-1].reason
    assert Action.STOP_SETPOINTS in h.actions() and Action.HOLD not in h.actions()
    assert outs[-1].setpoint is None


def test_pilot_mode_change_during_engage_aborts_without_a_mode_change() -> None:
    h = Harness()
    h.step(Engage())
    h.run(0.2)
    h.vehicle = vehicle("ALTCTL")
    out = h.step()
    assert out.state is State.DISENGAGED and "pilot changed the mode to ALTCTL" in out.reason
    assert out.actions == (Action.STOP_SETPOINTS,)
    assert Action.START_OFFBOARD not in h.actions()


def test_frames_stale_during_engage_abort_it() -> None:
    h = Harness()
    h.step(Engage())
    out = h.run(0.7, fresh_frame=False)[-1]
    assert out.state is State.DISENGAGED and "stale during engage" in out.reason


def test_engage_while_engaged_is_refused_and_changes_nothing() -> None:
    h = Harness()
    h.engage()
    out = h.step(Engage())
    assert not out.replies[0].ok and "already engaged" in out.replies[0].message
    assert out.state is State.ENGAGED


def test_late_offboard_after_an_abandoned_engage_is_left_to_hold() -> None:
    h = Harness()
    h.step(Engage())
    h.run(0.6)
    h.run(h.cfg.engage_timeout_s + 0.1)  # start pending, never confirmed
    assert h.sup.state is State.DISENGAGED
    # The autopilot switches after all: it is our request, so we leave to Hold.
    h.vehicle = vehicle("OFFBOARD")
    out = h.step()
    assert Action.HOLD in out.actions and out.setpoint == ZERO_SETPOINT
    h.vehicle = vehicle("HOLD")
    out = h.step(ActionResult(Action.HOLD, True))
    assert out.actions == (Action.STOP_SETPOINTS,)
    assert h.step().setpoint is None


# ---------------------------------------------------------------------------------------------- stale / failsafe


def test_stale_frames_give_zero_within_the_timeout_with_the_defaults() -> None:
    h = Harness()
    assert h.cfg.command.stale_frame_timeout_s == 0.5 and h.cfg.command.failsafe_timeout_s == 5.0
    h.engage()
    last_frame_s = h.frame.timestamp_s
    outs = h.run(0.8, fresh_frame=False)
    for o in outs:
        age = o.frame_age_s
        if age > 0.5:
            assert o.setpoint == ZERO_SETPOINT and o.state is State.DEGRADED, age
        else:
            assert o.setpoint.forward_m_s > 0 and o.state is State.ENGAGED
    assert outs[-1].frame_age_s == pytest.approx(h.now - last_frame_s)
    assert not any(o.actions for o in outs)


def test_fresh_frames_after_degraded_resume_engaged() -> None:
    h = Harness()
    h.engage()
    h.run(1.0, fresh_frame=False)
    assert h.sup.state is State.DEGRADED
    out = h.step()
    assert out.state is State.ENGAGED and out.setpoint.forward_m_s > 0


def test_camera_lost_gives_zero_at_once() -> None:
    h = Harness()
    h.engage()
    h.camera_ok = False
    out = h.step()
    assert out.state is State.DEGRADED and out.setpoint == ZERO_SETPOINT and "camera lost" in out.reason


def test_failsafe_after_five_seconds_holds_once_then_stops_the_stream() -> None:
    h = Harness()
    h.engage()
    t_last = h.frame.timestamp_s
    outs = h.run(6.0, fresh_frame=False)
    holds = [o for o in outs if Action.HOLD in o.actions]
    assert len(holds) == 1
    assert holds[0].frame_age_s > 5.0 and holds[0].frame_age_s < 5.0 + 0.051
    assert holds[0].state is State.FAILSAFE and holds[0].setpoint == ZERO_SETPOINT
    before = [o for o in outs if o.frame_age_s <= 5.0]
    assert all(o.state is not State.FAILSAFE for o in before)
    # Still reported OFFBOARD for a heartbeat: zero keeps flowing, no second Hold before hold_retry_s.
    assert all(o.setpoint == ZERO_SETPOINT for o in outs if o.frame_age_s > 5.0)
    h.vehicle = vehicle("HOLD")
    out = h.step(ActionResult(Action.HOLD, True), fresh_frame=False)
    assert out.actions == (Action.STOP_SETPOINTS,) and out.state is State.FAILSAFE
    assert "left offboard (vehicle in HOLD)" in out.reason
    assert h.now - t_last > 5.0


def test_failsafe_never_reengages_when_frames_return() -> None:
    h = Harness()
    h.engage()
    h.run(5.2, fresh_frame=False)
    h.vehicle = vehicle("HOLD")
    h.run(0.2, fresh_frame=False)
    outs = h.run(5.0)  # frames are back
    assert all(o.state is State.FAILSAFE and o.setpoint is None and not o.actions for o in outs)
    # An explicit engage leaves it.
    assert h.step(Engage()).replies[0].ok


def test_hold_is_retried_while_the_vehicle_stays_in_offboard() -> None:
    h = Harness()
    h.engage()
    h.run(5.1, fresh_frame=False)
    outs = h.run(h.cfg.hold_retry_s * 2 + 0.1, fresh_frame=False)
    assert h.actions().count(Action.HOLD) == 3
    assert all(o.setpoint == ZERO_SETPOINT for o in outs)


def test_hold_never_confirmed_stops_the_stream_for_px4s_failsafe() -> None:
    h = Harness()
    h.engage()
    h.run(5.1, fresh_frame=False)
    outs = h.run(h.cfg.leave_timeout_s + 0.2, fresh_frame=False)
    assert Action.STOP_SETPOINTS in h.actions()
    assert outs[-1].setpoint is None and "the autopilot's own failsafe" in outs[-1].reason


def test_vehicle_link_lost_stops_the_stream_without_a_mode_change() -> None:
    h = Harness()
    h.engage()
    h.vehicle = replace(h.vehicle, connected=False)
    out = h.step()
    assert out.state is State.FAILSAFE and out.actions == (Action.STOP_SETPOINTS,)
    assert out.setpoint == ZERO_SETPOINT and "link lost" in out.reason
    h.vehicle = vehicle("OFFBOARD")  # it comes back, still in offboard: no blind Hold, no stream
    outs = h.run(1.0)
    assert all(o.setpoint is None and not o.actions for o in outs)


# ---------------------------------------------------------------------------------------------- pilot


@pytest.mark.parametrize("activity", ["engaged", "degraded", "paused", "override"])
@pytest.mark.parametrize("new_mode", ["POSCTL", "ALTCTL", "HOLD", "RETURN_TO_LAUNCH", "LAND", "MANUAL"])
def test_pilot_leaving_offboard_disengages_and_is_never_fought(activity: str, new_mode: str) -> None:
    h = Harness()
    h.engage()
    if activity == "degraded":
        h.run(1.0, fresh_frame=False)
    elif activity == "paused":
        h.step(Pause())
    elif activity == "override":
        h.step(Override(0.5, 0.0, 0.5, 5.0))
    assert h.sup.state.value == activity
    h.vehicle = vehicle(new_mode)
    out = h.step()
    assert out.state is State.DISENGAGED and f"left OFFBOARD for {new_mode}" in out.reason
    assert out.actions == (Action.STOP_SETPOINTS,) and out.setpoint == ZERO_SETPOINT
    # Then: nothing at all, whatever happens: no mode change, no setpoint, no re-engage.
    outs = h.run(3.0)
    outs += h.run(6.0, fresh_frame=False)
    h.vehicle = vehicle("OFFBOARD")  # even if someone else switches back to offboard
    outs += h.run(2.0)
    assert all(o.setpoint is None and not o.actions for o in outs)
    assert all(o.state is State.DISENGAGED for o in outs)
    assert Action.HOLD not in h.actions()
    assert not h.sup.engaged


def test_autostart_engages_once_and_never_again() -> None:
    h = Harness(default_config(autostart=True))
    h.vehicle = vehicle(connected=False)
    assert all(o.state is State.PASSIVE for o in h.run(1.0))  # waits for the vehicle
    h.vehicle = vehicle()
    assert h.step().state is State.ENGAGING
    h.run(0.6)
    h.vehicle = vehicle("OFFBOARD")
    assert h.step().state is State.ENGAGED
    h.vehicle = vehicle("POSCTL")
    assert h.step().state is State.DISENGAGED
    assert all(o.state is State.DISENGAGED for o in h.run(3.0))


def test_autostart_is_consumed_by_a_refused_start() -> None:
    h = Harness(default_config(autostart=True))
    h.step()
    h.run(0.6)
    h.step(ActionResult(Action.START_OFFBOARD, False, "denied"))
    assert all(o.state is State.DISENGAGED and not o.actions for o in h.run(3.0))


# ---------------------------------------------------------------------------------------------- operator


def test_operator_disengage_leaves_to_hold_then_stops() -> None:
    h = Harness()
    h.engage()
    out = h.step(Disengage())
    assert out.replies[0].ok and out.state is State.DISENGAGED
    assert out.actions == (Action.HOLD,) and out.setpoint == ZERO_SETPOINT
    assert "operator disengage: leaving offboard to Hold" in out.reason
    out = h.step()
    assert out.setpoint == ZERO_SETPOINT and not out.actions  # zero until the vehicle reports Hold
    h.vehicle = vehicle("HOLD")
    out = h.step(ActionResult(Action.HOLD, True))
    assert out.actions == (Action.STOP_SETPOINTS,)
    assert all(o.setpoint is None for o in h.run(1.0))
    assert h.step(Engage()).replies[0].ok  # explicit re-engage is fine


def test_disengage_during_prestream_needs_no_hold() -> None:
    h = Harness()
    h.step(Engage())
    out = h.step(Disengage())
    assert out.actions == (Action.STOP_SETPOINTS,) and out.state is State.DISENGAGED


def test_disengage_while_passive_is_ok_and_harmless() -> None:
    h = Harness()
    out = h.step(Disengage())
    assert out.replies[0].ok and out.state is State.PASSIVE and out.setpoint is None


def test_pause_and_resume() -> None:
    h = Harness()
    assert not h.step(Pause()).replies[0].ok
    h.engage()
    out = h.step(Pause())
    assert out.replies[0].ok and out.state is State.PAUSED and out.setpoint == ZERO_SETPOINT
    assert all(o.setpoint == ZERO_SETPOINT and o.state is State.PAUSED for o in h.run(2.0))
    out = h.step(Resume())
    assert out.replies[0].ok and out.state is State.ENGAGED and out.setpoint.forward_m_s > 0


def test_override_flies_the_manual_values_then_expires_to_automatic() -> None:
    h = Harness()
    h.engage()
    out = h.step(Override(yaw=0.5, pitch=-0.5, speed_fraction=0.25, duration_s=1.0))
    assert out.replies[0].ok and out.state is State.OVERRIDE
    p, env = CompanionConfig().planner, CompanionConfig().envelope
    assert out.setpoint.forward_m_s == pytest.approx(0.25 * p.cruise_speed_m_s)
    assert out.setpoint.yaw_rate_deg_s == pytest.approx(0.5 * min(p.max_yaw_rate_deg_s, env.max_yaw_rate_deg_s))
    assert out.setpoint.down_m_s == pytest.approx(0.5 * min(p.max_vertical_speed_m_s, env.max_vertical_speed_m_s))
    remaining = h.sup.override_status(h.now)["remaining_s"]
    assert remaining == pytest.approx(1.0)
    outs = h.run(1.1)
    assert outs[-1].state is State.ENGAGED and outs[-1].setpoint.forward_m_s > 0.0  # the local stack again
    assert h.sup.override_status(h.now) is None


def test_override_respects_brake() -> None:
    h = Harness()
    h.engage()
    h.frame = Result(h.now, BRAKE)
    out = h.step(Override(yaw=1.0, pitch=0.0, speed_fraction=1.0, duration_s=2.0))
    assert out.setpoint.forward_m_s == 0.0 and out.setpoint.yaw_rate_deg_s > 0
    h2 = Harness(default_config(override_respects_brake=False))
    h2.engage()
    h2.frame = Result(h2.now, BRAKE)
    assert h2.step(Override(1.0, 0.0, 1.0, 2.0)).setpoint.forward_m_s == pytest.approx(CompanionConfig().planner.cruise_speed_m_s)


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        (Override(0.0, 0.0, 0.5, 10.5), "override_max_duration_s"),
        (Override(0.0, 0.0, 0.5, 0.0), "duration_s"),
        (Override(1.5, 0.0, 0.5, 1.0), "[-1, 1]"),
        (Override(0.0, -1.1, 0.5, 1.0), "[-1, 1]"),
        (Override(0.0, 0.0, 1.5, 1.0), "[0, 1]"),
        (Override(math.nan, 0.0, 0.5, 1.0), "finite"),
        (Override(0.0, 0.0, 0.5, math.inf), "finite"),
    ],
)
def test_override_bounds(override: Override, expected: str) -> None:
    h = Harness()
    h.engage()
    out = h.step(override)
    assert not out.replies[0].ok and expected in out.replies[0].message
    assert out.state is State.ENGAGED


def test_override_refused_when_not_engaged_or_stale() -> None:
    h = Harness()
    assert "not engaged" in h.step(Override(0, 0, 0.5, 1)).replies[0].message
    h.engage()
    h.run(0.7, fresh_frame=False)
    assert "stale" in h.step(Override(0, 0, 0.5, 1), fresh_frame=False).replies[0].message


def test_override_during_stale_frames_gives_zero() -> None:
    h = Harness()
    h.engage()
    h.step(Override(0.5, 0.0, 1.0, 5.0))
    outs = h.run(1.0, fresh_frame=False)
    assert outs[-1].state is State.DEGRADED and outs[-1].setpoint == ZERO_SETPOINT


def test_resume_cancels_an_override() -> None:
    h = Harness()
    h.engage()
    h.step(Override(0.5, 0.0, 1.0, 5.0))
    out = h.step(Resume())
    assert out.state is State.ENGAGED and out.setpoint.yaw_rate_deg_s == 0.0


def test_override_duration_bound_follows_reconfigure() -> None:
    h = Harness()
    h.engage()
    h.sup.reconfigure(default_config(override_max_duration_s=30.0))
    assert h.step(Override(0.0, 0.0, 0.5, 20.0)).replies[0].ok


# ---------------------------------------------------------------------------------------------- shutdown


def test_shutdown_when_engaged_zero_then_hold_then_stop() -> None:
    h = Harness()
    h.engage()
    out = h.step(Shutdown())
    assert out.setpoint == ZERO_SETPOINT and out.actions == (Action.HOLD,)
    assert not h.sup.finished
    h.vehicle = vehicle("HOLD")
    out = h.step()
    assert out.actions == (Action.STOP_SETPOINTS,) and h.sup.finished
    assert not h.step(Engage()).replies[0].ok


def test_shutdown_when_passive_is_immediate_and_sends_nothing() -> None:
    h = Harness()
    out = h.step(Shutdown())
    assert out.setpoint is None and not out.actions and h.sup.finished


def test_shutdown_after_the_pilot_took_over_sends_no_mode_change() -> None:
    h = Harness()
    h.engage()
    h.vehicle = vehicle("POSCTL")
    h.step()
    out = h.step(Shutdown())
    assert not out.actions and h.sup.finished
    assert Action.HOLD not in h.actions()


# ---------------------------------------------------------------------------------------------- invariants


_REQUESTS = st.sampled_from(
    [
        None,
        Engage(),
        Disengage(),
        Pause(),
        Resume(),
        Override(0.3, -0.2, 0.5, 2.0),
        ActionResult(Action.START_OFFBOARD, True),
        ActionResult(Action.START_OFFBOARD, False, "denied"),
        ActionResult(Action.HOLD, True),
    ]
)
_MODES = st.sampled_from(["POSCTL", "OFFBOARD", "HOLD", "ALTCTL", "LAND"])


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            _REQUESTS,
            _MODES,
            st.booleans(),  # connected
            st.sampled_from([0.0, 0.1, 0.6, 3.0, 6.0]),  # frame age
            st.booleans(),  # camera ok
            st.sampled_from([CLEAR, AVOID, BRAKE]),
        ),
        min_size=1,
        max_size=60,
    )
)
def test_invariants_under_random_sequences(seq) -> None:
    """Whatever happens: never a non-zero setpoint on a stale/braking frame, Hold only while the
    vehicle reports OFFBOARD and we took it there, and no setpoint at all after the pilot took over."""
    sup = Supervisor(default_config())
    now = 0.0
    prev_mode = "POSCTL"
    owned = False
    for req, mode, connected, age, cam_ok, decision in seq:
        now += 0.05
        v = VehicleState(connected=connected, armed=True, flight_mode=mode, in_offboard=mode == "OFFBOARD")
        frame = Result(now - age, decision)
        requests = () if req is None else (req,)
        owned_before = sup.owns_offboard
        out = sup.step(now, frame, v, requests, camera_ok=cam_ok)
        sp = out.setpoint
        if sp is not None and not sp.is_zero:
            assert age <= 0.5 and cam_ok and connected and mode == "OFFBOARD"
            assert out.state in (State.ENGAGED, State.OVERRIDE)
            if out.state is State.ENGAGED:
                assert decision.kind is not DecisionKind.BRAKE
        if Action.HOLD in out.actions:
            assert connected and mode == "OFFBOARD"
        if Action.STOP_SETPOINTS in out.actions:
            assert sp is not None and sp.is_zero
        if owned_before and connected and mode != "OFFBOARD" and Action.HOLD not in out.actions:
            # Left offboard: this step stops (or has stopped) commanding.
            assert not sup.engaged
        assert isinstance(out.reason, str) and out.reason
        owned = sup.owns_offboard
        prev_mode = mode
    assert prev_mode in ("POSCTL", "OFFBOARD", "HOLD", "ALTCTL", "LAND") and owned in (True, False)


# ------------------------------------------------------------------------------------ progress watchdog


def _engaged_at(position_ned_m, *, cfg: SupervisorConfig | None = None) -> Harness:
    """A harness engaged with the defaults at ``position_ned_m``, facing north (the course: north)."""
    h = Harness(cfg)
    h.vehicle = replace(vehicle(), position_ned_m=np.array(position_ned_m, dtype=float))
    h.step(Engage())
    h.run(0.6)
    h.vehicle = replace(h.vehicle, flight_mode="OFFBOARD", in_offboard=True)
    assert h.step().state is State.ENGAGED
    return h


def test_no_progress_pauses_with_a_position_hold_and_resume_goes_on() -> None:
    cfg = CompanionConfig()
    timeout_s = cfg.planner.no_progress_timeout_s
    assert timeout_s == 20.0 and cfg.command.progress_step_m == 1.0  # 60 m at 3 m/s
    h = _engaged_at([0.0, 0.0, -1.5])
    # Circling in front of something: 0.8 m along the course at most, for the whole timeout.
    for k in range(int(timeout_s / 0.05) - 2):
        a = k * 0.05
        h.vehicle = replace(h.vehicle, position_ned_m=np.array([0.4 + 0.4 * math.cos(a), 0.4 * math.sin(a), -1.5]))
        assert h.step().state is State.ENGAGED
    outs = h.run(0.2)
    stalled = outs[-1]
    assert stalled.state is State.PAUSED and "no progress along the course for 20 s" in stalled.reason
    assert "resume" in stalled.reason
    assert h.sup.planner_status()["mode"] == "hold"
    # The planner holds the point where it stopped: pushed on 0.2 m, it is told back.
    where = h.vehicle.position_ned_m.copy()
    h.vehicle = replace(h.vehicle, position_ned_m=where + np.array([0.2, 0.0, 0.0]))
    assert h.step().setpoint.forward_m_s < 0.0
    assert all(o.state is State.PAUSED and o.setpoint.forward_m_s <= 0.0 for o in h.run(30.0))
    out = h.step(Resume())
    assert out.replies[0].ok and out.state is State.ENGAGED
    assert h.run(0.3)[-1].setpoint.forward_m_s > 0.0
    # The clock starts again at resume: another full timeout before the next pause.
    assert all(o.state is State.ENGAGED for o in h.run(timeout_s - 1.5))


def test_progress_keeps_the_flight_going() -> None:
    h = _engaged_at([0.0, 0.0, -1.5])
    # 1.1 m along the course every 15 s: slow, but progress.
    for k in range(int(60.0 / 0.05)):
        h.vehicle = replace(h.vehicle, position_ned_m=np.array([1.1 * (k * 0.05 // 15.0), 3.0, -1.5]))
        assert h.step().state is State.ENGAGED


def test_flying_away_from_the_goal_is_no_stall_by_itself() -> None:
    """The planner's way round can lead away from the goal for seconds: only no progress holds."""
    h = _engaged_at([0.0, 0.0, -1.5])
    for k in range(200):  # 10 s flying south, away from the course ahead
        h.vehicle = replace(h.vehicle, position_ned_m=np.array([-0.05 * k, 0.0, -1.5]))
        assert h.step().state is State.ENGAGED


def test_no_progress_watchdog_off_with_a_zero_distance() -> None:
    cfg = SupervisorConfig.from_config(CompanionConfig.model_validate({"planner": {"no_progress_distance_m": 0.0}}))
    h = _engaged_at([0.0, 0.0, -1.5], cfg=cfg)
    assert all(o.state is State.ENGAGED for o in h.run(30.0))


def test_no_progress_clock_waits_while_paused_stale_or_overridden() -> None:
    h = _engaged_at([0.0, 0.0, -1.5])
    h.run(15.0)
    h.step(Pause())
    h.run(30.0)
    assert h.step(Resume()).state is State.ENGAGED
    assert all(o.state is State.ENGAGED for o in h.run(15.0))  # 15 s since resume, not 60
    h.run(4.0, fresh_frame=False)  # stale: degraded, the clock restarts when frames return
    assert all(o.state is State.ENGAGED for o in h.run(15.0))
    h.step(Override(0.0, 0.0, 0.5, 4.0))
    h.run(4.1)  # overridden: not the automatic flight, the clock restarts after it
    assert all(o.state is State.ENGAGED for o in h.run(15.0))
    assert h.run(6.0)[-1].state is State.PAUSED
    # An operator's pause replaces the watchdog's: zero velocity, the operator's reason.
    out = h.step(Pause())
    assert out.state is State.PAUSED and out.reason.startswith("paused by the operator") and out.setpoint == ZERO_SETPOINT


def test_goto_gives_a_new_goal_and_ends_a_hold() -> None:
    from companion.core.goal import GoalSpec
    from companion.core.supervisor import Goto

    h = Harness()
    assert not h.step(Goto(GoalSpec(kind="point", north_m=5.0, east_m=0.0))).replies[0].ok  # not engaged
    h = _engaged_at([0.0, 0.0, -1.5])
    h.run(20.5)
    assert h.sup.state is State.PAUSED
    out = h.step(Goto(GoalSpec(kind="point", north_m=10.0, east_m=2.0)))
    assert out.replies[0].ok and out.state is State.ENGAGED
    goal = h.sup.goal_status(h.vehicle.position_ned_m)
    assert goal["kind"] == "point" and goal["north_m"] == 10.0 and goal["distance_m"] == pytest.approx(math.hypot(10.0, 2.0))
    assert goal["reached"] is False


# ---------------------------------------------------------------------------------------------- engage from the sticks


def _sticks() -> Harness:
    return Harness(default_config(engage_on_offboard_switch=True))


def test_offboard_switch_off_by_default_streams_nothing_while_passive() -> None:
    h = Harness()
    assert all(o.setpoint is None for o in h.run(1.0)) and not h.sup.ready


def test_ready_streams_zero_and_a_pilots_switch_engages_with_no_mode_command() -> None:
    h = _sticks()
    outs = h.run(1.0)
    assert all(o.setpoint == ZERO_SETPOINT and o.state is State.PASSIVE for o in outs)
    assert h.sup.ready and h.sup.streaming and not h.actions()
    h.vehicle = vehicle("OFFBOARD")  # the pilot's RC switch (or QGC) onto the zero stream
    out = h.step()
    assert out.state is State.ENGAGED and "offboard switch" in out.reason and h.sup.engaged
    assert out.setpoint is not None  # the local stack's setpoint at once
    assert not h.actions()  # no START_OFFBOARD: the pilot did it
    # Switching away gives it back at once: zero, stream stopped, no mode command ...
    h.vehicle = vehicle("POSCTL")
    out = h.step()
    assert out.state is State.DISENGAGED and out.setpoint == ZERO_SETPOINT
    assert out.actions == (Action.STOP_SETPOINTS,)
    # ... and ready again on the next step, so the switch works again.
    out = h.step()
    assert out.setpoint == ZERO_SETPOINT and h.sup.ready and not out.actions
    h.vehicle = vehicle("OFFBOARD")
    assert h.step().state is State.ENGAGED
    assert Action.START_OFFBOARD not in h.actions() and Action.HOLD not in h.actions()


@pytest.mark.parametrize(
    "spoil",
    [
        lambda h: setattr(h, "vehicle", vehicle(armed=False)),
        lambda h: setattr(h, "camera_ok", False),
        lambda h: setattr(h, "vehicle", vehicle(connected=False)),
    ],
)
def test_not_ready_stops_the_stream_so_the_autopilot_refuses_offboard(spoil) -> None:
    h = _sticks()
    h.run(0.5)
    assert h.sup.ready
    spoil(h)
    out = h.step()
    assert out.setpoint == ZERO_SETPOINT and out.actions == (Action.STOP_SETPOINTS,) and not h.sup.ready
    assert all(o.setpoint is None for o in h.run(0.5))


def test_stale_frames_stop_the_ready_stream_too() -> None:
    h = _sticks()
    h.run(0.5)
    outs = h.run(1.0, fresh_frame=False)
    assert Action.STOP_SETPOINTS in [a for o in outs for a in o.actions] and not h.sup.ready
    assert outs[-1].setpoint is None


def test_a_switch_that_finds_the_service_not_ready_is_refused_and_not_flown() -> None:
    h = _sticks()
    h.run(0.5)
    h.camera_ok = False
    h.vehicle = vehicle("OFFBOARD")  # the same step: the switch and the camera loss
    out = h.step()
    assert out.state is State.DISENGAGED and "offboard switch refused" in out.reason
    assert out.setpoint == ZERO_SETPOINT and out.actions == (Action.STOP_SETPOINTS,)
    assert not h.sup.engaged


def test_no_ready_stream_after_a_failsafe_until_an_explicit_engage() -> None:
    h = _sticks()
    h.engage()
    h.run(6.0, fresh_frame=False)  # failsafe: Hold
    h.vehicle = vehicle("HOLD")
    h.run(0.5)
    assert h.sup.state is State.FAILSAFE and not h.sup.ready
    assert all(o.setpoint is None for o in h.run(1.0))
