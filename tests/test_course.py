"""CourseHold: the course-hold bookkeeping the supervisor and the simulator share (one clock)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.core.course import CourseHold
from companion.core.types import Decision, DecisionKind

CMD = CompanionConfig().command  # heading hold on (0.8 /s), hold_resume_delay_s 1.5
CLEAR = Decision(kind=DecisionKind.CLEAR, yaw=0.0, pitch=0.0, speed_fraction=1.0, reason="centre clear")
TURN = Decision(kind=DecisionKind.AVOID, yaw=0.6, pitch=0.0, speed_fraction=0.5, reason="R5")
BRAKE = Decision(kind=DecisionKind.BRAKE, yaw=0.0, pitch=0.0, speed_fraction=0.0, reason="no escape")
ORIGIN = np.array([0.0, 0.0, -1.5])


def _engaged() -> CourseHold:
    hold = CourseHold()
    hold.engage(ORIGIN, 0.0)  # course: north from the origin, 1.5 m up
    return hold


def _yaw_rate(hold: CourseHold, decision: Decision, now_s: float, yaw_rad: float = -0.3) -> float:
    """The setpoint's yaw rate with the vehicle on the line, facing 0.3 rad left of the course."""
    sp = hold.setpoint(decision, now_s, 0.05, CMD, position_ned_m=ORIGIN.copy(), yaw_rad=yaw_rad)
    return sp.yaw_rate_deg_s


def test_the_hold_waits_from_the_capture_time_of_the_first_clear_frame() -> None:
    hold = _engaged()
    hold.observe(CLEAR, 10.0, ORIGIN)  # frame captured at 10.0 s
    hold.observe(CLEAR, 10.1, ORIGIN)  # the same stretch of CLEAR: the timer keeps its start
    assert _yaw_rate(hold, CLEAR, 10.0 + CMD.hold_resume_delay_s - 0.01) == 0.0
    assert _yaw_rate(hold, CLEAR, 10.0 + CMD.hold_resume_delay_s + 0.01) > 0.0  # back to the right


def test_a_turning_decision_restarts_the_wait() -> None:
    hold = _engaged()
    hold.observe(CLEAR, 10.0, ORIGIN)
    hold.observe(TURN, 11.0, ORIGIN)
    hold.observe(CLEAR, 11.2, ORIGIN)
    assert _yaw_rate(hold, CLEAR, 12.0) == 0.0  # 0.8 s since 11.2: still waiting
    assert _yaw_rate(hold, CLEAR, 11.2 + CMD.hold_resume_delay_s + 0.01) > 0.0


def test_without_a_decision_nothing_is_held_and_the_wait_restarts() -> None:
    hold = _engaged()
    hold.observe(CLEAR, 10.0, ORIGIN)
    hold.observe(None, None, ORIGIN)
    sp = hold.setpoint(None, 20.0, math.inf, CMD, position_ned_m=ORIGIN.copy(), yaw_rad=-0.3)
    assert sp.yaw_rate_deg_s == 0.0 and sp.forward_m_s == 0.0
    hold.observe(CLEAR, 21.0, ORIGIN)
    assert _yaw_rate(hold, CLEAR, 21.5) == 0.0


def test_engage_keeps_the_clear_timer_and_forgets_the_brake_and_the_progress_clock() -> None:
    hold = CourseHold()
    hold.observe(CLEAR, 10.0, ORIGIN)  # clear before engagement
    hold.brake.offset_body(BRAKE, ORIGIN, 0.0)
    assert hold.brake.at_ned_m is not None
    assert not hold.no_progress(ORIGIN, 0.0, CMD)  # no course yet: the watchdog cannot judge
    hold.engage(ORIGIN, 0.0)
    assert hold.brake.at_ned_m is None and hold.progress.mark_m is None
    assert _yaw_rate(hold, CLEAR, 12.0) > 0.0  # clear since 10.0: holds at once


def test_unknown_heading_or_position_leaves_that_hold_off() -> None:
    hold = CourseHold()
    hold.engage(np.array([np.nan, 0.0, -1.5]), None)
    assert hold.origin_ned_m is None and hold.heading_rad is None and hold.altitude_m is None
    hold.observe(CLEAR, 0.0, ORIGIN)
    sp = hold.setpoint(CLEAR, 5.0, 0.05, CMD, position_ned_m=np.array([0.0, 2.0, -1.0]), yaw_rad=-0.3)
    assert sp.yaw_rate_deg_s == 0.0 and sp.right_m_s == 0.0 and sp.down_m_s == 0.0


def test_the_progress_watchdog_fires_after_no_progress_along_the_course() -> None:
    hold = _engaged()
    assert not hold.no_progress(ORIGIN, 0.0, CMD)
    beside = ORIGIN + np.array([0.5, 3.0, 0.0])  # 3 m sideways, 0.5 m along: no progress
    assert not hold.no_progress(beside, CMD.no_progress_timeout_s - 0.1, CMD)
    assert hold.no_progress(beside, CMD.no_progress_timeout_s + 0.1, CMD)
    ahead = ORIGIN + np.array([CMD.progress_step_m + 0.1, 0.0, 0.0])
    assert not hold.no_progress(ahead, CMD.no_progress_timeout_s + 0.2, CMD)  # progress restarts the clock


def test_a_brake_holds_where_it_began() -> None:
    hold = _engaged()
    hold.observe(BRAKE, 1.0, ORIGIN)
    hold.setpoint(BRAKE, 1.0, 0.05, CMD, position_ned_m=ORIGIN.copy(), yaw_rad=0.0)  # latches here
    sp = hold.setpoint(BRAKE, 1.5, 0.05, CMD, position_ned_m=ORIGIN + np.array([0.4, 0.0, 0.0]), yaw_rad=0.0)
    assert sp.forward_m_s < 0.0  # drifted 0.4 m forward: flies back


def test_no_setpoint_descends_through_the_floor_whatever_asks_for_it() -> None:
    """PX4 SITL office-2: the up regions unknown (plain sky over the office), the controller ducked,
    and the vehicle flew into the floor. Every setpoint's descent is capped near the floor."""
    from companion.core.command import FLOOR_GAIN_PER_S

    duck = Decision(DecisionKind.AVOID, 0.0, -1.0, 0.3, "up near: duck")  # descend at the most
    full = CMD.max_vertical_speed_m_s

    def down(altitude_m: float, cmd=CMD) -> float:
        hold = CourseHold()
        hold.engage(np.array([0.0, 0.0, -1.5]), 0.0)
        return hold.setpoint(duck, 1.0, 0.05, cmd, position_ned_m=np.array([0.0, 0.0, -altitude_m]), yaw_rad=0.0).down_m_s

    assert CMD.min_altitude_m == 0.5
    assert down(2.0) == pytest.approx(full)  # well above it: the controller's own descent
    assert down(0.6) == pytest.approx(FLOOR_GAIN_PER_S * 0.1)
    assert down(0.5) == 0.0 and down(0.3) == 0.0
    off = CMD.model_copy(update={"min_altitude_m": 0.0})
    assert down(0.3, off) == pytest.approx(full)
    # A climb is never held back, and an unknown altitude leaves the setpoint as it was.
    climb = Decision(DecisionKind.AVOID, 0.0, 1.0, 0.3, "down near: climb")
    hold = CourseHold()
    hold.engage(np.array([0.0, 0.0, -1.5]), 0.0)
    assert hold.setpoint(climb, 1.0, 0.05, CMD, position_ned_m=np.array([0.0, 0.0, -0.3]), yaw_rad=0.0).down_m_s < 0.0
    assert CourseHold().setpoint(duck, 1.0, 0.05, CMD, position_ned_m=None, yaw_rad=0.0).down_m_s == pytest.approx(full)


def test_the_floor_reckons_with_a_sink_the_autopilot_is_still_carrying() -> None:
    """PX4 follows a velocity setpoint with a lag (command.motion_brake_lag_s): a descent of 0.46 m/s
    stopped by the floor alone still sank on through it. The floor counts the measured sink over that
    lag as height already lost: the same setpoint descends slower the faster the vehicle sinks, and a
    sink that would carry it through the floor is met with a climb."""
    from companion.core.command import FLOOR_GAIN_PER_S

    duck = Decision(DecisionKind.AVOID, 0.0, -1.0, 0.3, "up near: duck")
    lag = CMD.motion_brake_lag_s

    def down(altitude_m: float, sink_m_s: float | None) -> float:
        hold = _engaged()
        velocity = None if sink_m_s is None else np.array([0.0, 0.0, sink_m_s])
        return hold.setpoint(duck, 1.0, 0.05, CMD, position_ned_m=np.array([0.0, 0.0, -altitude_m]), yaw_rad=0.0,
                             velocity_ned_m_s=velocity, region_depths_m=np.full(9, 5.0)).down_m_s

    assert down(0.8, None) == pytest.approx(FLOOR_GAIN_PER_S * 0.3)
    assert down(0.8, 0.1) == pytest.approx(FLOOR_GAIN_PER_S * (0.3 - 0.1 * lag))
    assert down(0.8, -0.3) == pytest.approx(FLOOR_GAIN_PER_S * 0.3)  # a climb is no sink
    assert down(0.8, 0.5) < 0.0  # 0.5 m/s for 0.85 s would take it 0.13 m under: climb
    assert down(3.0, 0.5) == pytest.approx(CMD.max_vertical_speed_m_s)  # high up: the controller's own descent


def test_below_the_floor_a_fresh_setpoint_climbs_back_and_a_stale_one_stays_zero() -> None:
    """PX4 in offboard velocity control holds a vertical speed, not a height: with 0.1 m/s of vertical
    drift the kinematic suite flew 4 vehicles into the ground under setpoints that asked for no
    descent. Below the floor, a fresh decision's setpoint climbs back unless the up region reads
    nearer than FLOOR_CLIMB_UP_CLEAR_M; an unknown up region does not stop it (PX4 SITL r15's
    office-2 sank into the ground in front of a plain wall whose up region read unknown). A stale
    frame still gets zero velocity."""
    from companion.core.command import FLOOR_CLIMB_UP_CLEAR_M, FLOOR_GAIN_PER_S
    from companion.core.types import REGION_INDEX

    open_up = np.full(9, 5.0)
    low = np.array([0.0, 0.0, -0.35])  # 0.15 m under the 0.5 m floor

    def sp(decision: Decision, age_s: float = 0.05, depths: np.ndarray | None = open_up):
        hold = _engaged()
        return hold.setpoint(decision, 1.0, age_s, CMD, position_ned_m=low, yaw_rad=0.0, region_depths_m=depths)

    climb = min(CMD.max_altitude_hold_speed_m_s, FLOOR_GAIN_PER_S * 0.15)
    for decision in (CLEAR, TURN, BRAKE):
        assert sp(decision).down_m_s == pytest.approx(-climb), decision.reason
    near_up = open_up.copy()
    near_up[REGION_INDEX["up"]] = 0.5 * FLOOR_CLIMB_UP_CLEAR_M
    unknown_up = open_up.copy()
    unknown_up[REGION_INDEX["up"]] = np.nan
    assert sp(CLEAR, depths=near_up).down_m_s <= 0.0 and sp(CLEAR, depths=near_up).down_m_s > -climb
    assert sp(TURN, depths=unknown_up).down_m_s == pytest.approx(-climb)  # the ground is measured; the up region looks ahead
    assert sp(TURN, depths=None).down_m_s == 0.0  # no regions at all: no climb, no descent
    stale = sp(CLEAR, age_s=CMD.stale_frame_timeout_s + 0.1)
    assert (stale.forward_m_s, stale.right_m_s, stale.down_m_s, stale.yaw_rate_deg_s) == (0.0, 0.0, 0.0, 0.0)
    off = CMD.model_copy(update={"min_altitude_m": 0.0})
    assert _engaged().setpoint(TURN, 1.0, 0.05, off, position_ned_m=low, yaw_rad=0.0, region_depths_m=open_up).down_m_s == 0.0


def test_every_setpoint_keeps_clear_of_what_is_remembered_below() -> None:
    """PX4 SITL pitch-4: over a low wall it had climbed, the vehicle braked, PX4 sagged 0.3 m with every
    setpoint's vertical speed 0, and it touched the wall's top, which the camera no longer saw. Within
    memory.clearance_below_m of a remembered point below, every setpoint climbs back (the up region
    open), whatever drove it; the ground's points (below the floor's altitude) do not count."""
    from companion.core.command import BELOW_CLIMB_GAIN_PER_S
    from companion.core.memory import ObstacleMemory

    assert CompanionConfig().memory.clearance_below_m == 0.0  # off by default (its description says why)
    mem_cfg = CompanionConfig().memory.model_copy(update={"clearance_below_m": 0.6})
    up_open = np.full(9, 10.0)

    def down(gap_m: float, *, regions=up_open, decision=CLEAR, mem_cfg=mem_cfg, top_altitude_m=1.62,
             horizontal_m: float = 0.2) -> float:
        mem = ObstacleMemory()
        top = np.array([[0.0, horizontal_m, -top_altitude_m], [0.1, horizontal_m, -top_altitude_m]])
        mem.add(top, 0.0, mem_cfg.duration_s, ranges_m=np.full(2, 1.0), viewpoint_ned_m=np.array([-1.0, 0.0, -2.0]),
                cfg=mem_cfg)
        hold = CourseHold()
        here = np.array([0.0, 0.0, -(top_altitude_m + gap_m)])
        hold.engage(here, 0.0)  # engaged here: the altitude hold has nothing to add
        return hold.setpoint(decision, 1.0, 0.05, CMD, position_ned_m=here, yaw_rad=0.0, region_depths_m=regions,
                             memory_cfg=mem_cfg, obstacles=mem).down_m_s

    assert down(0.5) == pytest.approx(-BELOW_CLIMB_GAIN_PER_S * 0.1)  # 0.1 m short: climbs 0.2 m/s
    assert down(0.3) == pytest.approx(-CMD.max_altitude_hold_speed_m_s)  # at most the hold's speed
    assert down(0.7) >= 0.0  # clear by more than 0.6 m: no climb
    assert down(0.3, horizontal_m=0.5) >= 0.0  # beside the vehicle (a wall), not under it
    assert down(0.3, mem_cfg=mem_cfg.model_copy(update={"clearance_below_m": 0.0})) >= 0.0  # off
    up_near = up_open.copy()
    up_near[1] = 0.5
    assert down(0.3, regions=up_near) >= 0.0  # no climb into what the up region sees
    # A braking or ducking decision climbs back all the same; a faster climb is kept.
    assert down(0.3, decision=BRAKE) == pytest.approx(-CMD.max_altitude_hold_speed_m_s)
    climb = Decision(DecisionKind.AVOID, 0.0, 1.0, 0.3, "down near: climb")
    assert down(0.3, decision=climb) < -CMD.max_altitude_hold_speed_m_s
    # The ground is not an obstacle below: points 0.2 m over the take-off point lie below the 0.5 m floor.
    assert down(0.4, top_altitude_m=0.2) >= 0.0
