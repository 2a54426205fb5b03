"""The camera's check on the velocity estimate: closing on what is ahead faster than the vehicle says.

PX4 and ArduPilot fly a velocity setpoint against their own velocity estimate. When that estimate is
off (PX4 SITL's EKF2 with SIH's GPS: ~0.1-0.2 m/s rms; indoors on optical flow, more), the vehicle
drifts while the velocity it reports matches the setpoint, so nothing commanded from that estimate
corrects it, and the brake's position hold drifts with it. The camera sees the truth: for a static
surface, the depth (the distance along the optical axis) of any point falls at exactly the forward
speed, wherever the point is in the view; a yaw rate ``w`` adds ``w * x`` for a point ``x`` metres
to the side, a quarter of the depth at most in the centre region (its half-width at the ZED's ~85
deg view). So while the vehicle turns slowly, how fast the centre region's depth falls, less the
forward speed the vehicle reports, is the forward drift (or something coming closer).

:class:`ClosingWatch` estimates that over a short window, in time passed in, and holds it for a while
along the heading it was measured on (:meth:`ClosingWatch.drift`); course hold takes it off the
setpoint in the body frame (:meth:`~companion.core.course.CourseHold.setpoint`), so that the vehicle
flies what was asked of it (``command.unseen_closing_range_m``, 1.5 m; 0 = off). Pure: no clock, no
I/O.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from companion.config.core import CommandConfig

#: The centre region's half-width as a fraction of its depth (one third of an ~85 deg view: +-14 deg,
#: tan = 0.25): how far to the side a point of it can be, for the yaw rate's share of its depth change.
_CENTRE_HALF_WIDTH_PER_M = 0.25
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


class ClosingWatch:
    """Unseen forward motion toward what the centre region sees: the rate the centre's depth falls,
    less the forward speed reported, m/s (:meth:`unseen_closing_m_s`), over the last
    ``command.unseen_closing_window_s`` of frames.

    Feed every frame once (:meth:`observe_frame`: its capture time, the centre's refined depth, the
    heading then) and every setpoint's reported velocity (:meth:`observe_velocity`). The window
    restarts where the centre's depth is unknown, beyond ``unseen_closing_range_m``, or jumps by more
    than ``unseen_closing_max_step_m`` beyond what the reported motion explains in one frame (another
    surface came into the region)."""

    def __init__(self) -> None:
        self._frames = _Ring(3)  # capture time s, centre depth m, yaw rad
        self._speeds = _Ring(2)  # time s, reported forward speed m/s
        self._held: tuple[float, float, float] | None = None  # m/s, heading rad, until s
        self._unseen_m_s = 0.0  # measured at the newest frame (it changes only with a frame)

    def reset(self) -> None:
        """Forget every sample (a new engagement)."""
        self._frames.clear()
        self._speeds.clear()
        self._held = None
        self._unseen_m_s = 0.0

    def observe_velocity(self, now_s: float, forward_m_s: float | None) -> None:
        """The forward speed the vehicle reports (body x, m/s) at ``now_s``; None or not finite: none."""
        if forward_m_s is not None and math.isfinite(forward_m_s) and math.isfinite(now_s):
            self._speeds.push(float(now_s), float(forward_m_s))

    def observe_frame(self, capture_s: float, centre_depth_m: float, yaw_rad: float | None, cmd: CommandConfig) -> None:
        """A new frame's centre depth (metres, NaN unknown) seen at ``capture_s`` facing ``yaw_rad``,
        and the measurement with it (:meth:`unseen_closing_m_s`: the speeds it uses are those
        reported up to the frame, so it is made once here). The same capture time again changes
        nothing."""
        last = self._frames.last()
        if last is not None and capture_s <= last[0]:
            return
        if (
            yaw_rad is None
            or not math.isfinite(yaw_rad)
            or not math.isfinite(centre_depth_m)
            or centre_depth_m > cmd.unseen_closing_range_m
        ):
            self._frames.clear()
            self._unseen_m_s = 0.0
            return
        if last is not None:
            dt = capture_s - last[0]
            speed = self._mean_speed(last[0], capture_s)
            explained = (speed or 0.0) * dt
            if dt > 2.0 * cmd.unseen_closing_window_s or abs((last[1] - centre_depth_m) - explained) > cmd.unseen_closing_max_step_m:
                self._frames.clear()
        self._frames.push(float(capture_s), float(centre_depth_m), float(yaw_rad))
        self._unseen_m_s = self._measure(cmd)

    def _mean_speed(self, t0_s: float, t1_s: float) -> float | None:
        rows = self._speeds.since(t0_s)
        rows = rows[rows[:, 0] <= t1_s] if len(rows) else rows
        if len(rows) == 0:
            last = self._speeds.last()
            return None if last is None else float(last[1])
        return float(rows[:, 1].mean())

    def drift(self, now_s: float, cmd: CommandConfig) -> tuple[float, float] | None:
        """The unseen drift now: (m/s, the heading it points along, radians), or None.

        Measured (:meth:`unseen_closing_m_s`) while it can be; then held for
        ``unseen_closing_hold_s`` along the heading it was measured on, since the estimate's error
        outlasts the turn that stops the measurement (an escape turns at 30-55 deg/s, and the drift
        that carried the vehicle toward the obstacle carries it on while it turns)."""
        unseen = self.unseen_closing_m_s(cmd)
        last = self._frames.last()
        if unseen > 0.0 and last is not None:
            self._held = (unseen, float(last[2]), float(last[0]) + cmd.unseen_closing_hold_s)
            return unseen, float(last[2])
        if self._held is not None and now_s <= self._held[2]:
            return self._held[0], self._held[1]
        self._held = None
        return None

    def unseen_closing_m_s(self, cmd: CommandConfig) -> float:
        """The forward drift toward the centre's surface the reported velocity does not show, m/s, as
        measured at the newest frame (:meth:`_measure`); 0 when off (``unseen_closing_range_m`` 0)."""
        return self._unseen_m_s if cmd.unseen_closing_range_m > 0.0 else 0.0

    def _measure(self, cmd: CommandConfig) -> float:
        """The forward drift toward the centre's surface the reported velocity does not show, m/s, or
        0: off (``unseen_closing_range_m`` 0), too few frames (4, over half the window), turning
        faster than ``unseen_closing_max_yaw_rate_deg_s``, or below ``unseen_closing_min_m_s``. At most
        ``max_unseen_closing_counter_m_s``. The centre's depth must itself fall at
        ``unseen_closing_min_m_s`` or more."""
        if cmd.unseen_closing_range_m <= 0.0:
            return 0.0
        last = self._frames.last()
        if last is None:
            return 0.0
        rows = self._frames.since(last[0] - cmd.unseen_closing_window_s)
        if len(rows) < 4 or rows[-1, 0] - rows[0, 0] < 0.5 * cmd.unseen_closing_window_s:
            return 0.0
        t, depth, yaw = rows[:, 0], rows[:, 1], rows[:, 2]
        dyaw = np.abs((np.diff(yaw) + math.pi) % (2.0 * math.pi) - math.pi)
        yaw_rate = float(np.max(dyaw / np.diff(t)))
        if math.degrees(yaw_rate) > cmd.unseen_closing_max_yaw_rate_deg_s:
            return 0.0
        speed = self._mean_speed(float(t[0]), float(t[-1]))
        if speed is None:
            return 0.0
        tc = t - t.mean()
        slope = float(np.dot(tc, depth - depth.mean()) / np.dot(tc, tc))
        residual = depth - depth.mean() - slope * tc
        if float(np.sqrt(np.mean(residual * residual))) > cmd.unseen_closing_max_fit_error_m:
            # Not a surface coming steadily nearer: a see-through fence's bars and the room behind
            # them, a plain wall's matches coming and going from frame to frame.
            return 0.0
        closing = -slope
        # The yaw rate's share of the depth change, at its worst for the region, is not drift.
        unseen = closing - speed - yaw_rate * _CENTRE_HALF_WIDTH_PER_M * float(depth.mean())
        # ... and the surface must truly come nearer: backing off from one whose depth does not rise
        # is no danger now (a fence's depth, from its bars, can fall while the vehicle backs off);
        # the drift measured before is held meanwhile (drift()).
        if unseen < cmd.unseen_closing_min_m_s or closing < cmd.unseen_closing_min_m_s:
            return 0.0
        return min(unseen, cmd.max_unseen_closing_counter_m_s)


class TrackWatch:
    """The motion of the reported position that the reported velocity does not explain, m/s.

    The obstacle memory, the course's line and the camera's rendered world in the simulators all
    live in the position the autopilot reports; the guard's distances to remembered points change
    at the rate that position moves. PX4's position can move a tenth of a m/s or more otherwise
    than the velocity it reports (over 1 s windows, steady flight or not), and the kinematic
    simulator's drift is of that kind. So the guard and the motion
    brake can use the reported velocity plus this (``command.track_velocity_window_s``). Pure: time
    is passed in; the samples live in a fixed ring."""

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
