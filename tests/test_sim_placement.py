"""Placing a course in an autopilot's local frame, and the Judge shared by the simulator and SITL."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.sim.courses import head_on_course
from companion.core.placement import CoursePlacement
from companion.sim.scoring import Judge, Outcome


def test_placement_round_trips_and_rotates_about_the_vertical() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        placement = CoursePlacement(tuple(rng.uniform(-50, 50, 3)), float(rng.uniform(-math.pi, math.pi)))
        p = rng.uniform(-20, 20, (5, 3))
        np.testing.assert_allclose(placement.position_in_local(placement.position_in_course(p)), p, atol=1e-9)
        # Distances and heights are preserved.
        q = placement.position_in_course(p)
        np.testing.assert_allclose(np.linalg.norm(q[1:] - q[:-1], axis=1), np.linalg.norm(p[1:] - p[:-1], axis=1))
        np.testing.assert_allclose(q[:, 2], p[:, 2] - placement.origin_ned_m[2])


def test_placement_under_a_vehicle_puts_it_at_the_course_start_facing_the_course() -> None:
    placement = CoursePlacement.under(np.array([3.0, -2.0, -0.45]), math.radians(-120.0))
    pose = placement.pose_in_course(np.array([3.0, -2.0, -1.95]), np.array([0.0, 0.0, math.radians(-120.0)]))
    np.testing.assert_allclose(pose.position_ned_m, (0.0, 0.0, -1.5), atol=1e-12)
    assert pose.yaw_rad == pytest.approx(0.0, abs=1e-12)
    # One metre forward along the vehicle's heading is one metre north in the course.
    ahead = np.array([3.0 + math.cos(math.radians(-120.0)), -2.0 + math.sin(math.radians(-120.0)), -1.95])
    np.testing.assert_allclose(placement.position_in_course(ahead), (1.0, 0.0, -1.5), atol=1e-12)
    # A heading that crosses +-180 degrees wraps.
    assert placement.pose_in_course(ahead, np.array([0.0, 0.0, math.radians(170.0)])).yaw_rad == pytest.approx(
        math.radians(-70.0)
    )


def _judge(**kw: float) -> Judge:
    course = head_on_course(0)  # a 0.6 m box 5 m north, goal at 8 m
    return Judge(course, 0.25, kw.get("held_speed", 0.1), kw.get("held_after", 2.0), np.array([0.0, 0.0, -1.5]), 10.0)


def test_judge_reports_the_goal_and_keeps_the_minimum_clearance() -> None:
    j = _judge()
    for k in range(1, 20):
        out = j.update(10.0 + 0.5 * k, np.array([0.5 * k, 1.2, -1.5]), 1.0, 0.0)
        if out is not None:
            break
    assert out is Outcome.GOAL and j.success
    assert j.path_length_m == pytest.approx(np.hypot(0.5, 1.2) + 7.5)  # start -> (0.5, 1.2) -> (8, 1.2)
    # The box's side is 0.3 m east of the line: closest pass 1.2 - 0.3 - 0.25 radius.
    assert j.min_clearance_m == pytest.approx(0.65, abs=1e-9)
    assert j.update(99.0, np.array([5.0, 0.0, -1.5]), 1.0, 0.0) is Outcome.GOAL  # decided stays decided


def test_judge_collision_held_and_timeout() -> None:
    j = _judge()
    assert j.update(11.0, np.array([4.8, 0.0, -1.5]), 1.0, 0.0) is Outcome.COLLISION
    assert "collision" in j.reason and not j.success

    j = _judge(held_after=2.0)
    for k in range(0, 25):
        if j.update(10.0 + 0.1 * k, np.array([3.0, 0.0, -1.5]), 0.02, 0.0) is not None:
            break
    assert j.outcome is Outcome.HELD and j.success  # head-on counts holding as success
    assert "held safely" in j.reason

    j = _judge()
    limit = j.course.time_limit_s
    assert j.update(10.0 + limit - 0.1, np.array([1.0, 0.0, -1.5]), 0.5, 0.0) is None  # counts from start_time_s
    assert j.update(10.0 + limit, np.array([1.1, 0.0, -1.5]), 0.5, 0.0) is Outcome.TIMEOUT


def test_judge_with_a_held_radius_calls_a_wandering_hover_held_but_not_a_creep() -> None:
    course = head_on_course(0)
    start = np.array([3.0, 0.0, -1.5])
    hover = Judge(course, 0.25, 0.05, 2.0, start, 0.0, held_radius_m=0.15)
    rng = np.random.default_rng(0)
    out = None
    for k in range(1, 60):  # +-5 cm of wander at a noisy 0.2 m/s: still in place
        out = hover.update(0.05 * k, start + rng.uniform(-0.05, 0.05, 3), 0.2, 0.0)
        if out is not None:
            break
    assert out is Outcome.HELD and 2.0 <= 0.05 * k <= 2.1
    creep = Judge(course, 0.25, 0.05, 2.0, start, 0.0, held_radius_m=0.15)
    for k in range(1, 60):  # 0.1 m/s towards the box: never held
        assert creep.update(0.05 * k, start + np.array([0.005 * k, 0.0, 0.0]), 0.1, 0.0) is None


def test_judge_with_a_held_radius_does_not_call_a_turn_in_place_held() -> None:
    # A detour's look round: in place, turning at 50 deg/s for 4 s; held only 2 s after the turn ends.
    course = head_on_course(0)
    start = np.array([3.0, 0.0, -1.5])
    j = Judge(course, 0.25, 0.05, 2.0, start, 0.0, held_radius_m=0.15)
    turn = np.radians(50.0)
    for k in range(1, 81):
        assert j.update(0.05 * k, start, 0.0, turn) is None
    out = None
    for k in range(81, 200):
        out = j.update(0.05 * k, start, 0.0, 0.0)
        if out is not None:
            break
    assert out is Outcome.HELD and 0.05 * k >= 4.0 + 2.0 - 0.06
