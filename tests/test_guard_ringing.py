"""The guard's push between two points on opposite sides, flown by the simulator's vehicle model.

With PX4 SITL a strong guard (gain 3 /s, cap 0.8 m/s) rang between a wall and a box 1 m apart until
it touched (r27, corridor-8); the first-order vehicle did not show it, a second-order one does, and
the damped push (``memory.guard_damping_fraction``) calms it."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config.memory import MemoryConfig
from companion.core.memory import apply_guard
from companion.core.types import VelocitySetpoint
from companion.sim.render import Pose
from companion.sim.vehicle import VehicleModel, VehicleParams

GAP_M = 1.0  # a wall and a box 1 m apart, the vehicle between them


def _swing_after_5_s(memory: MemoryConfig, params: VehicleParams) -> float:
    """Largest |sideways offset| from the middle, metres, in seconds 5-10 of a flight started 0.15 m
    off the middle at 0.3 m/s sideways, with only the guard commanding (20 Hz)."""
    model = VehicleModel(params, Pose.at(0.0, 0.15, 1.5))
    model.velocity_ned_m_s[1] = 0.3
    dt, late = 0.005, 0.0
    for i in range(2000):
        if i % 10 == 0:
            y = float(model.position_ned_m[1])
            rows = np.array([[GAP_M / 2 + y, 0.0, -1.0, 1.0], [GAP_M / 2 - y, 0.0, 1.0, 1.0]])
            rows = rows[rows[:, 0] < memory.guard_distance_m]
            v = model.velocity_ned_m_s
            forward, right = apply_guard(0.0, 0.0, rows, memory, (float(v[0]), float(v[1])))
            model.command(VelocitySetpoint(forward_m_s=forward, right_m_s=right))
        model.step(dt)
        if i >= 1000:
            late = max(late, abs(float(model.position_ned_m[1])))
    return late


STRONG = MemoryConfig(guard_gain_per_s=3.0, max_guard_speed_m_s=0.8)
FIRST_ORDER = VehicleParams(velocity_time_constant_s=0.85)
SECOND_ORDER = VehicleParams(velocity_time_constant_s=0.56, acceleration_time_constant_s=0.3)


def test_a_strong_guard_rings_on_a_second_order_vehicle_and_not_on_a_first_order_one() -> None:
    assert _swing_after_5_s(STRONG, FIRST_ORDER) < 0.02
    assert _swing_after_5_s(STRONG, SECOND_ORDER) > 0.15  # a limit cycle: it would touch with drift


@pytest.mark.parametrize(("damping", "swing_m"), [(0.5, 0.15), (1.0, 0.08)])
def test_the_damped_push_calms_the_ringing(damping: float, swing_m: float) -> None:
    damped = STRONG.model_copy(update={"guard_damping_fraction": damping})
    assert _swing_after_5_s(damped, SECOND_ORDER) < swing_m  # undamped: over 0.15 m
