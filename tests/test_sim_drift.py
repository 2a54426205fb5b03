"""Flights of the kinematic standard suite with 0.14 m/s drift that used to end in a collision."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import parse_config
from companion.sim.courses import make_course
from companion.sim.loop import fly
from companion.sim.scoring import Outcome


@pytest.mark.parametrize(("kind", "seed"), [("office", 4), ("forest", 6)])
def test_drifting_flights_that_flew_on_into_what_the_camera_saw_no_longer_collide(kind: str, seed: int) -> None:
    """StereoBM and the defaults (the detour layer and gap centering on), 0.14 m/s of drift the
    autopilot's estimate does not show. office-4: turning away from a cabinet the vehicle still flew
    its old course into what its right region read; forest-6 the same at a trunk. The motion brake
    (``command.motion_brake_*``) leans against that motion."""
    cfg = parse_config({"stereo": {"backend": "opencv-bm"}, "sim": {"drift_speed_m_s": 0.14}})
    result = fly(make_course(kind, seed), cfg)
    assert result.outcome is not Outcome.COLLISION, result.reason


def test_a_vehicle_drifting_in_height_keeps_the_goal_s_altitude_through_a_door() -> None:
    """PX4 SITL at 3 m/s climbed 0.8-1.8 m, never came back down and met the wall over a door
    (doorway-1, office-0); an autopilot in offboard velocity control holds a vertical speed, not a
    height (PX4 drifted 0.4 m up in 4 s under zero vertical speed). Here the simulated vehicle drifts in height unseen by its velocity estimate; the local
    planner holds the goal's altitude on the position and counters the drift, and flies through."""
    cfg = parse_config(
        {"stereo": {"backend": "opencv-bm"},
         "sim": {"vertical_drift_speed_m_s": 0.3, "drift_time_constant_s": 20.0}}
    )
    course = make_course("doorway", 1)
    result = fly(course, cfg)
    assert result.outcome is Outcome.GOAL, result.reason
    altitude = -result.log.position_ned_m[:, 2]
    start = -float(course.start.position_ned_m[2])
    off = np.abs(altitude - start)
    # Unchecked, the drift would carry it 1.7 m off in the flight's 5.7 s. A lower line under the
    # door's lintel is the planner's to choose; past the door it heads back to the goal's altitude.
    assert float(np.max(off)) < 0.6
    assert off[-1] < float(np.max(off)) - 0.05
