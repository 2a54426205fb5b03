"""The vehicle model's constants fitted to a step response (companion/sim/stepfit.py), and the
step-response scenario's analysis of a telemetry file (companion/sitl/step_response.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.core.types import VelocitySetpoint
from companion.sim.render import Pose
from companion.sim.stepfit import StepData, fit_steps, step_response
from companion.sim.vehicle import VehicleModel, VehicleParams
from companion.sitl.step_response import analyse, read_csv


def _model_step(params: VehicleParams, start: float, target: float, seconds: float, rate_hz: float = 30.0, delay_s: float = 0.0):
    """The simulator's vehicle flying a forward step, sampled at ``rate_hz`` (the step ``delay_s`` late)."""
    m = VehicleModel(params, Pose((0.0, 0.0, -2.0), 0.0))
    m.command(VelocitySetpoint(start, 0.0, 0.0, 0.0))
    for _ in range(2000):
        m.step(0.005)
    t, v = [], []
    dt = 0.005
    n = int(round(seconds / dt))
    every = int(round(1.0 / (rate_hz * dt)))
    for k in range(n):
        if k * dt >= delay_s:
            m.command(VelocitySetpoint(target, 0.0, 0.0, 0.0))
        if k % every == 0:
            t.append(k * dt)
            v.append(m.velocity_ned_m_s[0])
        m.step(dt)
    return StepData(np.array(t), np.array(v), start, target)


def test_the_closed_form_is_the_simulators_vehicle():
    params = VehicleParams(velocity_time_constant_s=0.5, max_horizontal_accel_m_s2=2.0)
    for a, b in ((0.0, 1.0), (0.0, 3.0), (3.0, 0.0)):
        d = _model_step(params, a, b, 5.0)
        assert np.max(np.abs(step_response(d.t_s, a, b, 0.5, 2.0) - d.value)) < 0.02


def test_the_fit_finds_the_simulators_constants_back():
    """Steps flown by the simulator's own vehicle (0.6 s lag, 2.5 m/s² limit, 0.1 s late) give its constants back."""
    params = VehicleParams(velocity_time_constant_s=0.6, max_horizontal_accel_m_s2=2.5)
    steps = [_model_step(params, a, b, 6.0, delay_s=0.1) for a, b in ((0.0, 1.0), (1.0, 0.0), (0.0, 3.0), (3.0, 0.0))]
    rng = np.random.default_rng(0)
    noisy = [StepData(s.t_s, s.value + rng.normal(0.0, 0.03, s.value.shape), s.start, s.target) for s in steps]
    fit = fit_steps(noisy, with_delay=True)
    assert fit.tau_s == pytest.approx(0.6, abs=0.05)
    assert fit.accel_limit == pytest.approx(2.5, rel=0.1)
    assert fit.delay_s == pytest.approx(0.1, abs=0.03)
    assert fit.accel_reached
    # 1 m/s / 0.6 s < 2.5 m/s²: the limit is never reached, and the fit says so
    small = fit_steps([_model_step(params, 0.0, 1.0, 6.0)], with_delay=False)
    assert small.tau_s == pytest.approx(0.6, abs=0.02)
    assert not small.accel_reached


def test_a_flight_file_is_analysed_step_by_step(tmp_path: Path):
    """The scenario's telemetry file, written by hand: forward 0 -> 2 -> 0 m/s and a yaw-rate step."""
    path = tmp_path / "step-response.csv"
    lines = ["t_s,since_step_s,sp_forward_m_s,sp_right_m_s,sp_yaw_rate_deg_s,forward_m_s,right_m_s,yaw_rate_deg_s"]
    t0 = 0.0
    for sp, axis_value in (((2.0, 0.0, 0.0), 2.0), ((0.0, 0.0, 0.0), 0.0), ((0.0, 2.0, 0.0), 2.0), ((0.0, 0.0, 0.0), 0.0), ((0.0, 0.0, 60.0), 60.0), ((0.0, 0.0, 0.0), 0.0)):
        for k in range(150):
            t = k / 30.0
            lines.append(f"{t0 + t:.4f},{t:.4f},{sp[0]},{sp[1]},{sp[2]},0,0,0")
        t0 += 5.0
    path.write_text("\n".join(lines) + "\n")
    segments = read_csv(path)
    assert [(axis, a, b) for axis, a, b, _ in segments] == [
        ("forward", 0.0, 2.0), ("forward", 2.0, 0.0), ("right", 0.0, 2.0), ("right", 2.0, 0.0), ("yaw", 0.0, 60.0), ("yaw", 60.0, 0.0),
    ]
    result = analyse(segments, path)
    assert set(result.fits) == {"forward", "right", "yaw", "horizontal", "horizontal, first 2 s"}
    assert len(result.lines()) == len(segments) + 1 + 5 + 1
