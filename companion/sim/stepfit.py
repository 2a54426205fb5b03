"""The vehicle model's constants fitted to a measured velocity (or yaw-rate) step response.

:class:`~companion.sim.vehicle.VehicleModel` follows a setpoint step from ``v0`` to ``v1`` with a
first-order lag of time constant ``tau`` whose acceleration is clipped to ``a_max``: while
``|v1 - v| / tau > a_max`` the velocity ramps at ``a_max``, then it closes the rest exponentially.
In closed form, with ``D = |v1 - v0|``, ``s = sign(v1 - v0)`` and ``t`` the time since the step less a
pure delay ``delay``:

* ``D / tau <= a_max``: ``v = v1 - (v1 - v0) · exp(-t / tau)``;
* otherwise, for ``t < T1 = (D - a_max · tau) / a_max``: ``v = v0 + s · a_max · t``; after it,
  ``v = v1 - s · a_max · tau · exp(-(t - T1) / tau)``.

:func:`fit_steps` fits ``tau``, ``a_max`` and (optionally) ``delay`` to one or several steps at once
(least squares on the measured samples). Pure: arrays in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

#: Bounds of the fitted constants: time constant s, delay s; the acceleration limit's are the
#: largest step's size times these, per second.
TAU_BOUNDS_S = (0.02, 5.0)
ACCEL_BOUNDS_PER_S = (0.02, 20.0)
DELAY_BOUNDS_S = (0.0, 0.6)


@dataclass(frozen=True)
class StepData:
    """One measured step.

    Attributes:
        t_s: float ``(N,)`` sample times since the setpoint changed, seconds.
        value: float ``(N,)`` the measured velocity (m/s) or yaw rate (deg/s) at those times.
        start: the setpoint before the step (what the vehicle flew then).
        target: the setpoint after it.
    """

    t_s: np.ndarray
    value: np.ndarray
    start: float
    target: float


@dataclass(frozen=True)
class StepFit:
    """Fitted constants.

    Attributes:
        tau_s: first-order time constant, seconds.
        accel_limit: acceleration limit, the value's unit per second (m/s², deg/s²); meaningless
            when no step was large enough to reach it (``accel_reached`` False).
        delay_s: pure delay before the response starts, seconds (0 when not fitted).
        rms: root-mean-square residual, the value's unit.
        accel_reached: some step asked for more than ``accel_limit`` (the limit was measured).
    """

    tau_s: float
    accel_limit: float
    delay_s: float
    rms: float
    accel_reached: bool


def step_response(t_s: np.ndarray, start: float, target: float, tau_s: float, accel_limit: float, delay_s: float = 0.0) -> np.ndarray:
    """The model's response (module doc) at times ``t_s`` (float ``(N,)`` seconds since the step)."""
    t = np.maximum(0.0, np.asarray(t_s, dtype=np.float64) - delay_s)
    d = abs(target - start)
    s = 1.0 if target >= start else -1.0
    if d / tau_s <= accel_limit:
        return target - (target - start) * np.exp(-t / tau_s)
    t1 = (d - accel_limit * tau_s) / accel_limit
    ramp = start + s * accel_limit * t
    tail = target - s * accel_limit * tau_s * np.exp(-np.maximum(0.0, t - t1) / tau_s)
    return np.where(t < t1, ramp, tail)


def _residuals(params: np.ndarray, steps: Sequence[StepData], with_delay: bool) -> np.ndarray:
    tau, accel = float(params[0]), float(params[1])
    delay = float(params[2]) if with_delay else 0.0
    return np.concatenate([step_response(s.t_s, s.start, s.target, tau, accel, delay) - s.value for s in steps])


def fit_steps(steps: Sequence[StepData], with_delay: bool = True, window_s: float | None = None) -> StepFit:
    """Least-squares fit of one ``tau``, one ``a_max`` (and one delay, with ``with_delay``) to every
    step in ``steps`` at once (from a few starting points; the best one wins); with ``window_s``,
    only the samples within that long after each step count.

    Raises:
        ValueError: no step, or a step with fewer than 5 finite samples.
    """
    from scipy.optimize import least_squares

    if not steps:
        raise ValueError("fit_steps: no step to fit")
    clean = []
    for s in steps:
        t = np.asarray(s.t_s, dtype=np.float64)
        v = np.asarray(s.value, dtype=np.float64)
        ok = np.isfinite(t) & np.isfinite(v)
        if window_s is not None:
            ok &= t <= window_s
        if np.count_nonzero(ok) < 5:
            raise ValueError(f"fit_steps: a step {s.start:g} -> {s.target:g} has {np.count_nonzero(ok)} finite samples (needs 5)")
        clean.append(StepData(t[ok], v[ok], float(s.start), float(s.target)))
    largest = max(abs(s.target - s.start) for s in clean)
    accel_lo, accel_hi = ACCEL_BOUNDS_PER_S[0] * largest, ACCEL_BOUNDS_PER_S[1] * largest
    lo = [TAU_BOUNDS_S[0], accel_lo] + ([DELAY_BOUNDS_S[0]] if with_delay else [])
    hi = [TAU_BOUNDS_S[1], accel_hi] + ([DELAY_BOUNDS_S[1]] if with_delay else [])
    best = None
    for tau0 in (0.2, 0.5, 1.0):
        for accel0 in (0.5 * largest / tau0, 2.0 * largest / tau0, 0.9 * accel_hi):
            for delay0 in (0.02, 0.15, 0.3) if with_delay else (None,):
                x0 = [tau0, min(max(accel0, 1.01 * accel_lo), 0.99 * accel_hi)] + ([delay0] if with_delay else [])
                r = least_squares(_residuals, x0, bounds=(lo, hi), args=(clean, with_delay))
                if best is None or r.cost < best.cost:
                    best = r
    assert best is not None
    tau, accel = float(best.x[0]), float(best.x[1])
    delay = float(best.x[2]) if with_delay else 0.0
    n = sum(len(s.t_s) for s in clean)
    rms = math.sqrt(2.0 * float(best.cost) / n)
    reached = any(abs(s.target - s.start) / tau > accel for s in clean)
    return StepFit(tau, accel, delay, rms, reached)
