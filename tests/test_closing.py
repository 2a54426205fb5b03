"""The camera's check on the velocity estimate (companion/core/closing.py) and course hold's use of it:
the centre's depth falling faster than the reported forward speed is unseen drift, and it comes off
the setpoint."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import parse_config
from companion.core.closing import ClosingWatch
from companion.core.course import CourseHold
from companion.core.types import REGION_INDEX, Decision, DecisionKind, VelocitySetpoint

FPS = 15.0
ON = {"command": {"unseen_closing_range_m": 1.5}}
OFF = {"command": {"unseen_closing_range_m": 0.0}}
BRAKE = Decision(kind=DecisionKind.BRAKE, yaw=0.0, pitch=0.0, speed_fraction=0.0, reason="centre blocked")


def _cmd(**command):
    return parse_config({"command": {**ON["command"], **command}}).command


def _feed(watch, cmd, frames, *, depth0_m=1.4, true_closing_m_s=0.65, reported_m_s=0.2, yaw_rate_deg_s=0.0, t0_s=0.0):
    """``frames`` frames at 15 fps: the centre depth falls at ``true_closing_m_s`` while the vehicle
    reports ``reported_m_s`` forward, turning at ``yaw_rate_deg_s``. Returns the last capture time."""
    t = t0_s
    for k in range(frames):
        t = t0_s + k / FPS
        watch.observe_velocity(t, reported_m_s)
        watch.observe_velocity(t + 0.03, reported_m_s)
        watch.observe_frame(t, depth0_m - true_closing_m_s * (t - t0_s), math.radians(yaw_rate_deg_s) * t, cmd)
    return t


def test_the_centre_closing_faster_than_the_reported_speed_is_unseen_drift():
    cmd = _cmd()
    w = ClosingWatch()
    _feed(w, cmd, 3)
    assert w.unseen_closing_m_s(cmd) == 0.0  # too few frames yet
    _feed(w, cmd, 8)
    assert w.unseen_closing_m_s(cmd) == pytest.approx(0.45, abs=1e-6)


def test_no_drift_when_the_depth_falls_as_the_reported_speed_says_or_slower():
    cmd = _cmd()
    for closing in (0.5, 0.4, 0.0):
        w = ClosingWatch()
        _feed(w, cmd, 10, true_closing_m_s=closing, reported_m_s=0.5)
        assert w.unseen_closing_m_s(cmd) == 0.0


def test_small_unseen_closing_is_left_alone_and_a_large_one_is_capped():
    cmd = _cmd()
    w = ClosingWatch()
    _feed(w, cmd, 10, true_closing_m_s=0.3, reported_m_s=0.2)  # 0.1 m/s: noise, the LUT's scale
    assert w.unseen_closing_m_s(cmd) == 0.0
    w = ClosingWatch()
    _feed(w, cmd, 6, true_closing_m_s=1.2, reported_m_s=0.0, depth0_m=1.45)
    assert w.unseen_closing_m_s(cmd) == pytest.approx(cmd.max_unseen_closing_counter_m_s)


def test_nothing_when_off_beyond_the_range_and_while_turning_fast():
    assert parse_config({}).command.unseen_closing_range_m == 1.5  # on by default
    off = parse_config(OFF).command
    w = ClosingWatch()
    _feed(w, off, 10)
    assert w.unseen_closing_m_s(off) == 0.0
    cmd = _cmd()
    w = ClosingWatch()
    _feed(w, cmd, 10, depth0_m=2.5)  # 2.5 -> 1.9 m: the centre never nearer than 1.5 m
    assert w.unseen_closing_m_s(cmd) == 0.0
    w = ClosingWatch()
    _feed(w, cmd, 10, yaw_rate_deg_s=30.0)  # an escape sweeping the region over other surfaces
    assert w.unseen_closing_m_s(cmd) == 0.0
    w = ClosingWatch()
    _feed(w, cmd, 10, yaw_rate_deg_s=10.0)  # slow turns still measure (less the yaw's share)
    assert 0.3 < w.unseen_closing_m_s(cmd) < 0.45


def test_another_surface_stepping_into_the_region_restarts_the_window():
    cmd = _cmd()
    w = ClosingWatch()
    t = _feed(w, cmd, 8, true_closing_m_s=0.2, reported_m_s=0.2)
    w.observe_velocity(t + 1 / FPS, 0.2)
    w.observe_frame(t + 1 / FPS, 0.7, 0.0, cmd)  # 0.55 m nearer in one frame: a box's edge came in
    assert w.unseen_closing_m_s(cmd) == 0.0


def test_a_measured_drift_is_held_along_its_heading_while_an_escape_turns():
    cmd = _cmd()
    w = ClosingWatch()
    t = _feed(w, cmd, 8)
    drift = w.drift(t, cmd)
    assert drift is not None and drift[0] == pytest.approx(0.45, abs=1e-6) and drift[1] == pytest.approx(0.0)
    # the escape turns at 50 deg/s: nothing more is measured, the drift is held for unseen_closing_hold_s
    for k in range(1, 5):
        w.observe_velocity(t + k / FPS, 0.2)
        w.observe_frame(t + k / FPS, 1.0 + 0.3 * k, math.radians(50.0) * k / FPS, cmd)
    assert w.unseen_closing_m_s(cmd) == 0.0
    assert w.drift(t + 4 / FPS, cmd) == pytest.approx((0.45, 0.0), abs=1e-6)
    assert w.drift(t + cmd.unseen_closing_hold_s + 0.01, cmd) is None


def _hold_setpoint(hold, cmd, t, depth_m, *, yaw=0.0, age_s=0.0, reported_forward_m_s=0.0, guard_m=None, memory_cfg=None):
    depths = np.full(9, 3.0)
    depths[REGION_INDEX["center"]] = depth_m
    hold.observe(BRAKE, t - age_s, np.zeros(3))
    velocity = np.array([reported_forward_m_s * math.cos(yaw), reported_forward_m_s * math.sin(yaw), 0.0])
    return hold.setpoint(
        BRAKE,
        t,
        age_s,
        cmd,
        position_ned_m=np.zeros(3),
        yaw_rad=yaw,
        velocity_ned_m_s=velocity,
        region_depths_m=depths,
        guard_m=guard_m,
        memory_cfg=memory_cfg,
    )


def test_course_hold_takes_the_unseen_drift_off_the_brake_and_turns_it_with_the_body():
    cmd = _cmd()
    hold = CourseHold()
    hold.engage(np.zeros(3), 0.0)
    sp = VelocitySetpoint()
    for k in range(12):  # the vehicle holds (reports 0 m/s) but the wall 1.4 m ahead comes 0.3 m/s nearer
        t = k / FPS
        sp = _hold_setpoint(hold, cmd, t, 1.4 - 0.3 * t)
    assert sp.forward_m_s == pytest.approx(-0.3, abs=1e-6)
    assert sp.right_m_s == pytest.approx(0.0, abs=1e-6)
    assert hold.unseen_drift_m_s == pytest.approx(0.3, abs=1e-6)  # what the health message reports
    # turned 90 deg right (an escape): the drift still points north, now to the vehicle's left
    t = 12 / FPS
    sp = _hold_setpoint(hold, cmd, t, 2.5, yaw=math.radians(90.0))
    assert sp.forward_m_s == pytest.approx(0.0, abs=1e-6)
    assert sp.right_m_s == pytest.approx(0.3, abs=1e-6)
    # a stale frame's zero stays zero
    assert _hold_setpoint(hold, cmd, t + 0.1, 2.5, yaw=math.radians(90.0), age_s=0.9).is_zero


def test_off_or_with_nothing_unseen_the_setpoints_are_unchanged():
    on, off = _cmd(), parse_config(OFF).command
    a, b = CourseHold(), CourseHold()
    a.engage(np.zeros(3), 0.0)
    b.engage(np.zeros(3), 0.0)
    for k in range(12):
        t = k / FPS
        assert _hold_setpoint(a, off, t, 1.4 - 0.3 * t) == _hold_setpoint(b, on, t, 1.4)


def _approach(cmd, drift_m_s):
    """A vehicle braked 1.2 m before a wall, its velocity estimate blind to a constant drift toward it:
    the closest its centre comes to the wall, metres. Velocity lags the setpoint by 0.85 s (PX4)."""
    hold = CourseHold()
    hold.engage(np.zeros(3), 0.0)
    wall_m, x, v, dt = 1.2, 0.0, 0.0, 1.0 / 60.0
    closest = wall_m
    next_frame = 0.0
    depth = wall_m
    sp = VelocitySetpoint()
    for k in range(int(6.0 / dt)):
        t = k * dt
        if t >= next_frame:  # a frame at 15 fps
            depth = wall_m - x
            next_frame += 1.0 / FPS
        if k % 3 == 0:  # setpoints at 20 Hz
            sp = _hold_setpoint(hold, cmd, t, depth, reported_forward_m_s=v)
        v += (sp.forward_m_s - v) * dt / 0.85
        x += (v + drift_m_s) * dt
        closest = min(closest, wall_m - x)
    return closest


def test_a_braked_vehicle_drifting_unseen_toward_a_wall_holds_off_it_with_the_check():
    off, on = parse_config(OFF).command, _cmd()
    assert _approach(off, 0.3) < 0.25  # without the check the drift carries it into the wall
    # with it the vehicle backs off, and creeps back each time the counter has stopped the approach
    # (the depth must be falling for the check to act), never within 0.45 m of the wall
    assert _approach(on, 0.3) > 0.45
    assert _approach(on, 0.15) > 0.55
    assert _approach(on, 0.0) == pytest.approx(_approach(off, 0.0))


def test_depths_that_do_not_lie_on_a_line_say_nothing():
    """A see-through fence's bars and the room behind them: the centre's depth jumps about by a few
    centimetres from frame to frame, falling on the whole; no drift is read from it, nor from a
    surface that does not come nearer while the vehicle backs off."""
    cmd = _cmd()
    w = ClosingWatch()
    for k in range(10):
        t = k / FPS
        w.observe_velocity(t, 0.0)
        w.observe_frame(t, 1.2 - 0.3 * t + (0.06 if k % 2 else -0.06), 0.0, cmd)
    assert w.unseen_closing_m_s(cmd) == 0.0
    w = ClosingWatch()
    _feed(w, cmd, 10, true_closing_m_s=0.0, reported_m_s=-0.3)
    assert w.unseen_closing_m_s(cmd) == 0.0


def test_backing_off_the_drift_never_runs_into_a_remembered_point_behind():
    """The counter backs away from what the camera sees, toward what it does not: a remembered point
    0.4 m behind, on that path, stops the backing (the guard's slide past), as it stops any command."""
    cfg = parse_config(ON)
    behind = np.array([[0.4, -1.0, 0.0, 0.0]])  # distance m, unit forward, unit right, may push (no)
    hold = CourseHold()
    hold.engage(np.zeros(3), 0.0)
    sp = VelocitySetpoint()
    for k in range(12):
        t = k / FPS
        sp = _hold_setpoint(hold, cfg.command, t, 1.4 - 0.3 * t, guard_m=behind, memory_cfg=cfg.memory)
    assert hold.unseen_drift_m_s == pytest.approx(0.3, abs=1e-6)
    assert sp.forward_m_s >= -1e-9
