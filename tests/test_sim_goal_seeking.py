"""Course hold in setpoint_for (goal seeking): off by default, back toward the course only when CLEAR,
after the resume delay, toward a side that is seen to be free."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config.core import CommandConfig
from companion.core.command import ProgressWatch, along_course_m, is_heading_clear, is_straight_clear, setpoint_for
from companion.core.types import REGION_INDEX, Decision, DecisionKind

HOLD = CommandConfig(heading_hold_gain_per_s=1.0, max_heading_hold_rate_deg_s=20.0, altitude_hold_gain_per_s=0.5,
                     max_altitude_hold_speed_m_s=0.3, hold_resume_delay_s=1.0, hold_clear_depth_m=2.0)
CLEAR = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "centre clear")
FREE = np.full(9, 10.0)


def _depths(**regions: float) -> np.ndarray:
    d = FREE.copy()
    for k, v in regions.items():
        d[REGION_INDEX[k]] = v
    return d


def test_without_the_inputs_it_is_the_papers_setpoint() -> None:
    for cmd in (CommandConfig(), HOLD):
        for d in (CLEAR, Decision(DecisionKind.AVOID, 0.4, -0.2, 0.5, "x")):
            assert setpoint_for(d, 0.1, cmd) == setpoint_for(
                d, 0.1, cmd, heading_error_rad=None, altitude_error_m=None, region_depths_m=None, clear_for_s=None
            )
    # The paper-faithful profile has zero gains: errors change nothing.
    paper = CommandConfig(heading_hold_gain_per_s=0.0, altitude_hold_gain_per_s=0.0)
    assert setpoint_for(CLEAR, 0.1, paper, heading_error_rad=1.0, altitude_error_m=1.0) == setpoint_for(CLEAR, 0.1, paper)


def test_heading_hold_turns_back_toward_the_course_with_the_right_sign_and_limit() -> None:
    sp = setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=math.radians(10.0), clear_for_s=5.0)
    assert sp.yaw_rate_deg_s == pytest.approx(10.0)  # gain 1/s: 10 deg error -> 10 deg/s, to the right
    sp = setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=-math.radians(90.0), clear_for_s=5.0)
    assert sp.yaw_rate_deg_s == pytest.approx(-20.0)  # clipped, to the left
    # The error is wrapped: 350 deg to the right is 10 deg to the left.
    sp = setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=math.radians(350.0), clear_for_s=5.0)
    assert sp.yaw_rate_deg_s == pytest.approx(-10.0)
    assert sp.forward_m_s == HOLD.cruise_speed_m_s


def test_altitude_hold_climbs_when_low_and_descends_when_high() -> None:
    assert setpoint_for(CLEAR, 0.1, HOLD, altitude_error_m=0.2, clear_for_s=5.0).down_m_s == pytest.approx(-0.1)
    assert setpoint_for(CLEAR, 0.1, HOLD, altitude_error_m=-2.0, clear_for_s=5.0).down_m_s == pytest.approx(0.3)


def test_hold_waits_for_clear_straight_decisions_and_the_resume_delay() -> None:
    kw = {"heading_error_rad": 0.3, "altitude_error_m": -0.5}  # a descent waits; a climb back does not (below)
    assert setpoint_for(CLEAR, 0.1, HOLD, clear_for_s=0.5, **kw) == setpoint_for(CLEAR, 0.1, HOLD)
    for kind in (DecisionKind.AVOID, DecisionKind.BRAKE):
        d = Decision(kind, 0.3 if kind is DecisionKind.AVOID else 0.0, 0.0, 0.5, "x")
        assert setpoint_for(d, 0.1, HOLD, clear_for_s=5.0, **kw) == setpoint_for(d, 0.1, HOLD)
    # Stale frames: zero, whatever the course says.
    assert setpoint_for(CLEAR, 1.0, HOLD, clear_for_s=5.0, **kw).is_zero


def test_hold_never_steers_toward_a_side_it_sees_blocked_or_unknown() -> None:
    right = math.radians(15.0)
    assert setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=right, region_depths_m=_depths(right=1.0),
                        clear_for_s=5.0).yaw_rate_deg_s == 0.0
    assert setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=right, region_depths_m=_depths(right=math.nan),
                        clear_for_s=5.0).yaw_rate_deg_s == 0.0
    # The other side being blocked does not matter.
    assert setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=right, region_depths_m=_depths(left=0.3),
                        clear_for_s=5.0).yaw_rate_deg_s == pytest.approx(15.0)
    # Climbing needs 'up' free, descending 'down' free.
    assert setpoint_for(CLEAR, 0.1, HOLD, altitude_error_m=0.4, region_depths_m=_depths(up=1.0),
                        clear_for_s=5.0).down_m_s == 0.0
    assert setpoint_for(CLEAR, 0.1, HOLD, altitude_error_m=-0.4, region_depths_m=_depths(down=1.0),
                        clear_for_s=5.0).down_m_s == 0.0
    assert setpoint_for(CLEAR, 0.1, HOLD, altitude_error_m=-0.4, region_depths_m=_depths(up=1.0),
                        clear_for_s=5.0).down_m_s == pytest.approx(0.2)


def test_straight_clear_is_what_the_resume_timer_counts() -> None:
    assert is_straight_clear(CLEAR)
    assert not is_straight_clear(None)
    assert not is_straight_clear(Decision(DecisionKind.CLEAR, 0.2, 0.0, 1.0, "side rule"))
    assert not is_straight_clear(Decision(DecisionKind.AVOID, 0.0, 0.0, 0.5, "x"))


BRAKE = Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "wall ahead")


def test_brake_position_hold_flies_back_to_where_the_brake_began() -> None:
    cmd = CommandConfig(brake_hold_gain_per_s=1.0, brake_hold_max_speed_m_s=0.3)
    assert setpoint_for(BRAKE, 0.1, cmd).is_zero  # no position: plain zero velocity
    sp = setpoint_for(BRAKE, 0.1, cmd, brake_offset_body_m=np.array([0.2, -0.1, 0.05]))
    assert (sp.forward_m_s, sp.right_m_s, sp.down_m_s, sp.yaw_rate_deg_s) == pytest.approx((-0.2, 0.1, -0.05, 0.0))
    far = setpoint_for(BRAKE, 0.1, cmd, brake_offset_body_m=np.array([2.0, 0.0, 0.0]))
    assert far.forward_m_s == pytest.approx(-0.3)  # clipped
    assert setpoint_for(BRAKE, 0.6, cmd, brake_offset_body_m=np.array([0.2, 0.0, 0.0])).is_zero  # stale: zero
    assert setpoint_for(BRAKE, 0.1, cmd, brake_offset_body_m=np.array([np.nan, 0.0, 0.0])).is_zero
    off = CommandConfig(brake_hold_gain_per_s=0.0)
    assert setpoint_for(BRAKE, 0.1, off, brake_offset_body_m=np.array([0.2, 0.0, 0.0])).is_zero


def test_brake_offset_is_in_the_body_frame() -> None:
    from companion.core.command import brake_offset_body

    # Heading east: 0.3 m further east is 0.3 m forward; 0.1 m south is 0.1 m to the right.
    off = brake_offset_body(np.array([9.9, 5.3, -1.5]), np.array([10.0, 5.0, -1.5]), math.pi / 2)
    np.testing.assert_allclose(off, (0.3, 0.1, 0.0), atol=1e-12)


def test_line_offset_is_signed_toward_the_line() -> None:
    from companion.core.command import line_offset_m

    origin = np.array([0.0, 0.0, -1.5])
    assert line_offset_m(np.array([5.0, -0.4, -1.5]), origin, 0.0) == pytest.approx(0.4)  # left of a north line
    assert line_offset_m(np.array([5.0, 0.4, -1.5]), origin, 0.0) == pytest.approx(-0.4)
    assert line_offset_m(np.array([0.3, 5.0, -1.5]), origin, math.pi / 2) == pytest.approx(0.3)  # facing east, north is left


def test_line_hold_turns_toward_the_line_only_when_heading_hold_acts() -> None:
    cmd = CommandConfig(heading_hold_gain_per_s=1.0, max_heading_hold_rate_deg_s=20.0, line_hold_gain_per_m=0.5,
                        max_line_hold_angle_deg=30.0, hold_resume_delay_s=1.0)
    # On the heading, 0.4 m left of the line: aim atan(0.2) = 11.3 deg to the right.
    sp = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=5.0)
    assert sp.yaw_rate_deg_s == pytest.approx(math.degrees(math.atan(0.2)))
    far = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=-50.0, clear_for_s=5.0)
    assert far.yaw_rate_deg_s == pytest.approx(-20.0)  # at most 30 deg aimed, rate-limited to 20 deg/s
    assert setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=0.5).yaw_rate_deg_s == 0.0
    off = CommandConfig(heading_hold_gain_per_s=1.0, line_hold_gain_per_m=0.0)
    assert setpoint_for(CLEAR, 0.1, off, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=5.0).yaw_rate_deg_s == 0.0
    # Toward a side seen blocked: nothing.
    blocked = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=5.0,
                           region_depths_m=_depths(right=0.5))
    assert blocked.yaw_rate_deg_s == 0.0


def test_brake_heading_hold_turns_back_to_the_heading_the_brake_began_with() -> None:
    from companion.core.command import BrakeLatch

    cmd = CommandConfig(brake_hold_gain_per_s=1.0, max_heading_hold_rate_deg_s=20.0)
    latch = BrakeLatch()
    pos = np.array([4.0, 0.0, -1.5])
    latch.offset_body(BRAKE, pos, 0.5)  # the brake begins facing 0.5 rad
    # PX4 keeps turning left after the zero yaw rate: 0.2 rad later, turn right back.
    offset = latch.offset_body(BRAKE, pos, 0.3)
    err = latch.heading_error_rad(0.3)
    assert err == pytest.approx(0.2)
    sp = setpoint_for(BRAKE, 0.1, cmd, brake_offset_body_m=offset, brake_heading_error_rad=err)
    assert sp.yaw_rate_deg_s == pytest.approx(math.degrees(0.2))
    assert (sp.forward_m_s, sp.right_m_s, sp.down_m_s) == pytest.approx((0.0, 0.0, 0.0))
    big = setpoint_for(BRAKE, 0.1, cmd, brake_heading_error_rad=-1.0)
    assert big.yaw_rate_deg_s == pytest.approx(-20.0)  # capped at max_heading_hold_rate_deg_s
    # Across +-pi the shorter way round.
    latch.reset()
    latch.offset_body(BRAKE, pos, math.pi - 0.05)
    assert latch.heading_error_rad(-math.pi + 0.05) == pytest.approx(-0.1)
    # Any other decision forgets it; gain 0 (the paper) is plain zero.
    latch.offset_body(CLEAR, pos, 0.0)
    assert latch.heading_error_rad(0.0) is None
    assert setpoint_for(BRAKE, 0.1, CommandConfig(brake_hold_gain_per_s=0.0), brake_heading_error_rad=0.3).is_zero
    assert setpoint_for(BRAKE, 0.1, cmd, brake_heading_error_rad=math.nan).is_zero


def test_lateral_line_hold_flies_sideways_toward_the_line() -> None:
    cmd = CommandConfig(heading_hold_gain_per_s=0.0, line_hold_lateral_gain_per_s=0.5,
                        max_line_hold_lateral_speed_m_s=0.3, hold_resume_delay_s=1.0, line_hold_lateral_clear_depth_m=1.0)
    # 0.4 m left of the line, on the heading: 0.2 m/s to the right, still looking ahead.
    sp = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=5.0)
    assert sp.right_m_s == pytest.approx(0.2)
    assert sp.yaw_rate_deg_s == 0.0 and sp.forward_m_s == pytest.approx(cmd.cruise_speed_m_s)
    assert setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=-5.0, clear_for_s=5.0).right_m_s == pytest.approx(-0.3)
    # Facing back along the course, the line is on the other hand; crossing it square, no sideways part.
    assert setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=math.pi, line_offset_m=0.4, clear_for_s=5.0).right_m_s == pytest.approx(-0.2)
    assert setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=math.pi / 2, line_offset_m=0.4, clear_for_s=5.0).right_m_s == pytest.approx(0.0, abs=1e-12)
    # Only as course hold: after the delay, toward a side seen free, with a heading, and not with gain 0.
    assert setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=0.5).right_m_s == 0.0
    # Toward a side seen near (closer than line_hold_lateral_clear_depth_m): nothing; a wall 2 m
    # ahead-right (a doorway's wall) does not stop a sideways step.
    assert setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=5.0,
                        region_depths_m=_depths(right=0.8)).right_m_s == 0.0
    assert setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=5.0,
                        region_depths_m=_depths(right=2.0)).right_m_s == pytest.approx(0.2)
    assert setpoint_for(CLEAR, 0.1, cmd, line_offset_m=0.4, clear_for_s=5.0).right_m_s == 0.0
    off = CommandConfig(line_hold_lateral_gain_per_s=0.0)
    assert setpoint_for(CLEAR, 0.1, off, heading_error_rad=0.0, line_offset_m=0.4, clear_for_s=5.0).right_m_s == 0.0
    assert setpoint_for(Decision(DecisionKind.AVOID, 0.3, 0.0, 0.5, "x"), 0.1, cmd, heading_error_rad=0.0,
                        line_offset_m=0.4, clear_for_s=5.0).right_m_s == 0.0


def test_lateral_line_hold_waits_for_the_turn_toward_its_aim() -> None:
    """Sliding toward a side while still turning toward it would carry the body into what the camera
    has not seen yet (PX4 SITL forest-4): the sideways speed tapers to 0 at the aim error's limit."""
    cmd = CommandConfig(heading_hold_gain_per_s=0.8, line_hold_gain_per_m=0.0, line_hold_lateral_gain_per_s=1.0,
                        max_line_hold_lateral_speed_m_s=0.3, hold_resume_delay_s=1.0,
                        line_hold_lateral_max_aim_error_deg=15.0)
    facing = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=0.0, line_offset_m=-4.0, clear_for_s=5.0)
    assert facing.right_m_s == pytest.approx(-0.3)
    # the course lies 30 deg left: turning left at full rate, no slide left yet
    turning = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=math.radians(-30.0), line_offset_m=-4.0, clear_for_s=5.0)
    assert turning.yaw_rate_deg_s < 0.0 and turning.right_m_s == 0.0
    # 7.5 deg from the aim: half the slide (times the heading error's cosine)
    near = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=math.radians(-7.5), line_offset_m=-4.0, clear_for_s=5.0)
    assert near.right_m_s == pytest.approx(-0.3 * 0.5 * math.cos(math.radians(7.5)))
    # 180: no taper (the slide as before)
    old = cmd.model_copy(update={"line_hold_lateral_max_aim_error_deg": 180.0})
    assert setpoint_for(CLEAR, 0.1, old, heading_error_rad=math.radians(-30.0), line_offset_m=-4.0,
                        clear_for_s=5.0).right_m_s == pytest.approx(-0.3 * math.cos(math.radians(30.0)))


def test_altitude_hold_waits_for_a_distance_flown_as_well_as_a_time() -> None:
    cmd = CommandConfig(heading_hold_gain_per_s=1.0, altitude_hold_gain_per_s=0.5, hold_resume_delay_s=1.0,
                        hold_resume_distance_m=1.5)
    # Climbed over a box, slowed down: clear for 3 s but only 0.8 m further on: no descent yet
    # (the box's rear edge may be below, out of view); turning back to the heading does not wait.
    slow = setpoint_for(CLEAR, 0.1, cmd, altitude_error_m=-0.5, heading_error_rad=0.2, clear_for_s=3.0, clear_for_m=0.8)
    assert slow.down_m_s == 0.0 and slow.yaw_rate_deg_s > 0.0
    on = setpoint_for(CLEAR, 0.1, cmd, altitude_error_m=-0.5, heading_error_rad=0.2, clear_for_s=3.0, clear_for_m=1.6)
    assert on.down_m_s > 0.0 and on.yaw_rate_deg_s == slow.yaw_rate_deg_s
    # Unknown distance (no position): the time alone decides, as before.
    assert setpoint_for(CLEAR, 0.1, cmd, altitude_error_m=-0.5, clear_for_s=3.0).down_m_s > 0.0


def test_a_climb_back_to_the_engaged_altitude_does_not_wait() -> None:
    """PX4 SITL pitch-4: PX4 sagged 0.27 m as it sped up after engaging, the controller's small climbs
    on CLEAR decisions (the ground near in the down regions) kept resetting the clear timers, and
    the altitude hold never acted: 0.3 m low, the low wall's top filled the up regions and the way
    over it read blocked. Below the engaged altitude, on a level or climbing CLEAR decision, the
    hold climbs back at once; what was overhead (since_up_near_m) and the up region still stop it."""
    cmd = CommandConfig(altitude_hold_gain_per_s=0.5, hold_resume_delay_s=1.5, hold_resume_distance_m=1.5)
    for kw in ({"clear_for_s": 0.0, "clear_for_m": 0.0}, {}):
        assert setpoint_for(CLEAR, 0.1, cmd, altitude_error_m=0.26, **kw).down_m_s == pytest.approx(-0.13)
    climbing = Decision(DecisionKind.CLEAR, 0.0, 0.05, 1.0, "centre clear, ground near below")
    sp = setpoint_for(climbing, 0.1, cmd, altitude_error_m=0.26, clear_for_s=0.0, clear_for_m=0.0)
    assert sp.down_m_s == pytest.approx(-0.05 * cmd.max_vertical_speed_m_s - 0.95 * 0.13)
    ducking = Decision(DecisionKind.CLEAR, 0.0, -0.2, 1.0, "going under")
    assert setpoint_for(ducking, 0.1, cmd, altitude_error_m=0.26, clear_for_s=0.0).down_m_s > 0.0  # no climb back
    assert setpoint_for(CLEAR, 0.1, cmd, altitude_error_m=0.26, since_up_near_m=0.5).down_m_s == 0.0
    assert setpoint_for(CLEAR, 0.1, cmd, altitude_error_m=0.26, region_depths_m=_depths(up=1.0)).down_m_s == 0.0
    brake = Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "no escape")
    assert setpoint_for(brake, 0.1, cmd, altitude_error_m=0.26).down_m_s == 0.0


def test_a_level_decision_a_hair_off_zero_pitch_still_climbs_back_and_descends() -> None:
    """The defuzzified pitch of a level CLEAR decision is rarely exactly 0 (-1e-4 in the simulator):
    a strict sign test read it as a descent and the climb back waited for 1.5 m of straight flight
    while the vehicle sank (0.1 m/s vertical drift: pitch-2 sank 0.37 m and lost its way over the
    low wall). Level means within STRAIGHT_TOLERANCE, as in is_straight_clear."""
    from companion.core.command import STRAIGHT_TOLERANCE

    cmd = CommandConfig(altitude_hold_gain_per_s=0.5, hold_resume_delay_s=1.5, hold_resume_distance_m=1.5)
    hair = 0.1 * STRAIGHT_TOLERANCE
    for pitch in (-hair, hair):
        level = Decision(DecisionKind.CLEAR, 0.0, pitch, 1.0, "centre clear")
        assert is_straight_clear(level)
        # Below the engaged altitude: the climb back at once (scaled by 1 - |pitch|, and the pitch's own
        # tiny vertical speed on top).
        sp = setpoint_for(level, 0.1, cmd, altitude_error_m=0.26, clear_for_s=0.0, clear_for_m=0.0)
        assert sp.down_m_s == pytest.approx(-pitch * cmd.max_vertical_speed_m_s - (1.0 - abs(pitch)) * 0.13)
        # Above it, over nothing remembered below: the descent at once too.
        sp = setpoint_for(level, 0.1, cmd, altitude_error_m=-0.26, clear_for_s=0.0, clear_for_m=0.0, below_clear=True)
        assert sp.down_m_s == pytest.approx(-pitch * cmd.max_vertical_speed_m_s + (1.0 - abs(pitch)) * 0.13)
    # A real descent or climb of the decision still keeps the hold from fighting it.
    ducking = Decision(DecisionKind.CLEAR, 0.0, -STRAIGHT_TOLERANCE, 1.0, "going under")
    assert setpoint_for(ducking, 0.1, cmd, altitude_error_m=0.26, clear_for_s=0.0).down_m_s == pytest.approx(
        STRAIGHT_TOLERANCE * cmd.max_vertical_speed_m_s
    )
    climbing = Decision(DecisionKind.CLEAR, 0.0, STRAIGHT_TOLERANCE, 1.0, "climbing over")
    assert setpoint_for(
        climbing, 0.1, cmd, altitude_error_m=-0.26, clear_for_s=0.0, below_clear=True
    ).down_m_s == pytest.approx(-STRAIGHT_TOLERANCE * cmd.max_vertical_speed_m_s)


def test_nothing_climbs_until_the_vehicle_has_flown_past_what_was_overhead() -> None:
    from companion.core.command import OverheadMemory

    cmd = CommandConfig(altitude_hold_gain_per_s=0.5, hold_resume_delay_s=0.0, hold_resume_distance_m=1.5,
                        hold_clear_depth_m=2.25, max_vertical_speed_m_s=0.8)
    memory = OverheadMemory()
    assert memory.update(_depths(), np.array([0.0, 0.0, -1.0]), 2.25) is None  # nothing overhead yet
    # Ducking under a block: the up region reads it at 0.8 m.
    assert memory.update(_depths(up=0.8), np.array([5.0, 0.0, -1.0]), 2.25) == 0.0
    # Under it the camera sees past its rear edge: up reads far, but only 0.6 m flown since.
    since = memory.update(_depths(), np.array([5.6, 0.0, -1.0]), 2.25)
    assert since == pytest.approx(0.6)
    climb = Decision(DecisionKind.CLEAR, 0.0, 0.3, 1.0, "side rule: ground below")
    assert setpoint_for(climb, 0.1, cmd, since_up_near_m=since).down_m_s == 0.0
    assert setpoint_for(CLEAR, 0.1, cmd, altitude_error_m=0.5, since_up_near_m=since).down_m_s == 0.0
    descend = Decision(DecisionKind.AVOID, 0.0, -0.5, 0.5, "R2")
    assert setpoint_for(descend, 0.1, cmd, since_up_near_m=since).down_m_s == pytest.approx(0.4)  # descending is fine
    # 1.5 m on: climbing is allowed again.
    since = memory.update(_depths(), np.array([6.5, 0.0, -1.0]), 2.25)
    assert since == pytest.approx(1.5)
    assert setpoint_for(climb, 0.1, cmd, since_up_near_m=since).down_m_s == pytest.approx(-0.24)
    # Unknown up latches too; no position: no answer; reset forgets.
    assert memory.update(_depths(up=np.nan), np.array([7.0, 0.0, -1.0]), 2.25) == 0.0
    assert memory.update(_depths(), None, 2.25) is None
    memory.reset()
    assert memory.update(_depths(), np.array([7.0, 0.0, -1.0]), 2.25) is None


def test_a_clear_decision_that_keeps_turning_away_is_turned_back_after_turn_back_after_clear_s() -> None:
    """A side rule along a corridor wall kept a CLEAR decision turning right at 23 deg/s for 5 s: it
    carried the vehicle round through 160 deg and back along the course at cruise (kinematic
    corridor-7 with drift), since course hold waited for a CLEAR decision that does not turn."""
    turning = Decision(DecisionKind.CLEAR, 0.25, 0.0, 1.0, "S2: left near")
    kw = {"heading_error_rad": -math.radians(130.0), "heading_clear_for_s": 0.0, "clear_for_s": 0.0}
    sp = setpoint_for(turning, 0.1, HOLD, any_clear_for_s=1.0, **kw)  # just cleared: the escape's own turn
    assert sp.forward_m_s == HOLD.cruise_speed_m_s and sp.yaw_rate_deg_s == pytest.approx(0.25 * HOLD.max_yaw_rate_deg_s)
    sp = setpoint_for(turning, 0.1, HOLD, any_clear_for_s=HOLD.turn_back_after_clear_s, **kw)
    assert (sp.forward_m_s, sp.yaw_rate_deg_s) == (0.0, -HOLD.max_heading_hold_rate_deg_s)  # stops, turns back
    # Below the turn-back angle the heading hold still waits for a straight CLEAR.
    near = {**kw, "heading_error_rad": -math.radians(60.0)}
    sp = setpoint_for(turning, 0.1, HOLD, any_clear_for_s=10.0, **near)
    assert sp.yaw_rate_deg_s == pytest.approx(0.25 * HOLD.max_yaw_rate_deg_s)
    # Course hold times CLEAR decisions, turning or not, from the first one's frame.
    from companion.core.course import CourseHold

    hold = CourseHold()
    here = np.array([4.0, 0.5, -1.5])
    hold.engage(np.array([0.0, 0.0, -1.5]), 0.0)
    yaw = math.radians(130.0)
    for t in (10.0, 11.0, 12.0):
        hold.observe(turning, t, here)
        assert hold.setpoint(turning, t, 0.05, HOLD, position_ned_m=here, yaw_rad=yaw).forward_m_s > 0.0
    hold.observe(turning, 13.0, here)
    sp = hold.setpoint(turning, 13.0, 0.05, HOLD, position_ned_m=here, yaw_rad=yaw)
    assert (sp.forward_m_s, sp.yaw_rate_deg_s) == (0.0, -HOLD.max_heading_hold_rate_deg_s)


def test_facing_away_from_the_course_it_stops_and_turns_back_in_place_whatever_the_sides_read() -> None:
    """A vehicle that turned around in a corridor has walls beside it nearer than hold_clear_depth_m,
    which block the ordinary hold; past turn_back_angle_deg it turns back in place instead."""
    walls = _depths(left=1.5, right=1.5, up_left=1.5, up_right=1.5, down_left=1.5, down_right=1.5)
    kw = {"region_depths_m": walls, "clear_for_s": 5.0, "altitude_error_m": 0.5}
    sp = setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=-math.radians(150.0), **kw)
    assert (sp.forward_m_s, sp.right_m_s, sp.down_m_s, sp.yaw_rate_deg_s) == (0.0, 0.0, 0.0, -20.0)
    sp = setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=math.radians(170.0), **kw)
    assert sp.yaw_rate_deg_s == 20.0 and sp.forward_m_s == 0.0
    # The line counts: 95 deg off the heading, and the line 2 m further that way, is past 100 deg.
    cmd = HOLD.model_copy(update={"line_hold_gain_per_m": 0.5})
    sp = setpoint_for(CLEAR, 0.1, cmd, heading_error_rad=math.radians(95.0), line_offset_m=2.0, **kw)
    assert sp.forward_m_s == 0.0 and sp.yaw_rate_deg_s == 20.0
    # Below the angle, or off (180), the ordinary hold, which the near walls block.
    sp = setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=-math.radians(90.0), **kw)
    assert sp.forward_m_s == HOLD.cruise_speed_m_s and sp.yaw_rate_deg_s == 0.0
    off = HOLD.model_copy(update={"turn_back_angle_deg": 180.0})
    sp = setpoint_for(CLEAR, 0.1, off, heading_error_rad=-math.radians(150.0), **kw)
    assert sp.forward_m_s == HOLD.cruise_speed_m_s and sp.yaw_rate_deg_s == 0.0
    # Only on CLEAR after the resume delay: avoiding, or just clear, the controller flies.
    assert setpoint_for(CLEAR, 0.1, HOLD, heading_error_rad=3.0, region_depths_m=walls, clear_for_s=0.5).forward_m_s > 0.0
    avoid = Decision(DecisionKind.AVOID, 0.5, 0.0, 0.5, "x")
    assert setpoint_for(avoid, 0.1, HOLD, heading_error_rad=3.0, **kw).yaw_rate_deg_s == pytest.approx(0.5 * HOLD.max_yaw_rate_deg_s)


def test_along_course_is_the_distance_along_the_engagement_heading() -> None:
    origin = np.array([1.0, 2.0, -1.5])
    assert along_course_m(np.array([4.0, 2.0, -3.0]), origin, 0.0) == pytest.approx(3.0)  # north, height ignored
    assert along_course_m(np.array([1.0, 5.0, -1.5]), origin, 0.0) == pytest.approx(0.0)  # abeam
    assert along_course_m(np.array([1.0, 5.0, -1.5]), origin, math.pi / 2) == pytest.approx(3.0)  # facing east
    assert along_course_m(np.array([0.0, 2.0, -1.5]), origin, 0.0) == pytest.approx(-1.0)  # behind


def test_progress_watch_times_the_last_step_along_the_course() -> None:
    cmd = CommandConfig(no_progress_timeout_s=10.0, progress_step_m=1.0)
    w = ProgressWatch()
    assert not w.update(0.0, 0.0, cmd) and w.mark_m == 0.0
    assert not w.update(0.9, 9.0, cmd)  # not a step yet
    assert not w.update(1.0, 9.5, cmd) and w.mark_m == 1.0  # a step: the clock restarts
    assert not w.update(-3.0, 19.5, cmd)  # going back is not progress, and the limit is not passed yet
    assert w.update(1.9, 19.6, cmd)  # 10.1 s without a whole step
    # Unknown position, or the watchdog off (no timeout, or no course hold): never, and it restarts.
    assert not w.update(None, 30.0, cmd) and w.mark_m is None
    assert not w.update(float("nan"), 31.0, cmd)
    for off in (CommandConfig(no_progress_timeout_s=0.0), CommandConfig(heading_hold_gain_per_s=0.0)):
        w = ProgressWatch()
        assert not any(w.update(0.0, t, off) for t in range(0, 100, 5))


def test_a_climb_alone_does_not_keep_the_heading_hold_waiting() -> None:
    """The down regions see the ground near at low altitude and the controller climbs a little on
    CLEAR decisions: the heading hold and turning back wait only for decisions that do not turn
    (heading_clear_for_s), the altitude hold for decisions that neither turn nor climb (clear_for_s).
    With one timer for both, a PX4 flight facing 95° off its course flew 6 m out of bounds."""
    climbing = Decision(DecisionKind.CLEAR, 0.0, 0.2, 1.0, "centre clear")
    assert is_heading_clear(climbing) and not is_straight_clear(climbing)
    kw = {"heading_error_rad": math.radians(150.0), "altitude_error_m": 0.5, "clear_for_s": 0.0}
    sp = setpoint_for(climbing, 0.1, HOLD, heading_clear_for_s=5.0, **kw)
    # Turning back in place, the decision's climb kept, the altitude hold waiting.
    assert (sp.forward_m_s, sp.yaw_rate_deg_s) == (0.0, 20.0)
    assert sp.down_m_s == pytest.approx(-0.2 * HOLD.max_vertical_speed_m_s)
    assert setpoint_for(climbing, 0.1, HOLD, heading_clear_for_s=0.5, **kw).forward_m_s == HOLD.cruise_speed_m_s
    sp = setpoint_for(climbing, 0.1, HOLD, heading_error_rad=0.1, heading_clear_for_s=5.0, clear_for_s=0.0, altitude_error_m=-0.5)
    assert sp.yaw_rate_deg_s == pytest.approx(math.degrees(0.1))  # the heading hold acts
    assert sp.down_m_s == pytest.approx(-0.2 * HOLD.max_vertical_speed_m_s)  # the altitude hold's descent waits
    # Without heading_clear_for_s, one timer as before.
    assert setpoint_for(climbing, 0.1, HOLD, heading_error_rad=0.1, clear_for_s=0.0).yaw_rate_deg_s == 0.0


def test_the_motion_brake_leans_against_flying_on_into_what_the_camera_reads_near() -> None:
    """Kinematic office-4 with drift: turning away from a cabinet, the vehicle still flew its old
    course at 0.9 m/s, 40 degrees right of its nose, into what its right region read. The brake
    takes the setpoint's own motion that way out and leans against the speed it cannot stop in."""
    from companion.core.command import motion_brake

    cmd = CommandConfig()
    assert cmd.motion_brake_clearance_m == 0.5 and cmd.motion_brake_lag_s == 0.85  # on by default
    b = math.radians(40.0)
    v = (0.9 * math.cos(b), 0.9 * math.sin(b))  # 40 deg right: the right region
    allowed = (0.9 / math.cos(b) - 0.5) / 0.85
    sp = motion_brake(setpoint_for(CLEAR, 0.1, cmd), _depths(right=0.9), v, cmd)
    along = sp.forward_m_s * math.cos(b) + sp.right_m_s * math.sin(b)
    assert along == pytest.approx(-(0.9 - allowed))  # nothing toward it, the excess against it
    # Through the whole setpoint, BRAKE included.
    sp = setpoint_for(BRAKE, 0.1, cmd, region_depths_m=_depths(right=0.9), velocity_body_m_s=v)
    assert sp.forward_m_s * math.cos(b) + sp.right_m_s * math.sin(b) == pytest.approx(-(0.9 - allowed))
    # Where it can stop short, moving back, out of the view's sides or toward an unknown region:
    # unchanged (the controller already counts unknown as near; the memory guards the sides).
    free = setpoint_for(CLEAR, 0.1, cmd)
    assert motion_brake(free, _depths(right=3.0), v, cmd) == free
    assert motion_brake(free, _depths(right=0.4), (-0.5, 0.3), cmd) == free
    assert motion_brake(free, _depths(right=0.4), (0.2, 0.6), cmd) == free  # 72 deg: out of view
    assert motion_brake(free, _depths(right=math.nan), v, cmd) == free
    assert motion_brake(free, _depths(right=0.4), None, cmd) == free
    # Straight at a wall the centre reads 0.8 m, at cruise: backs off by what it cannot stop in;
    # the brake never commands more than the cruise speed.
    at_wall = motion_brake(free, _depths(center=0.8), (0.7, 0.0), cmd)
    assert (at_wall.forward_m_s, at_wall.right_m_s) == pytest.approx((-(0.7 - 0.3 / 0.85), 0.0))
    fast = motion_brake(free, _depths(center=0.6), (1.5, 0.0), cmd)
    assert (fast.forward_m_s, fast.right_m_s) == pytest.approx((-cmd.cruise_speed_m_s, 0.0))
    off = cmd.model_copy(update={"motion_brake_clearance_m": 0.0})
    assert motion_brake(free, _depths(right=0.9), v, off) == free


def test_nothing_in_a_setpoint_goes_forward_faster_than_the_centre_region_allows() -> None:
    """PX4 SITL r14 corridor-8: looking round 0.4 m from a box with a wall 0.6 m behind, the memory's
    push off the wall sent the vehicle forward at 0.5 m/s into the box the camera read. Whatever a
    setpoint carries, its forward speed is at most what the vehicle can stop short of the centre's
    reading in: (depth - motion_brake_clearance_m) / motion_brake_lag_s."""
    from companion.config.memory import MemoryConfig

    cmd = CommandConfig()
    behind = np.array([[0.3, -1.0, 0.0, 1.0]])  # a remembered point 0.3 m straight behind, may push

    def pushed(centre: float, c: CommandConfig = cmd) -> float:
        return setpoint_for(
            BRAKE, 0.1, c, region_depths_m=_depths(center=centre), guard_m=behind, guard_cfg=MemoryConfig(),
            velocity_body_m_s=(0.0, 0.0),
        ).forward_m_s

    free = pushed(5.0)
    assert free > 0.3  # the push off the wall, nothing ahead
    assert pushed(0.8) == pytest.approx((0.8 - 0.5) / 0.85)
    assert (0.8 - 0.5) / 0.85 < free
    assert pushed(0.45) == 0.0  # inside the clearance: no forward motion at all
    assert pushed(math.nan) == pytest.approx(free)  # unknown: the controller already counts it as near
    assert pushed(0.45, cmd.model_copy(update={"motion_brake_clearance_m": 0.0})) == pytest.approx(free)  # off
    # The controller's own forward speed is slower than this from 0.56 m out, so a decision alone is
    # not cut there; nearer, its creep (avoid_speed_fraction of the cruise) stops.
    for centre in (0.6, 0.9, 1.2, 1.6, 2.0):
        near = min(1.0, max(0.0, (2.25 - centre) / 1.5))
        own = Decision(DecisionKind.AVOID, 0.3, 0.0, 1.0 + (cmd.avoid_speed_fraction - 1.0) * near, "turning")
        assert setpoint_for(own, 0.1, cmd, region_depths_m=_depths(center=centre)) == setpoint_for(own, 0.1, cmd)
    creep = Decision(DecisionKind.AVOID, 0.3, 0.0, cmd.avoid_speed_fraction, "turning")
    assert setpoint_for(creep, 0.1, cmd, region_depths_m=_depths(center=0.5)).forward_m_s == 0.0


def test_standoff_is_off_by_default_and_pushes_away_from_a_near_middle_row_region_when_on() -> None:
    """The stand-off closes the loop on the measured depth (a drifting velocity estimate carries the
    vehicle on into a wall it sees): every decision, the brake included, gets the push; unknown and
    the up/down rows push nothing; the push is capped."""
    from companion.core.command import STANDOFF_SIDE_BEARING_RAD, standoff_push_m_s

    near_left = _depths(left=0.5)
    assert standoff_push_m_s(near_left, CommandConfig()) == (0.0, 0.0)  # off by default
    on = CommandConfig(standoff_depth_m=0.8, standoff_gain_per_s=2.0, max_standoff_speed_m_s=0.7)
    f, r = standoff_push_m_s(near_left, on)
    push = 2.0 * (0.8 - 0.5)
    assert (f, r) == pytest.approx(
        (-push * math.cos(STANDOFF_SIDE_BEARING_RAD), push * math.sin(STANDOFF_SIDE_BEARING_RAD))
    )  # back and to the right, away from the left
    assert standoff_push_m_s(_depths(center=0.6), on) == pytest.approx((-0.4, 0.0))
    assert standoff_push_m_s(_depths(center=math.nan, up=0.1, down=0.1), on) == (0.0, 0.0)
    assert math.hypot(*standoff_push_m_s(_depths(center=0.0, left=0.0), on)) == pytest.approx(0.7)  # capped
    sp = setpoint_for(BRAKE, 0.1, on, region_depths_m=_depths(center=0.6))
    assert (sp.forward_m_s, sp.right_m_s) == pytest.approx((-0.4, 0.0))
    sp = setpoint_for(CLEAR, 0.1, on, region_depths_m=near_left)
    assert (sp.forward_m_s, sp.right_m_s) == pytest.approx((on.cruise_speed_m_s + f, r))
    assert setpoint_for(CLEAR, 1.0, on, region_depths_m=near_left).is_zero  # stale: zero, no push
