"""The reported position's motion that the reported velocity does not explain (companion/core/closing.py
TrackWatch) and course hold's use of it: the guard and the motion brake act on how the vehicle moves
in the frame its memory lives in, and the unexplained motion comes off the setpoint
(``command.track_velocity_window_s``, ``track_counter_fraction``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import parse_config
from companion.core.closing import TRACK_DEADBAND_M_S, TrackWatch
from companion.core.course import CourseHold
from companion.core.types import REGION_INDEX, Decision, DecisionKind, VelocitySetpoint

RATE_HZ = 20.0
BRAKE = Decision(kind=DecisionKind.BRAKE, yaw=0.0, pitch=0.0, speed_fraction=0.0, reason="centre blocked")
OFF = {"command": {"track_velocity_window_s": 0.0, "track_counter_fraction": 0.0}}


def _feed(watch: TrackWatch, seconds: float, reported_ned_m_s, drift_ned_m_s, t0_s: float = 0.0) -> float:
    """Samples at 20 Hz of a vehicle reporting ``reported_ned_m_s`` whose position moves at that plus
    ``drift_ned_m_s``. Returns the last sample's time."""
    v = np.array([*reported_ned_m_s, 0.0])
    d = np.array([*drift_ned_m_s, 0.0])
    t = t0_s
    for k in range(int(round(seconds * RATE_HZ)) + 1):
        t = t0_s + k / RATE_HZ
        watch.observe(t, (v + d) * t, v)
    return t


def test_the_unexplained_motion_is_the_drift_less_the_dead_band():
    w = TrackWatch()
    t = _feed(w, 1.0, (0.5, 0.0), (0.0, 0.3))
    u = w.unexplained_m_s(t, 0.5, 0.6)
    assert u == pytest.approx([0.0, 0.3 - TRACK_DEADBAND_M_S], abs=1e-9)


def test_nothing_unexplained_without_drift_too_little_history_or_a_jump():
    still = TrackWatch()
    t = _feed(still, 1.0, (0.7, -0.2), (0.0, 0.0))
    assert still.unexplained_m_s(t, 0.5, 0.6) is None  # the position moved as reported
    short = TrackWatch()
    t = _feed(short, 0.1, (0.0, 0.0), (0.3, 0.0))
    assert short.unexplained_m_s(t, 0.5, 0.6) is None  # 0.1 s of a 0.5 s window
    assert TrackWatch().unexplained_m_s(0.0, 0.5, 0.6) is None
    fast = TrackWatch()
    t = _feed(fast, 1.0, (0.0, 0.0), (1.5, 0.0))  # counted at most max_m_s
    assert fast.unexplained_m_s(t, 0.5, 0.6) == pytest.approx([0.6, 0.0], abs=1e-9)
    jump = TrackWatch()
    t = _feed(jump, 1.0, (0.0, 0.0), (0.0, 0.0))
    jump.observe(t + 0.05, np.array([2.0, 0.0, 0.0]), np.zeros(3))  # an estimator's reset, not motion
    jump.observe(t + 0.10, np.array([2.0, 0.0, 0.0]), np.zeros(3))
    assert jump.unexplained_m_s(t + 0.10, 0.5, 0.6) is None  # the window starts again after the jump
    jump.observe(t + 0.30, np.array([2.0, 0.0, 0.0]), np.zeros(3))
    assert jump.unexplained_m_s(t + 0.30, 0.5, 0.6) is None  # still: nothing moved since
    small = TrackWatch()
    t = _feed(small, 1.0, (0.0, 0.0), (0.015, 0.0))
    assert small.unexplained_m_s(t, 0.5, 0.6) is None  # within the dead band
    assert TrackWatch().unexplained_m_s(0.0, 0.0, 0.6) is None  # off


def test_bad_samples_are_not_kept():
    w = TrackWatch()
    t = _feed(w, 1.0, (0.0, 0.0), (0.2, 0.0))
    before = w.unexplained_m_s(t, 0.5, 0.6)
    w.observe(t, np.array([math.nan, 0.0, 0.0]), np.zeros(3))
    w.observe(t + 0.05, None, np.zeros(3))
    w.observe(t - 1.0, np.zeros(3), np.zeros(3))  # back in time
    assert w.unexplained_m_s(t, 0.5, 0.6) == pytest.approx(before)
    w.reset()
    assert w.unexplained_m_s(t, 0.5, 0.6) is None


def _setpoint(hold, cmd, t, position, velocity, *, yaw=0.0, age_s=0.0):
    hold.observe(BRAKE, t - age_s, position)
    depths = np.full(9, 3.0)  # nothing near: the camera's own check (the centre closing) has nothing to say
    return hold.setpoint(BRAKE, t, age_s, cmd, position_ned_m=position, yaw_rad=yaw, velocity_ned_m_s=velocity, region_depths_m=depths)


def test_course_hold_takes_the_unexplained_motion_off_the_setpoint_in_the_body_frame():
    cmd = parse_config({}).command
    assert cmd.track_velocity_window_s > 0.0 and cmd.track_counter_fraction == 1.0  # on by default
    for yaw_deg, forward, right in ((0.0, 0.0, -1.0), (90.0, -1.0, 0.0)):
        hold = CourseHold()
        hold.engage(np.zeros(3), math.radians(yaw_deg))
        sp = VelocitySetpoint()
        for k in range(20):  # braked, reporting 0 m/s, while the position moves 0.25 m/s east
            t = k / RATE_HZ
            sp = _setpoint(hold, cmd, t, np.array([0.0, 0.25 * t, -1.5]), np.zeros(3), yaw=math.radians(yaw_deg))
        # what the brake's pull back asks is there as well; the counter is the difference
        ref = CourseHold()
        ref.engage(np.zeros(3), math.radians(yaw_deg))
        off = parse_config(OFF).command
        for k in range(20):
            t = k / RATE_HZ
            sp_off = _setpoint(ref, off, t, np.array([0.0, 0.25 * t, -1.5]), np.zeros(3), yaw=math.radians(yaw_deg))
        counter = 0.25 - TRACK_DEADBAND_M_S
        assert sp.forward_m_s - sp_off.forward_m_s == pytest.approx(forward * counter, abs=1e-6)
        assert sp.right_m_s - sp_off.right_m_s == pytest.approx(right * counter, abs=1e-6)
        assert hold.track_counter_m_s == pytest.approx(counter, abs=1e-6)  # what the health message reports
        # a stale frame's zero stays zero
        t = 20 / RATE_HZ
        assert _setpoint(hold, cmd, t, np.array([0.0, 0.25 * t, -1.5]), np.zeros(3), yaw=math.radians(yaw_deg), age_s=0.9).is_zero


def test_without_drift_the_setpoints_are_those_of_the_reported_velocity_alone():
    on, off = parse_config({}).command, parse_config(OFF).command
    a, b = CourseHold(), CourseHold()
    a.engage(np.zeros(3), 0.0)
    b.engage(np.zeros(3), 0.0)
    v = np.array([0.4, -0.1, 0.0])
    for k in range(30):
        t = k / RATE_HZ
        p = v * t
        assert _setpoint(a, on, t, p, v) == _setpoint(b, off, t, p, v)


def _held_drift(cmd, drift_east_m_s: float, seconds: float = 8.0) -> float:
    """A braked vehicle (the brake holds where it stopped) whose position moves east at a steady
    ``drift_east_m_s`` the velocity it reports does not show; the velocity follows the setpoint with a
    0.85 s lag (PX4). Returns how far east it ends, metres."""
    hold = CourseHold()
    hold.engage(np.array([0.0, 0.0, -1.5]), 0.0)
    p, v, dt = np.array([0.0, 0.0, -1.5]), np.zeros(3), 1.0 / 60.0
    sp = VelocitySetpoint()
    for k in range(int(seconds / dt)):
        t = k * dt
        if k % 3 == 0:
            sp = _setpoint(hold, cmd, t, p.copy(), v.copy())
        v[:2] += (np.array([sp.forward_m_s, sp.right_m_s]) - v[:2]) * dt / 0.85
        p += (v + np.array([0.0, drift_east_m_s, 0.0])) * dt
    return float(p[1])


def test_a_braked_vehicle_drifting_beside_what_the_camera_sees_stays_where_it_stopped():
    """The camera's check sees only motion toward the centre region; a sideways drift it does not see.
    The brake's pull back alone leaves the vehicle off by the drift over its gain; countering the
    unexplained motion keeps it within a few centimetres."""
    on, off = parse_config({}).command, parse_config(OFF).command
    without = _held_drift(off, 0.3)
    with_counter = _held_drift(on, 0.3)
    assert without > 0.25
    assert abs(with_counter) < 0.3 * without
    assert _held_drift(on, 0.0) == pytest.approx(_held_drift(off, 0.0))


def test_the_counter_adds_no_forward_motion_toward_what_brakes_or_reads_near():
    """The unexplained motion may be the estimate's, not the vehicle's; the fuzzy brake is absolute. A
    vehicle whose position slides back (south, facing north) at 0.4 m/s: braked, the counter adds
    nothing forward; clear with the centre at 0.8 m, no more than it can stop short of."""
    on, off = parse_config({}).command, parse_config(OFF).command
    clear = Decision(kind=DecisionKind.CLEAR, yaw=0.0, pitch=0.0, speed_fraction=1.0, reason="centre clear")

    def last(cmd, decision, centre_m):
        hold = CourseHold()
        hold.engage(np.array([0.0, 0.0, -1.5]), 0.0)
        sp = VelocitySetpoint()
        depths = np.full(9, 3.0)
        depths[REGION_INDEX["center"]] = centre_m
        for k in range(20):
            t = k / RATE_HZ
            p = np.array([-0.4 * t, 0.0, -1.5])
            hold.observe(decision, t, p)
            sp = hold.setpoint(decision, t, 0.0, cmd, position_ned_m=p, yaw_rad=0.0, velocity_ned_m_s=np.zeros(3), region_depths_m=depths)
        return sp

    assert last(on, BRAKE, 0.6).forward_m_s <= max(0.0, last(off, BRAKE, 0.6).forward_m_s) + 1e-9
    room = (0.8 - on.motion_brake_clearance_m) / on.motion_brake_lag_s
    assert last(on, clear, 0.8).forward_m_s <= max(room, last(off, clear, 0.8).forward_m_s) + 1e-9
    assert last(on, clear, math.nan).forward_m_s <= max(0.0, last(off, clear, math.nan).forward_m_s) + 1e-9
    # far from anything the counter does its work: forward more than without it, below the cruise
    half = Decision(kind=DecisionKind.CLEAR, yaw=0.0, pitch=0.0, speed_fraction=0.5, reason="centre clear")
    assert last(on, half, 5.0).forward_m_s > last(off, half, 5.0).forward_m_s + 0.2


def test_the_counter_never_sends_the_vehicle_past_the_cruise():
    """PX4 SITL, clear ahead at the cruise: PX4's reported position moved slower than its reported
    velocity, so the track counter read the vehicle as falling behind and added forward speed: the
    setpoint went 0.74 m/s over a 0.7 m/s cruise in every flight, up to 1.21 m/s. The counter may
    slow the vehicle or push it sideways, never past the cruise, in any direction."""
    cmd = parse_config({}).command
    clear = Decision(kind=DecisionKind.CLEAR, yaw=0.0, pitch=0.0, speed_fraction=1.0, reason="centre clear")
    for drift in ((-0.4, 0.0), (-0.4, 0.4), (0.0, -0.5)):
        hold = CourseHold()
        hold.engage(np.array([0.0, 0.0, -1.5]), 0.0)
        depths = np.full(9, 10.0)
        for k in range(30):
            t = k / RATE_HZ
            v = np.array([cmd.cruise_speed_m_s, 0.0, 0.0])
            p = np.array([(v[0] + drift[0]) * t, drift[1] * t, -1.5])
            hold.observe(clear, t, p)
            sp = hold.setpoint(clear, t, 0.0, cmd, position_ned_m=p, yaw_rad=0.0, velocity_ned_m_s=v, region_depths_m=depths)
            assert sp.forward_m_s <= cmd.cruise_speed_m_s + 1e-9, (drift, k, sp)
            assert math.hypot(sp.forward_m_s, sp.right_m_s) <= cmd.cruise_speed_m_s + 1e-9, (drift, k, sp)
        assert hold.track_counter_m_s > 0.0  # the counter acted


def test_a_false_point_across_the_counter_never_cancels_the_push_away_from_a_wall():
    """Braked beside a wall remembered 0.4 m to the right (it may push), a point that may not push
    0.45 m to the left (a false match), the position moving right at 0.3 m/s. The counter's slide
    past the left point takes the counter back, never the guard's push away from the wall: sliding
    the sum took both, and the drift carried the vehicle into the wall (PX4 SITL r32, office-1 and
    office-3)."""
    cfg = parse_config({})
    on, off = cfg.command, parse_config(OFF).command
    guard = np.array([[0.4, 0.0, 1.0, 1.0], [0.45, 0.0, -1.0, 0.0]])  # distance, unit forward, right, may push

    def last(cmd):
        hold = CourseHold()
        hold.engage(np.array([0.0, 0.0, -1.5]), 0.0)
        sp = VelocitySetpoint()
        for k in range(20):
            t = k / RATE_HZ
            p = np.array([0.0, 0.3 * t, -1.5])
            hold.observe(BRAKE, t, p)
            sp = hold.setpoint(
                BRAKE, t, 0.0, cmd, position_ned_m=p, yaw_rad=0.0, velocity_ned_m_s=np.zeros(3),
                region_depths_m=np.full(9, 3.0), guard_m=guard, memory_cfg=cfg.memory,
            )
        return sp, hold.track_counter_m_s

    (sp, counter), (sp_off, _) = last(on), last(off)
    assert counter > 0.2  # the counter is on, and slid away by the left point
    assert sp_off.right_m_s < -0.1  # the guard pushes away from the wall on the right
    assert sp.right_m_s <= sp_off.right_m_s + 1e-9


def test_nothing_added_to_a_cruising_setpoint_sends_it_forward_past_the_cruise():
    """PX4 SITL at 0.7 m/s: the guard's push away from a remembered point beside and behind the
    vehicle took the forward setpoint to 0.713 m/s. Whatever adds to it, the forward speed the
    course hold sends is at most the cruise; slower and sideways setpoints are left as they are."""
    from companion.core.course import forward_within_cruise

    cmd = parse_config({}).command
    over = VelocitySetpoint(cmd.cruise_speed_m_s + 0.013, 0.2, -0.1, 5.0)
    capped = forward_within_cruise(over, cmd)
    assert capped.forward_m_s == cmd.cruise_speed_m_s
    assert (capped.right_m_s, capped.down_m_s, capped.yaw_rate_deg_s) == (0.2, -0.1, 5.0)
    slow = VelocitySetpoint(0.3, -0.4, 0.0, 0.0)
    assert forward_within_cruise(slow, cmd) is slow

