"""A multicopter that follows body-frame velocity and yaw-rate setpoints, in simulated time.

:class:`VehicleModel` is the pure dynamics: velocity (NED) and yaw rate follow their setpoints with a
first-order lag, limited in acceleration (horizontal, vertical and yaw separately); the body tilts the
way a multicopter must to accelerate (and the hard-mounted camera with it). :class:`SimVehicle` wraps
it as a :class:`~companion.interfaces.VehicleLink` (the interface the daemon drives PX4 through), with
flight modes: outside OFFBOARD (before :meth:`SimVehicle.start_offboard`, after :meth:`SimVehicle.hold`)
the vehicle holds position, i.e. tracks zero velocity.

Frames: world NED (x north, y east, z down, metres); body FRD; yaw positive clockwise seen from
above. A body-frame setpoint is turned into NED with the yaw at the moment it is commanded (level body
frame: the tilt does not rotate it), as PX4 and ArduCopter do with a body-frame
``SET_POSITION_TARGET_LOCAL_NED`` on receipt; the response delay then acts on that NED velocity. A
vehicle turning while its setpoints wait out the delay flies them where they were meant, not turned
by the yaw it has when they act.

Nothing here reads a clock: time advances only through :meth:`VehicleModel.step`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from companion.sim import realization_key
from companion.sim.render import Pose
from companion.core.planner.safety import to_ned
from companion.core.types import ZERO_SETPOINT, VelocitySetpoint
from companion.errors import VehicleError
from companion.interfaces import VehicleState

#: Standard gravity, m/s².
GRAVITY_M_S2 = 9.80665


def wrap_angle_rad(a: float) -> float:
    """``a`` wrapped to [-pi, pi), radians."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class VehicleParams:
    """Dynamics of the simulated multicopter (see :class:`~companion.config.sim.SimConfig`).

    Attributes:
        velocity_time_constant_s: first-order lag of the velocity, seconds (> 0).
        acceleration_time_constant_s: first-order lag of the acceleration (all three axes) behind the one the
            velocity lag asks for (the tilt a multicopter needs first), seconds (>= 0; 0 = none).
        max_horizontal_accel_m_s2: limit on the norm of the horizontal acceleration, m/s² (> 0).
        max_vertical_accel_m_s2: limit on the vertical acceleration, m/s² (> 0).
        yaw_rate_time_constant_s: first-order lag of the yaw rate, seconds (> 0).
        max_yaw_accel_deg_s2: yaw acceleration limit, deg/s² (> 0).
        tilt_with_acceleration: tilt the body with the acceleration (camera pose follows).
        attitude_time_constant_s: lag of that tilt, seconds (> 0).
        collision_radius_m: radius of the collision sphere, metres (> 0).
        drift_speed_m_s: standard deviation of a random horizontal drift velocity added to the
            motion, per axis, m/s (>= 0; 0 = none). It models the estimator's error as PX4 shows it:
            the position moves while the velocity the vehicle reports (and tracks) does not.
        drift_time_constant_s: correlation time of that drift (Ornstein-Uhlenbeck), seconds (> 0).
        vertical_drift_speed_m_s: the same for a vertical drift (the same correlation time), m/s
            (>= 0; 0 = none): PX4 in offboard velocity control holds a vertical speed, not a height.
        response_delay_s: a setpoint takes effect this long after it is commanded, seconds (>= 0;
            0 = at once): the autopilot's link and loops, and its telemetry's age.
        slow_response_fraction: this share of every velocity step follows a second, slow first-order
            lag instead (0..1; 0 = none): PX4's velocity integrator closing the rest of a step over
            seconds. The horizontal and vertical acceleration limits hold for the sum.
        slow_response_time_constant_s: that slow lag, seconds (> 0).
    """

    velocity_time_constant_s: float = 0.3
    acceleration_time_constant_s: float = 0.0
    max_horizontal_accel_m_s2: float = 3.0
    max_vertical_accel_m_s2: float = 2.0
    yaw_rate_time_constant_s: float = 0.15
    max_yaw_accel_deg_s2: float = 200.0
    tilt_with_acceleration: bool = True
    attitude_time_constant_s: float = 0.1
    collision_radius_m: float = 0.25
    drift_speed_m_s: float = 0.0
    drift_time_constant_s: float = 4.0
    vertical_drift_speed_m_s: float = 0.0
    response_delay_s: float = 0.0
    slow_response_fraction: float = 0.0
    slow_response_time_constant_s: float = 8.0

    def __post_init__(self) -> None:
        for name in (
            "velocity_time_constant_s",
            "max_horizontal_accel_m_s2",
            "max_vertical_accel_m_s2",
            "yaw_rate_time_constant_s",
            "max_yaw_accel_deg_s2",
            "attitude_time_constant_s",
            "collision_radius_m",
            "drift_time_constant_s",
            "slow_response_time_constant_s",
        ):
            v = float(getattr(self, name))
            if not (v > 0.0 and math.isfinite(v)):
                raise ValueError(f"VehicleParams.{name} must be finite and > 0, got {v}")
        for name in ("drift_speed_m_s", "vertical_drift_speed_m_s", "acceleration_time_constant_s", "response_delay_s"):
            v = float(getattr(self, name))
            if not (v >= 0.0 and math.isfinite(v)):
                raise ValueError(f"VehicleParams.{name} must be finite and >= 0, got {v}")
        if not 0.0 <= float(self.slow_response_fraction) <= 1.0:
            raise ValueError(f"VehicleParams.slow_response_fraction must be within [0, 1], got {self.slow_response_fraction}")

    @classmethod
    def from_config(cls, sim: object) -> VehicleParams:
        """The parameters held by a :class:`~companion.config.sim.SimConfig`."""
        return cls(**{name: getattr(sim, name) for name in cls.__dataclass_fields__})


class VehicleModel:
    """The dynamics alone (pure, synchronous).

    Args:
        params: the dynamics.
        start: initial pose (only position and yaw are used: the vehicle starts level, at rest).
        time_s: initial simulated time, seconds.
        seed: seed of the drift's random generator (the same seed flies the same drift).
        realization: ``sim.realization``: another draw of the drift for the same seed (0: the
            seed's own; :func:`~companion.sim.realization_key`).
    """

    def __init__(
        self, params: VehicleParams, start: Pose, time_s: float = 0.0, seed: int = 0, realization: int = 0
    ) -> None:
        self.params = params
        self.time_s = float(time_s)
        self.position_ned_m = np.array(start.position_ned_m, dtype=np.float64)
        self.velocity_ned_m_s = np.zeros(3)
        self._slow_ned_m_s = np.zeros(3)  # the slow lag's part of the velocity (slow_response_fraction)
        self.yaw_rad = wrap_angle_rad(start.yaw_rad)
        self.yaw_rate_rad_s = 0.0
        self.pitch_rad = 0.0
        self.roll_rad = 0.0
        self.accel_ned_m_s2 = np.zeros(3)
        self.setpoint: VelocitySetpoint = ZERO_SETPOINT  # the one the dynamics follow now
        self._target_ned_m_s = np.zeros(3)  # its velocity, NED at the yaw it was commanded at
        # (when it takes effect s, setpoint, its NED velocity)
        self._pending: deque[tuple[float, VelocitySetpoint, np.ndarray]] = deque()
        key = realization_key(seed, realization)
        self._rng = np.random.default_rng(list(key))  # [seed] draws as seed did: realization 0 unchanged
        self._vrng = np.random.default_rng([*key, 1])  # the vertical drift's own draws
        self.drift_ned_m_s = np.zeros(3)  # the estimator-like drift now, m/s

    def command(self, setpoint: VelocitySetpoint) -> None:
        """Set the velocity/yaw-rate setpoint tracked from now on, or ``response_delay_s`` from now;
        its velocity is turned into NED with the yaw now, as an autopilot does on receipt (non-finite
        values are refused)."""
        vals = (setpoint.forward_m_s, setpoint.right_m_s, setpoint.down_m_s, setpoint.yaw_rate_deg_s)
        if not all(math.isfinite(v) for v in vals):
            raise VehicleError(f"non-finite setpoint {setpoint}")
        ned = to_ned(setpoint, self.yaw_rad)
        if self.params.response_delay_s > 0.0:
            self._pending.append((self.time_s + self.params.response_delay_s, setpoint, ned))
        else:
            self.setpoint, self._target_ned_m_s = setpoint, ned

    def commanded_velocity_ned_m_s(self) -> np.ndarray:
        """The velocity of the setpoint in effect, NED as it was commanded, float64 ``(3,)`` m/s."""
        return self._target_ned_m_s.copy()

    def step(self, dt_s: float) -> None:
        """Advance the state by ``dt_s`` seconds (> 0; keep it well below the time constants)."""
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s must be finite and > 0, got {dt_s}")
        p = self.params
        while self._pending and self._pending[0][0] <= self.time_s + 1e-9:
            _, self.setpoint, self._target_ned_m_s = self._pending.popleft()
        v_cmd = self._target_ned_m_s
        v = self.velocity_ned_m_s
        # Exact discrete first-order lag over dt, expressed as the acceleration that realises it,
        # then clipped to the limits (the limit wins during large steps, the lag near the target).
        k = -math.expm1(-dt_s / p.velocity_time_constant_s) / dt_s
        f = p.slow_response_fraction
        if f > 0.0:
            # Two lags: the fast one follows (1 - f) of the setpoint, the slow one f of it.
            k_slow = -math.expm1(-dt_s / p.slow_response_time_constant_s) / dt_s
            acc_slow = (f * v_cmd - self._slow_ned_m_s) * k_slow
            acc = ((1.0 - f) * v_cmd - (v - self._slow_ned_m_s)) * k + acc_slow
        else:
            acc_slow = None
            acc = (v_cmd - v) * k
        acc_asked = acc.copy()
        ah = math.hypot(acc[0], acc[1])
        if ah > p.max_horizontal_accel_m_s2:
            acc[:2] *= p.max_horizontal_accel_m_s2 / ah
        acc[2] = min(p.max_vertical_accel_m_s2, max(-p.max_vertical_accel_m_s2, acc[2]))
        if p.acceleration_time_constant_s > 0.0:
            # The vehicle gets the asked-for acceleration only as fast as it tilts.
            ka = -math.expm1(-dt_s / p.acceleration_time_constant_s)
            acc = self.accel_ned_m_s2 + (acc - self.accel_ned_m_s2) * ka
        v_new = v + acc * dt_s
        if acc_slow is not None:
            # The limits scale both parts alike.
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(acc_asked != 0.0, acc / acc_asked, 1.0)
            self._slow_ned_m_s = self._slow_ned_m_s + acc_slow * scale * dt_s
        self.position_ned_m = self.position_ned_m + 0.5 * (v + v_new) * dt_s
        if p.drift_speed_m_s > 0.0 or p.vertical_drift_speed_m_s > 0.0:
            # Ornstein-Uhlenbeck, exact over dt: stationary std drift_speed_m_s per horizontal axis
            # (vertical_drift_speed_m_s down), each from its own draws so that one does not change
            # the other's sequence.
            a = math.exp(-dt_s / p.drift_time_constant_s)
            if p.drift_speed_m_s > 0.0:
                noise = self._rng.standard_normal(2) * (p.drift_speed_m_s * math.sqrt(1.0 - a * a))
                self.drift_ned_m_s[:2] = a * self.drift_ned_m_s[:2] + noise
            if p.vertical_drift_speed_m_s > 0.0:
                noise = self._vrng.standard_normal() * (p.vertical_drift_speed_m_s * math.sqrt(1.0 - a * a))
                self.drift_ned_m_s[2] = a * self.drift_ned_m_s[2] + noise
            self.position_ned_m = self.position_ned_m + self.drift_ned_m_s * dt_s
        self.velocity_ned_m_s = v_new
        self.accel_ned_m_s2 = acc

        r_cmd = math.radians(self.setpoint.yaw_rate_deg_s)
        kr = -math.expm1(-dt_s / p.yaw_rate_time_constant_s) / dt_s
        yaw_acc = (r_cmd - self.yaw_rate_rad_s) * kr
        lim = math.radians(p.max_yaw_accel_deg_s2)
        yaw_acc = min(lim, max(-lim, yaw_acc))
        r_new = self.yaw_rate_rad_s + yaw_acc * dt_s
        self.yaw_rad = wrap_angle_rad(self.yaw_rad + 0.5 * (self.yaw_rate_rad_s + r_new) * dt_s)
        self.yaw_rate_rad_s = r_new

        if p.tilt_with_acceleration:
            c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
            a_fwd = c * acc[0] + s * acc[1]
            a_right = -s * acc[0] + c * acc[1]
            # Thrust tilts forward (nose down) to accelerate forward; right wing down to go right.
            pitch_target = -math.atan2(a_fwd, GRAVITY_M_S2)
            roll_target = math.atan2(a_right, GRAVITY_M_S2)
            ka = -math.expm1(-dt_s / p.attitude_time_constant_s)
            self.pitch_rad += (pitch_target - self.pitch_rad) * ka
            self.roll_rad += (roll_target - self.roll_rad) * ka
        self.time_s += dt_s

    def pose(self) -> Pose:
        """The body pose now (position, yaw, and the tilt if enabled)."""
        return Pose(tuple(self.position_ned_m), self.yaw_rad, self.pitch_rad, self.roll_rad)

    @property
    def speed_m_s(self) -> float:
        """Norm of the NED velocity, m/s."""
        return float(np.linalg.norm(self.velocity_ned_m_s))

    @property
    def altitude_m(self) -> float:
        """Height above the ground plane (z = 0), metres."""
        return float(-self.position_ned_m[2])


class SimVehicle:
    """The simulated vehicle as a :class:`~companion.interfaces.VehicleLink`, plus a synchronous core.

    The async methods are trivial wrappers over the synchronous ones, because the simulator owns
    time: :meth:`step` advances it. Flight modes (names as MAVSDK reports PX4's): ``POSCTL`` at start
    and ``HOLD`` after :meth:`hold` both hold position (zero velocity); ``OFFBOARD`` tracks the
    latest setpoint. As on PX4, offboard can only be entered once a setpoint has been sent.

    Args:
        params: the dynamics.
        start: initial pose (level, at rest).
        time_s: initial simulated time, seconds.
        seed: seed of the drift's random generator (see :class:`VehicleParams`).
        realization: ``sim.realization`` (see :class:`VehicleModel`).
    """

    def __init__(
        self, params: VehicleParams, start: Pose, time_s: float = 0.0, seed: int = 0, realization: int = 0
    ) -> None:
        self.model = VehicleModel(params, start, time_s, seed, realization)
        self.flight_mode = "POSCTL"
        self._last_setpoint: VelocitySetpoint | None = None
        self._connected = False
        self._closed = False

    # ---------------------------------------------------------------- synchronous core

    @property
    def time_s(self) -> float:
        """Simulated time, seconds."""
        return self.model.time_s

    def set_setpoint(self, setpoint: VelocitySetpoint) -> None:
        """Hand one setpoint over (tracked only while in OFFBOARD)."""
        if self._closed:
            raise VehicleError("simulated vehicle link is closed")
        self.model.command(setpoint)  # validates
        self._last_setpoint = setpoint
        if self.flight_mode != "OFFBOARD":
            self.model.command(ZERO_SETPOINT)

    def set_offboard(self) -> None:
        """Enter OFFBOARD. Raises VehicleError if no setpoint was sent first (PX4's rule)."""
        if self._last_setpoint is None:
            raise VehicleError("offboard refused: send a setpoint before starting offboard")
        self.flight_mode = "OFFBOARD"
        self.model.command(self._last_setpoint)

    def set_hold(self) -> None:
        """Leave offboard for HOLD: hold position (zero velocity) from now on."""
        self.flight_mode = "HOLD"
        self.model.command(ZERO_SETPOINT)

    def stop_streaming(self) -> None:
        """Stop streaming setpoints, with no mode change. PX4 holds position when offboard setpoints
        stop (its offboard-loss failsafe; the delay before it is not modelled): zero velocity until
        the next setpoint."""
        self.model.command(ZERO_SETPOINT)

    def step(self, dt_s: float) -> None:
        """Advance the physics by ``dt_s`` seconds."""
        self.model.step(dt_s)

    def pose(self) -> Pose:
        """The body pose now."""
        return self.model.pose()

    @property
    def in_offboard(self) -> bool:
        return self.flight_mode == "OFFBOARD"

    # ---------------------------------------------------------------- VehicleLink

    async def connect(self, timeout_s: float) -> None:
        if self._closed:
            raise VehicleError("simulated vehicle link is closed")
        self._connected = True

    async def send_setpoint(self, setpoint: VelocitySetpoint) -> None:
        self.set_setpoint(setpoint)

    async def start_offboard(self) -> None:
        self.set_offboard()

    async def hold(self) -> None:
        self.set_hold()

    async def stop_setpoints(self) -> None:
        self.stop_streaming()

    def state(self) -> VehicleState:
        m = self.model
        return VehicleState(
            connected=self._connected and not self._closed,
            armed=True,
            flight_mode=self.flight_mode,
            in_offboard=self.in_offboard,
            position_ned_m=m.position_ned_m.copy(),
            attitude_rad=np.array([m.roll_rad, m.pitch_rad, m.yaw_rad]),
            timestamp_s=m.time_s,
        )

    async def close(self) -> None:
        self._closed = True
        self._connected = False
