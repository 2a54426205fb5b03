"""The reported position's motion that the reported velocity does not explain (companion/core/track.py
TrackWatch): the local stack plans with it and takes it off the setpoint (tests/test_planner_local.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.core.track import TRACK_DEADBAND_M_S, TrackWatch

RATE_HZ = 20.0


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
