"""The motion of the reported position that the reported velocity does not explain.

PX4 and ArduPilot fly a velocity setpoint against their own velocity estimate. When that estimate is
off (PX4 SITL's EKF2 with SIH's GPS: ~0.1-0.2 m/s rms; indoors on optical flow, more), the position
the autopilot reports moves otherwise than the velocity it reports, while the vehicle's map and goal
live in that position. :class:`TrackWatch` measures the difference over a short window; the local
stack (:class:`~companion.core.planner.stack.LocalStack`) plans with it and takes it off the
setpoint, so that the vehicle moves in its reported position as planned. Pure: no clock, no I/O.
"""

from __future__ import annotations

import math

import numpy as np

#: Unexplained motion below this is none, m/s, and more is counted less this: the trapezoid over the
#: reported samples differs from the autopilot's own integration by ~1e-4 m/s where nothing drifts,
#: and a still world must leave every setpoint as it was (the closed loop amplifies any nudge).
TRACK_DEADBAND_M_S = 0.02
#: One sample's position moving more than this beyond what the reported velocity explains, metres,
#: is an estimator's reset (a GPS jump, a new origin), not motion: the window starts again there.
TRACK_RESET_STEP_M = 0.25
#: Samples kept (frames; setpoint calls): the longest window (2 s) at up to 120 a second (the service
#: sends a setpoint per frame besides its 20 Hz stream).
_CAPACITY = 256


class _Ring:
    """Fixed-size ring of float rows (no allocation per sample)."""

    def __init__(self, width: int) -> None:
        self._rows = np.full((_CAPACITY, width), np.nan)
        self._next = 0
        self._count = 0

    def clear(self) -> None:
        self._count = 0

    def push(self, *values: float) -> None:
        self._rows[self._next] = values
        self._next = (self._next + 1) % _CAPACITY
        self._count = min(self._count + 1, _CAPACITY)

    def last(self) -> np.ndarray | None:
        return None if self._count == 0 else self._rows[(self._next - 1) % _CAPACITY]

    def since(self, t0_s: float) -> np.ndarray:
        """The rows whose first column is >= ``t0_s``, oldest first (a copy)."""
        idx = (self._next - 1 - np.arange(self._count)) % _CAPACITY
        rows = self._rows[idx[::-1]]
        return rows[rows[:, 0] >= t0_s]


class TrackWatch:
    """The motion of the reported position that the reported velocity does not explain, m/s.

    The local map, the goal and the camera's rendered world in the simulators all live in the
    position the autopilot reports. PX4's position can move a tenth of a m/s or more otherwise than
    the velocity it reports (over 1 s windows, steady flight or not), and the kinematic simulator's
    drift is of that kind. So the local stack plans with the reported velocity plus this (at most
    ``vehicle.odometry_drift_m_s``). Pure: time is passed in; the samples live in a fixed ring."""

    def __init__(self, axes: int = 2) -> None:
        """``axes``: 2, north and east; 3, down too."""
        if axes not in (2, 3):
            raise ValueError(f"TrackWatch axes must be 2 or 3, not {axes}")
        self._n = axes
        self._rows = _Ring(1 + 2 * axes)  # time s, position m per axis, velocity m/s per axis

    def reset(self) -> None:
        """Forget every sample (a new engagement)."""
        self._rows.clear()

    def observe(self, now_s: float, position_ned_m: np.ndarray | None, velocity_ned_m_s: np.ndarray | None) -> None:
        """The reported position (float ``(3,)`` NED metres) and velocity (float ``(3,)`` NED m/s) at
        ``now_s`` seconds; a missing or non-finite one, or a time not after the last, is not kept."""
        if position_ned_m is None or velocity_ned_m_s is None or not math.isfinite(now_s):
            return
        n = self._n
        p = np.asarray(position_ned_m, dtype=np.float64).reshape(-1)
        v = np.asarray(velocity_ned_m_s, dtype=np.float64).reshape(-1)
        if p.size < n or v.size < n or not (np.all(np.isfinite(p[:n])) and np.all(np.isfinite(v[:n]))):
            return
        last = self._rows.last()
        if last is not None and now_s <= last[0]:
            return
        if last is not None:
            step = p[:n] - last[1 : 1 + n] - 0.5 * (v[:n] + last[1 + n :]) * (now_s - last[0])
            if float(np.linalg.norm(step)) > TRACK_RESET_STEP_M:
                self._rows.clear()
        self._rows.push(float(now_s), *(float(x) for x in p[:n]), *(float(x) for x in v[:n]))

    def unexplained_m_s(self, now_s: float, window_s: float, max_m_s: float) -> np.ndarray | None:
        """float ``(axes,)`` north, east (and down) m/s: over the samples of the last ``window_s`` seconds before
        ``now_s``, the position's change less the reported velocity's integral (trapezoid), per second
        (a least-squares slope over the samples), shortened by :data:`TRACK_DEADBAND_M_S` and at most
        ``max_m_s`` long; None with fewer than 3
        samples since the window began or the position last jumped (:data:`TRACK_RESET_STEP_M`),
        spanning under half the window, or within the dead band."""
        if window_s <= 0.0:
            return None
        rows = self._rows.since(now_s - window_s)
        if len(rows) < 3:
            return None
        t = rows[:, 0]
        span = float(t[-1] - t[0])
        if span < 0.5 * window_s:
            return None
        # The position less the velocity's running integral (trapezoid) is what the velocity does not
        # explain; its slope, fitted over every sample rather than read from the two ends, is the
        # unexplained motion: telemetry timed by its arrival jitters by tens of milliseconds.
        n = self._n
        vel = rows[:, 1 + n :]
        integral = np.concatenate([np.zeros((1, n)), np.cumsum(0.5 * (vel[1:] + vel[:-1]) * np.diff(t)[:, None], axis=0)])
        d = rows[:, 1 : 1 + n] - integral
        tc = t - t.mean()
        unexplained = (tc @ (d - d.mean(axis=0))) / float(tc @ tc)
        norm = float(np.linalg.norm(unexplained))
        if norm <= TRACK_DEADBAND_M_S:
            return None
        return unexplained * (min(norm - TRACK_DEADBAND_M_S, max_m_s) / norm)
