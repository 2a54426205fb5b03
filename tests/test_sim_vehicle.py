"""The simulated multicopter: lag and acceleration limits, frames and signs, modes, VehicleLink conformance."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from companion.sim.render import Pose, Scene
from companion.core.types import VelocitySetpoint
from companion.errors import VehicleError
from companion.interfaces import CameraSource, VehicleLink
from companion.sim.vehicle import SimVehicle, VehicleModel, VehicleParams, wrap_angle_rad

DT = 0.005


def _run(model: VehicleModel, seconds: float) -> list[tuple[float, np.ndarray, float]]:
    """(time, velocity NED, yaw rate) after every step."""
    out = []
    for _ in range(int(round(seconds / DT))):
        model.step(DT)
        out.append((model.time_s, model.velocity_ned_m_s.copy(), model.yaw_rate_rad_s))
    return out


def test_velocity_follows_a_first_order_lag_when_the_limit_is_not_reached() -> None:
    p = VehicleParams(velocity_time_constant_s=0.4, max_horizontal_accel_m_s2=100.0)
    m = VehicleModel(p, Pose.at(0, 0, 2))
    m.command(VelocitySetpoint(forward_m_s=1.0))
    for t, v, _ in _run(m, 2.0):
        assert v[0] == pytest.approx(1.0 - math.exp(-t / 0.4), abs=1e-9)
        assert abs(v[1]) < 1e-12 and v[2] == 0.0


def test_a_response_delay_shifts_the_lag_and_keeps_the_order_of_setpoints() -> None:
    """With ``response_delay_s`` the same first-order response starts that much later; setpoints
    commanded in between take effect in their order, each the delay after it was sent."""
    p = VehicleParams(velocity_time_constant_s=0.4, max_horizontal_accel_m_s2=100.0, response_delay_s=0.1)
    m = VehicleModel(p, Pose.at(0, 0, 2))
    m.command(VelocitySetpoint(forward_m_s=1.0))
    for t, v, _ in _run(m, 1.0):
        expected = 0.0 if t <= 0.1 + DT else 1.0 - math.exp(-(t - 0.1 - DT) / 0.4)
        assert v[0] == pytest.approx(expected, abs=2e-2)
    m.command(VelocitySetpoint(forward_m_s=0.0))
    v_then = m.velocity_ned_m_s[0]
    _run(m, 0.09)
    assert m.velocity_ned_m_s[0] > v_then  # still the old setpoint
    _run(m, 0.5)
    assert m.velocity_ned_m_s[0] < v_then


def test_a_slow_share_of_the_step_leaves_a_creep_after_a_stop() -> None:
    """PX4 SITL, asked to stop from 3 m/s, still moved at 0.2-0.4 m/s seconds later (its velocity
    integrator); with ``slow_response_fraction`` the model does too, and without it it does not."""
    def after_stop(fraction: float) -> tuple[float, float]:
        p = VehicleParams(velocity_time_constant_s=0.44, max_horizontal_accel_m_s2=100.0,
                          slow_response_fraction=fraction, slow_response_time_constant_s=8.0)
        m = VehicleModel(p, Pose.at(0, 0, 2))
        m.command(VelocitySetpoint(forward_m_s=3.0))
        _run(m, 20.0)
        m.command(VelocitySetpoint())
        x0 = m.position_ned_m[0]
        _run(m, 2.0)
        return float(m.velocity_ned_m_s[0]), float(m.position_ned_m[0] - x0)

    v_plain, d_plain = after_stop(0.0)
    v_slow, d_slow = after_stop(0.22)
    assert v_plain < 0.05
    assert 0.3 < v_slow < 0.7  # 0.22 of the step left, decaying over 8 s
    assert d_slow > d_plain + 0.6


def test_acceleration_limits_hold_horizontally_vertically_and_in_yaw() -> None:
    p = VehicleParams(velocity_time_constant_s=0.05, max_horizontal_accel_m_s2=2.0, max_vertical_accel_m_s2=1.0,
                      yaw_rate_time_constant_s=0.05, max_yaw_accel_deg_s2=90.0)
    m = VehicleModel(p, Pose.at(0, 0, 2, yaw_rad=0.3))
    m.command(VelocitySetpoint(forward_m_s=3.0, right_m_s=2.0, down_m_s=-2.0, yaw_rate_deg_s=60.0))
    rows = _run(m, 3.0)
    prev_v, prev_r = np.zeros(3), 0.0
    for _, v, r in rows:
        dv = (v - prev_v) / DT
        assert math.hypot(dv[0], dv[1]) <= 2.0 + 1e-9
        assert abs(dv[2]) <= 1.0 + 1e-9
        assert abs(math.degrees(r - prev_r) / DT) <= 90.0 + 1e-6
        prev_v, prev_r = v, r
    # Limited, not stuck: after 0.5 s the speed grew at the limit.
    assert math.hypot(*rows[99][1][:2]) == pytest.approx(1.0, rel=0.02)
    assert m.velocity_ned_m_s[2] == pytest.approx(-2.0, abs=0.02)
    assert math.degrees(m.yaw_rate_rad_s) == pytest.approx(60.0, abs=0.5)
    # The setpoint became a NED velocity when it was commanded: turning does not move it.
    assert math.hypot(*m.velocity_ned_m_s[:2]) == pytest.approx(math.hypot(3.0, 2.0), rel=0.01)
    # Sent again every 50 ms as the service does while turning at 60 deg/s, 3.6 m/s would need
    # 3.8 m/s² of centripetal acceleration: it lags behind.
    for _ in range(40):
        m.command(VelocitySetpoint(forward_m_s=3.0, right_m_s=2.0, down_m_s=-2.0, yaw_rate_deg_s=60.0))
        _run(m, 0.05)
    assert math.hypot(*m.velocity_ned_m_s[:2]) < 0.95 * math.hypot(3.0, 2.0)


def test_body_frame_setpoints_map_to_ned_with_the_yaw_when_commanded() -> None:
    p = VehicleParams(velocity_time_constant_s=0.05, max_horizontal_accel_m_s2=50.0, max_vertical_accel_m_s2=50.0)
    m = VehicleModel(p, Pose.at(0, 0, 2, yaw_rad=math.pi / 2))  # facing east
    m.command(VelocitySetpoint(forward_m_s=1.0, right_m_s=0.5, down_m_s=0.2))
    _run(m, 1.0)
    v = m.velocity_ned_m_s
    assert v[1] == pytest.approx(1.0, abs=1e-3)  # forward = east
    assert v[0] == pytest.approx(-0.5, abs=1e-3)  # right of east = south
    assert v[2] == pytest.approx(0.2, abs=1e-3)  # down: altitude falls
    assert m.altitude_m < 2.0


def test_a_delayed_setpoint_flies_where_it_was_meant_while_the_vehicle_turns() -> None:
    """An autopilot turns a body-frame setpoint into NED on receipt; its response delay acts after
    that. A vehicle turning at 90 deg/s while a setpoint waits out a 0.36 s delay must fly it in the
    NED direction of the moment it was sent, not 32 deg further round (the yaw when it acts)."""
    p = VehicleParams(velocity_time_constant_s=0.05, max_horizontal_accel_m_s2=50.0, yaw_rate_time_constant_s=0.01,
                      max_yaw_accel_deg_s2=10000.0, response_delay_s=0.36)
    m = VehicleModel(p, Pose.at(0, 0, 2, yaw_rad=0.0))  # facing north
    m.command(VelocitySetpoint(forward_m_s=1.0, yaw_rate_deg_s=90.0))
    _run(m, 0.36)
    assert abs(math.degrees(m.yaw_rad)) < 1.0  # the turn has not started yet: delayed too
    _run(m, 0.5)
    assert math.degrees(m.yaw_rad) > 30.0  # turning now
    v = m.velocity_ned_m_s
    assert math.degrees(math.atan2(v[1], v[0])) == pytest.approx(0.0, abs=1.0)  # still due north
    np.testing.assert_allclose(m.commanded_velocity_ned_m_s(), [1.0, 0.0, 0.0], atol=1e-12)


def test_yaw_rate_positive_turns_clockwise_and_wraps() -> None:
    m = VehicleModel(VehicleParams(), Pose.at(0, 0, 2, yaw_rad=3.0))
    m.command(VelocitySetpoint(yaw_rate_deg_s=90.0))
    _run(m, 1.0)
    assert -math.pi <= m.yaw_rad < math.pi
    assert wrap_angle_rad(m.yaw_rad - 3.0) > 0.5  # turned right past +pi, wrapped


def test_tilt_follows_acceleration_like_a_multicopter() -> None:
    m = VehicleModel(VehicleParams(), Pose.at(0, 0, 2))
    m.command(VelocitySetpoint(forward_m_s=2.0))
    _run(m, 0.3)
    assert m.pitch_rad < -0.1  # nose down to accelerate forward
    m.command(VelocitySetpoint())
    _run(m, 0.4)
    assert m.pitch_rad > 0.1  # nose up to brake
    flat = VehicleModel(VehicleParams(tilt_with_acceleration=False), Pose.at(0, 0, 2))
    flat.command(VelocitySetpoint(forward_m_s=2.0))
    _run(flat, 0.3)
    assert flat.pitch_rad == 0.0 and flat.roll_rad == 0.0


def test_modes_offboard_needs_a_setpoint_and_hold_stops() -> None:
    v = SimVehicle(VehicleParams(), Pose.at(0, 0, 2))
    with pytest.raises(VehicleError, match="send a setpoint"):
        v.set_offboard()
    v.set_setpoint(VelocitySetpoint(forward_m_s=1.0))
    for _ in range(200):
        v.step(DT)
    assert v.model.speed_m_s < 1e-12  # not in offboard yet: holds position
    v.set_offboard()
    for _ in range(400):
        v.step(DT)
    assert v.model.speed_m_s == pytest.approx(1.0, abs=0.01)
    v.set_hold()
    v.set_setpoint(VelocitySetpoint(forward_m_s=1.0))  # ignored in HOLD
    for _ in range(600):
        v.step(DT)
    assert v.model.speed_m_s < 0.01 and v.state().flight_mode == "HOLD"
    with pytest.raises(VehicleError, match="non-finite"):
        v.set_setpoint(VelocitySetpoint(forward_m_s=math.nan))


def test_params_reject_nonsense() -> None:
    with pytest.raises(ValueError, match="velocity_time_constant_s"):
        VehicleParams(velocity_time_constant_s=0.0)
    with pytest.raises(ValueError, match="dt_s"):
        VehicleModel(VehicleParams(), Pose.at(0, 0, 1)).step(-1.0)


def test_drift_moves_the_position_not_the_velocity_seeded_and_of_the_asked_size() -> None:
    """sim.drift_speed_m_s: the position wanders (PX4's estimate error) while the tracked velocity
    stays at the setpoint; the same seed flies the same drift; the stationary std is as asked."""
    params = VehicleParams(drift_speed_m_s=0.2, drift_time_constant_s=2.0)

    def hover(seed: int, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        m = VehicleModel(params, Pose.at(0, 0, 1.5), seed=seed)
        drift = []
        for _ in range(int(round(seconds / DT))):
            m.step(DT)
            drift.append(m.drift_ned_m_s.copy())
        assert np.all(m.velocity_ned_m_s == 0.0)  # the vehicle "thinks" it hovers
        return m.position_ned_m, np.asarray(drift)

    a, drift = hover(1, 400.0)
    b, _ = hover(1, 400.0)
    c, _ = hover(2, 400.0)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert a[2] == pytest.approx(-1.5) and np.all(drift[:, 2] == 0.0)  # horizontal only
    assert np.std(drift[:, :2], axis=0) == pytest.approx([0.2, 0.2], rel=0.25)
    still = VehicleModel(VehicleParams(), Pose.at(0, 0, 1.5), seed=1)
    _run(still, 2.0)
    assert np.array_equal(still.position_ned_m, [0.0, 0.0, -1.5])  # 0 = no drift
    with pytest.raises(ValueError, match="drift_speed_m_s"):
        VehicleParams(drift_speed_m_s=-0.1)


def test_a_realization_is_another_draw_of_the_same_seeds_drift() -> None:
    """sim.realization: 0 flies the seed's own drift (the draws before realizations existed); another
    number draws another drift for the same seed, the same one every time."""
    params = VehicleParams(drift_speed_m_s=0.2, drift_time_constant_s=2.0, vertical_drift_speed_m_s=0.05)

    def hover(**kw: int) -> np.ndarray:
        m = VehicleModel(params, Pose.at(0, 0, 1.5), **kw)
        _run(m, 20.0)
        return m.position_ned_m

    seed_only = hover(seed=4)
    assert np.array_equal(hover(seed=4, realization=0), seed_only)
    other = hover(seed=4, realization=1)
    assert not np.array_equal(other, seed_only) and np.array_equal(hover(seed=4, realization=1), other)
    assert not np.array_equal(hover(seed=4, realization=2), other)


def test_vertical_drift_moves_the_height_and_leaves_the_horizontal_drift_as_it_was() -> None:
    """sim.vertical_drift_speed_m_s: PX4 in offboard velocity control holds a vertical speed, not a
    height; the horizontal drift of the same seed is unchanged by it."""

    def hover(params: VehicleParams, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        m = VehicleModel(params, Pose.at(0, 0, 1.5), seed=3)
        drift = []
        for _ in range(int(round(seconds / DT))):
            m.step(DT)
            drift.append(m.drift_ned_m_s.copy())
        assert np.all(m.velocity_ned_m_s == 0.0)
        return m.position_ned_m, np.asarray(drift)

    both, drift = hover(VehicleParams(drift_speed_m_s=0.2, vertical_drift_speed_m_s=0.1, drift_time_constant_s=2.0), 400.0)
    flat, flat_drift = hover(VehicleParams(drift_speed_m_s=0.2, drift_time_constant_s=2.0), 400.0)
    assert np.array_equal(drift[:, :2], flat_drift[:, :2]) and np.all(flat_drift[:, 2] == 0.0)
    assert np.std(drift[:, 2]) == pytest.approx(0.1, rel=0.25) and both[2] != pytest.approx(-1.5)
    with pytest.raises(ValueError, match="vertical_drift_speed_m_s"):
        VehicleParams(vertical_drift_speed_m_s=-0.1)


def test_vehicle_link_protocol_and_async_wrappers() -> None:
    v = SimVehicle(VehicleParams(), Pose.at(1.0, 2.0, 1.5, yaw_rad=0.2))
    assert isinstance(v, VehicleLink)

    async def fly() -> None:
        await v.connect(timeout_s=1.0)
        await v.send_setpoint(VelocitySetpoint(forward_m_s=0.5))
        await v.start_offboard()
        for _ in range(100):
            v.step(DT)
        s = v.state()
        assert s.connected and s.armed and s.in_offboard and s.flight_mode == "OFFBOARD"
        assert s.position_ned_m is not None and s.position_ned_m[0] > 1.0
        assert s.attitude_rad is not None and s.attitude_rad[2] == pytest.approx(0.2)
        assert s.timestamp_s == pytest.approx(0.5)
        await v.stop_setpoints()
        for _ in range(600):
            v.step(DT)
        assert v.model.speed_m_s < 0.01 and v.state().in_offboard  # no mode change
        await v.send_setpoint(VelocitySetpoint(forward_m_s=0.5))  # streams again
        v.step(DT)
        assert v.model.speed_m_s > 0.0
        await v.hold()
        assert not v.state().in_offboard
        await v.close()
        await v.close()  # twice is fine
        assert not v.state().connected
        with pytest.raises(VehicleError):
            await v.send_setpoint(VelocitySetpoint())

    asyncio.run(fly())


def test_sim_camera_is_a_camera_source() -> None:
    from companion.core.geometry import StereoGeometry
    from companion.errors import CameraError
    from companion.sim.camera import SimCamera

    g = StereoGeometry.ideal(96, 54, 90.0, 0.12)
    t = {"now": 0.0}
    cam = SimCamera(g, Scene(), lambda: (Pose.at(0, 0, 1.5), t["now"]), noise_std_grey=2.0, fail_after_s=1.0)
    assert isinstance(cam, CameraSource)
    assert cam.eye_size_px == (96, 54)
    with pytest.raises(CameraError, match="before open"):
        cam.read()
    cam.open()
    f0 = cam.read()
    t["now"] = 0.5
    f1 = cam.read()
    assert f0.image.shape == (54, 192, 3) and f0.image.dtype == np.uint8
    assert (f0.seq, f1.seq) == (0, 1) and (f0.timestamp_s, f1.timestamp_s) == (0.0, 0.5)
    t["now"] = 1.0
    with pytest.raises(CameraError, match="stopped delivering"):
        cam.read()
    cam.close()
    cam.close()


def test_an_acceleration_lag_makes_the_velocity_second_order_overshooting_a_little() -> None:
    # Velocity loop 0.56 s and tilt 0.25 s: damping ratio 0.5·sqrt(0.56/0.25) = 0.75, about 3 % over.
    first = VehicleModel(VehicleParams(velocity_time_constant_s=0.56, max_horizontal_accel_m_s2=100.0), Pose.at(0, 0, 2))
    second = VehicleModel(
        VehicleParams(velocity_time_constant_s=0.56, acceleration_time_constant_s=0.25, max_horizontal_accel_m_s2=100.0),
        Pose.at(0, 0, 2),
    )
    for m in (first, second):
        m.command(VelocitySetpoint(right_m_s=1.0))
    a, b = _run(first, 4.0), _run(second, 4.0)
    # It starts later (it must tilt first) ...
    assert b[39][1][1] < 0.75 * a[39][1][1]
    # ... overshoots where the first-order lag never does, and settles on the setpoint.
    assert max(v[1] for _, v, _ in a) <= 1.0 + 1e-9
    assert 1.01 < max(v[1] for _, v, _ in b) < 1.1
    assert b[-1][1][1] == pytest.approx(1.0, abs=0.01)


def test_acceleration_time_constant_must_not_be_negative() -> None:
    with pytest.raises(ValueError, match="acceleration_time_constant_s"):
        VehicleParams(acceleration_time_constant_s=-0.1)
