"""Moments of PX4 SITL flights that went wrong, replayed in the kinematic simulator (``--start``)."""

from __future__ import annotations

import math

import pytest

from companion.config import parse_config
from companion.core.pose import Pose
from companion.sim.courses import make_course
from companion.sim.loop import fly
from companion.sim.scoring import Outcome


def test_px4_office3_moment_does_not_end_in_the_wall() -> None:
    """PX4 SITL r5, office-3 at 28 s (0.6 m from the right wall, the fence 3.5 m ahead on the left):
    from there the vehicle must not touch anything, whatever else it does. StereoBM aliases the
    fence at the edge of its band; what the alias puts on the map follows the vehicle and must not
    push it into the right wall."""
    cfg = parse_config({"stereo": {"backend": "opencv-bm"}})
    start = Pose.at(0.86, 1.54, 1.76, math.radians(-5.6))
    course = make_course("office", 3).started_at(start, cfg.sim.collision_radius_m)
    result = fly(course, cfg)
    assert result.outcome is not Outcome.COLLISION, result.reason


def test_arducopter_s_late_response_does_not_carry_it_into_a_door_s_leaf() -> None:
    """ArduPilot SITL flights at 3 m/s grazed door jambs. ArduCopter follows a velocity setpoint about
    0.36 s late (a fit of its logs: delay 0.36 s, lag 0.39 s, 2.75 m/s²), and with the service's own
    0.12 s the simulator flies office-0 the same way: in the door frame the planner chose a line that
    the vehicle's velocity would have swung clear of, but it was still chasing the setpoint sent
    before, and carried on sideways into the open leaf. The planner predicts the swing from the
    setpoint in flight too."""
    cfg = parse_config(
        {"sim": {"response_delay_s": 0.36, "velocity_time_constant_s": 0.39, "max_horizontal_accel_m_s2": 2.75,
                 "slow_response_fraction": 0.0, "processing_latency_s": 0.12}}
    )
    result = fly(make_course("office", 0), cfg)
    assert result.outcome is Outcome.GOAL, result.reason


def test_a_turn_within_arducopter_s_delay_does_not_swing_it_onto_a_door_jamb() -> None:
    """office-17000 on ArduCopter's fitted vehicle with StereoBM met its door's jamb at 3 m/s while a
    simulator turned each body-frame setpoint into NED with the yaw the vehicle had once the 0.36 s
    delay had passed: turning at 60 deg/s toward the door, every setpoint flew 20 deg further round
    than sent, and the vehicle drifted onto the jamb. ArduCopter and PX4 turn it on receipt; so does
    the simulator, and the flight reaches the goal."""
    cfg = parse_config(
        {"stereo": {"backend": "opencv-bm"},
         "sim": {"response_delay_s": 0.36, "velocity_time_constant_s": 0.39, "max_horizontal_accel_m_s2": 2.75,
                 "slow_response_fraction": 0.0, "processing_latency_s": 0.12}}
    )
    result = fly(make_course("office", 17000), cfg)
    assert result.outcome is Outcome.GOAL, result.reason


def test_a_block_whose_way_under_meets_the_floor_is_passed_under() -> None:
    """pitch-21005 (the GPU matcher's disparities, made bit for bit by ``cpu-sgm``; 0.14 m/s drift): an
    overhead block with its bottom at 1.37 m, below the vehicle's centre at its 1.5 m altitude. Every
    line that fits under it meets the floor first; scored as ending there, closed, the planner flew up
    and down along the block until the no-progress watchdog held it. A descent cut by the floor is
    scored on the path that levels off along it, and the flight passes under to the goal."""
    cfg = parse_config({"stereo": {"backend": "cpu-sgm"}, "sim": {"drift_speed_m_s": 0.14}})
    result = fly(make_course("pitch", 21005), cfg)
    assert result.outcome is Outcome.GOAL, result.reason
    assert result.min_clearance_m > 0.0
