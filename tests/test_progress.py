"""The progress watchdog and the goal's bookkeeping (companion/core/progress.py): the time since the
vehicle last got a step nearer its goal, along the course or toward a point."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.core.goal import GoalSpec
from companion.core.progress import GoalProgress, ProgressWatch, along_course_m


def test_along_course_is_the_distance_along_the_engagement_heading() -> None:
    origin = np.array([1.0, 2.0, -1.5])
    assert along_course_m(np.array([4.0, 2.0, -3.0]), origin, 0.0) == pytest.approx(3.0)  # north, height ignored
    assert along_course_m(np.array([1.0, 5.0, -1.5]), origin, 0.0) == pytest.approx(0.0)  # abeam
    assert along_course_m(np.array([1.0, 5.0, -1.5]), origin, math.pi / 2) == pytest.approx(3.0)  # facing east
    assert along_course_m(np.array([0.0, 2.0, -1.5]), origin, 0.0) == pytest.approx(-1.0)  # behind


def test_progress_watch_times_the_last_step_toward_the_goal() -> None:
    w = ProgressWatch()
    assert not w.update(0.0, 0.0, 1.0, 10.0) and w.mark_m == 0.0
    assert not w.update(0.9, 9.0, 1.0, 10.0)  # not a step yet
    assert not w.update(1.0, 9.5, 1.0, 10.0) and w.mark_m == 1.0  # a step: the clock restarts
    assert w.stalled_for_s(12.0) == pytest.approx(2.5)
    assert not w.update(-3.0, 19.5, 1.0, 10.0)  # going back is not progress, and the limit is not passed yet
    assert w.update(1.9, 19.6, 1.0, 10.0)  # 10.1 s without a whole step
    # Unknown progress, or the watchdog off (no time): never, and it restarts.
    assert not w.update(None, 30.0, 1.0, 10.0) and w.mark_m is None
    assert not w.update(float("nan"), 31.0, 1.0, 10.0)
    off = ProgressWatch()
    assert not any(off.update(0.0, t, 1.0, 0.0) for t in range(0, 100, 5))


def test_the_progress_is_along_the_course_or_toward_a_point() -> None:
    g = GoalProgress()
    assert g.progress_m(np.zeros(3)) is None  # no course yet
    g.engage(np.array([0.0, 0.0, -1.5]), math.pi / 2)  # facing east: the course
    assert g.progress_m(np.array([1.0, 4.0, -1.5])) == pytest.approx(4.0)
    assert g.status(np.zeros(3))["bearing_deg"] == pytest.approx(90.0)
    g.set_goal(GoalSpec(kind="point", north_m=10.0, east_m=0.0), np.array([0.0, 4.0, -1.5]), 0.0)
    assert g.progress_m(np.array([6.0, 0.0, -1.5])) == pytest.approx(-4.0)  # 4 m to go
    status = g.status(np.array([6.0, 0.0, -1.5]), reached=False)
    assert status["kind"] == "point" and status["distance_m"] == pytest.approx(4.0) and status["bearing_deg"] == pytest.approx(0.0)
    # Back to the course: the heading and line of the engagement, not of the goto.
    g.set_goal(GoalSpec(), np.array([6.0, 0.0, -1.5]), 0.0)
    assert g.progress_m(np.array([6.0, 3.0, -1.5])) == pytest.approx(3.0)
    assert g.progress_m(None) is None


def test_the_watchdog_holds_a_vehicle_that_gets_no_nearer() -> None:
    g = GoalProgress()
    g.engage(np.array([0.0, 0.0, -1.5]), 0.0)
    here = np.array([0.5, 0.0, -1.5])
    assert not any(g.no_progress(here, 0.1 * k, 1.0, 20.0) for k in range(200))
    assert g.no_progress(here, 20.2, 1.0, 20.0)
    g.resume()  # the operator's resume: another full time
    assert not g.no_progress(here, 21.0, 1.0, 20.0) and not g.no_progress(here, 40.0, 1.0, 20.0)


def test_coming_back_down_to_the_goals_altitude_is_progress() -> None:
    """office-40154: the vehicle climbed toward a fence's top, and in front of the door it came back
    down to its altitude at walking pace for twenty seconds with no metre gained over the floor; the
    watchdog held it as it reached the door's height. The height to come back is part of the way."""
    g = GoalProgress()
    g.engage(np.array([0.0, 0.0, -1.5]), 0.0, GoalSpec(kind="point", north_m=14.5, east_m=0.0))
    assert g.progress_m(np.array([10.5, 0.0, -2.7])) == pytest.approx(-4.0 - 1.2)
    t = 0.0
    for k in range(120):  # 1.2 m down in 24 s, in place over the floor
        t = 0.2 * k
        assert not g.no_progress(np.array([10.5, 0.0, -2.7 + 0.01 * k]), t, 1.0, 20.0)


def test_climbing_and_coming_down_again_in_place_is_no_progress() -> None:
    g = GoalProgress()
    g.engage(np.array([0.0, 0.0, -1.5]), 0.0)
    fired = False
    for k in range(300):  # up 1.5 m and down again, twice a minute, over the same spot
        t = 0.1 * k
        climb = 1.5 * abs(math.sin(math.pi * t / 15.0))
        fired = fired or g.no_progress(np.array([0.5, 0.0, -1.5 - climb]), t, 1.0, 20.0)
    assert fired
