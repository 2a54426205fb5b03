"""Moments of PX4 SITL flights that went wrong, replayed in the kinematic simulator (``--start``)."""

from __future__ import annotations

import math

import pytest

from companion.config import parse_config
from companion.core.pose import Pose
from companion.sim.courses import make_course
from companion.sim.loop import fly
from companion.sim.scoring import Outcome


@pytest.mark.parametrize(
    "overrides",
    [
        {},  # the defaults: the detour layer and gap centering on, as PX4 SITL r5 flew them
        {  # the reactive controller and course hold alone, as the defaults were until issue 21's runs
            "detour": {"trigger_after_s": 0.0},
            "memory": {"gap_centering_gain_per_s": 0.0},
            "command": {"line_hold_lateral_max_aim_error_deg": 180.0},
        },
    ],
    ids=["defaults", "no-layer"],
)
def test_px4_office3_moment_does_not_end_in_the_wall(overrides: dict) -> None:
    """PX4 SITL r5, office-3 at 28 s (0.6 m from the right wall, the fence 3.5 m ahead on the left):
    from there the vehicle must not touch anything, whatever else it does. StereoBM aliases the
    fence at the edge of its band; the alias's points follow the vehicle, persist, and used to push
    it into the right wall (docs/history.md, fifteenth and sixteenth sessions)."""
    cfg = parse_config({"stereo": {"backend": "opencv-bm"}, **overrides})
    start = Pose.at(0.86, 1.54, 1.76, math.radians(-5.6))
    course = make_course("office", 3).started_at(start, cfg.sim.collision_radius_m)
    result = fly(course, cfg)
    assert result.outcome is not Outcome.COLLISION, result.reason
