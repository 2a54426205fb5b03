"""Config section of the closed-loop simulator: camera, timing, vehicle model, scoring.

The simulator flies the product's own pipeline (every other section of the config applies as in the
service) through procedural courses; only what has no counterpart on a real vehicle lives here.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from companion.config._base import StrictModel


class SimConfig(StrictModel):
    """Simulator: camera rig and timing, the multicopter model, and when a flight ends."""

    # -- camera ----------------------------------------------------------------------------------
    camera_rate_hz: float = Field(
        default=30.0,
        gt=0.0,
        le=120.0,
        description=(
            "Simulated camera frame rate, Hz: the ZED's 30 by default (60 as the ZED's option at VGA). "
            "At 3 m/s a frame period is 0.1 m flown before the next look."
        ),
    )
    eye_width_px: int = Field(
        default=336,
        ge=64,
        le=2208,
        description=(
            "Width of one simulated eye, pixels. The rig is ideal and rectified, with "
            "calibration.ideal_hfov_deg and calibration.ideal_baseline_m (calibration.file is ignored). "
            "336 (half ZED VGA) with the default 64 disparities sees down to 0.31 m, as VGA (672) does "
            "with 128, at a quarter of the cost."
        ),
    )
    eye_height_px: int = Field(default=188, ge=48, le=1242, description="Height of one simulated eye, pixels (half ZED VGA: 188).")
    noise_std_grey: float = Field(
        default=2.0, ge=0.0, le=50.0, description="Gaussian sensor noise added to each eye, grey levels (0 = none)."
    )
    exposure_step_interval_s: float = Field(
        default=2.0,
        ge=0.0,
        le=600.0,
        description=(
            "Auto-exposure: the gain of both eyes jumps to a new random value this often, seconds "
            "(0 = constant gain)."
        ),
    )
    exposure_gain_range: tuple[float, float] = Field(
        default=(0.8, 1.2),
        description="Range the auto-exposure gain is drawn from (uniform), multiplying grey levels.",
    )
    eye_gain_mismatch: float = Field(
        default=0.03,
        ge=0.0,
        le=0.5,
        description="Largest relative gain difference between the eyes (drawn once per flight), 0.03 = 3 %.",
    )
    # -- timing ----------------------------------------------------------------------------------
    processing_latency_s: float = Field(
        default=0.06,
        ge=0.0,
        le=2.0,
        description=(
            "Capture-to-decision latency: a frame's decision is applied this long after its capture, "
            "seconds (set it to the measured pipeline time of the target computer)."
        ),
    )
    setpoint_rate_hz: float = Field(
        default=20.0, gt=0.0, le=200.0, description="Rate of velocity setpoints sent to the vehicle, Hz (the service's)."
    )
    physics_rate_hz: float = Field(
        default=200.0, ge=20.0, le=2000.0, description="Integration rate of the vehicle model and collision check, Hz."
    )
    # -- vehicle model ---------------------------------------------------------------------------
    velocity_time_constant_s: float = Field(
        default=0.44,
        gt=0.0,
        le=5.0,
        description=(
            "First-order lag of the velocity response to a velocity setpoint (of the share that "
            "slow_response_fraction leaves), seconds. Default: with response_delay_s 0.14 and "
            "slow_response_fraction 0.22, fitted to PX4 SITL's step response (SIH quadrotor, default "
            "MPC gains; steps of 1 and 3 m/s forward and sideways, 6-7 s each; docs/simulator.md): "
            "PX4 closes three quarters of a step within a second and the rest over seconds. Alone "
            "(slow_response_fraction 0), 1.17 s travels about as far as PX4 after a stop from 3 m/s. "
            "A crisp racer is nearer 0.3."
        ),
    )
    acceleration_time_constant_s: float = Field(
        default=0.0,
        ge=0.0,
        le=2.0,
        description=(
            "First-order lag between the acceleration the velocity loop asks for and the one the "
            "vehicle gets (a multicopter must tilt first), on all three axes, seconds; 0 = none, the "
            "velocity is a pure first-order lag (velocity_time_constant_s). With a lag here the "
            "response is second order, as PX4's cascade of velocity and attitude loops is: a guard "
            "that pushes from both sides rings with it where a first-order lag stays calm. PX4 SITL's "
            "step response fits the first-order lag (velocity_time_constant_s); 0.25 s here with velocity_time_constant_s "
            "0.56 is the harder vehicle that reproduced PX4's ringing (docs/simulator.md)."
        ),
    )
    response_delay_s: float = Field(
        default=0.14,
        ge=0.0,
        le=1.0,
        description=(
            "A velocity or yaw-rate setpoint takes effect this long after the service sends it, "
            "seconds (0 = at once): the autopilot's link and loops, and the age of the velocity it "
            "reports. It adds to the stopping distance as processing_latency_s does."
        ),
    )
    slow_response_fraction: float = Field(
        default=0.22,
        ge=0.0,
        le=1.0,
        description=(
            "This share of every velocity step follows a second, slow lag "
            "(slow_response_time_constant_s) instead of velocity_time_constant_s; 0 = none. An "
            "autopilot's velocity integrator closes the last part of a step over seconds: asked to stop "
            "from 3 m/s, PX4 SITL still moved at 0.4 m/s 2 s later and 0.25 m/s 6 s later, 3.9 m in "
            "all. The default 0.22 with 8 s, velocity_time_constant_s 0.44 and response_delay_s 0.14 "
            "reproduces PX4 SITL's steps (docs/simulator.md)."
        ),
    )
    slow_response_time_constant_s: float = Field(
        default=8.0, gt=0.0, le=60.0, description="The slow lag of slow_response_fraction, seconds."
    )
    max_horizontal_accel_m_s2: float = Field(
        default=2.6,
        gt=0.0,
        le=30.0,
        description=(
            "Horizontal acceleration limit of the vehicle, m/s². Default: PX4 SITL's step response over "
            "the first 2 s of its 3 m/s steps (starting and stopping)."
        ),
    )
    max_vertical_accel_m_s2: float = Field(
        default=2.0, gt=0.0, le=30.0, description="Vertical acceleration limit of the vehicle, m/s²."
    )
    yaw_rate_time_constant_s: float = Field(
        default=0.4,
        gt=0.0,
        le=5.0,
        description=(
            "First-order lag of the yaw rate response, seconds. Default: fitted to PX4 SITL's yaw-rate "
            "steps of 45 and 90 deg/s (0.36 s after 0.09 s of delay, or 0.42 s with none)."
        ),
    )
    max_yaw_accel_deg_s2: float = Field(
        default=130.0,
        gt=0.0,
        le=5000.0,
        description="Yaw acceleration limit, deg/s². Default: fitted with yaw_rate_time_constant_s to PX4 SITL's yaw-rate steps.",
    )
    tilt_with_acceleration: bool = Field(
        default=True,
        description=(
            "Tilt the body (and the hard-mounted camera) as a multicopter does to accelerate: pitch = "
            "-atan(a_forward/g), roll = atan(a_right/g)."
        ),
    )
    attitude_time_constant_s: float = Field(
        default=0.1, gt=0.0, le=2.0, description="First-order lag of that tilt, seconds."
    )
    collision_radius_m: float = Field(
        default=0.25,
        gt=0.0,
        le=5.0,
        description="The vehicle is a sphere of this radius around its centre for collisions and clearance, metres.",
    )
    realization: int = Field(
        default=0,
        ge=0,
        le=2**31 - 1,
        description=(
            "Which draw of the sensor noise, the exposure steps, the eyes' gain mismatch and the drift "
            "a flight gets, with its course seed; the course itself (geometry, textures, start) stays. "
            "0 = the course seed's own draws. The closed loop is chaotic: a 1 % change of "
            "noise_std_grey changes the outcome of several flights in a suite, so compare "
            "configurations over several realizations (companion sim --realizations; docs/simulator.md, "
            "'Judging a change')."
        ),
    )
    drift_speed_m_s: float = Field(
        default=0.0,
        ge=0.0,
        le=2.0,
        description=(
            "Standard deviation of a random horizontal drift added to the vehicle's motion, per axis, "
            "m/s; 0 = none. It models the position estimate's error as PX4 SITL shows it: with SIH's "
            "GPS, EKF2's velocity is off by ~0.2 m/s rms, so the vehicle wanders while the velocity it "
            "reports and tracks reads the setpoint. Seeded by the course."
        ),
    )
    drift_time_constant_s: float = Field(
        default=4.0,
        gt=0.0,
        le=60.0,
        description="Correlation time of that drift (a first-order Gauss-Markov process), seconds.",
    )
    vertical_drift_speed_m_s: float = Field(
        default=0.0,
        ge=0.0,
        le=1.0,
        description=(
            "Standard deviation of a random vertical drift added to the vehicle's motion, m/s (the "
            "same correlation time); 0 = none. PX4 in offboard velocity control holds a vertical "
            "speed, not a height: PX4 SITL drifted up 0.4 m in 4 s under zero vertical speed "
            "setpoints, and sagged 0.1-0.2 m as it sped up. Seeded by the course."
        ),
    )
    # -- the goal --------------------------------------------------------------------------------
    goal: Literal["point", "course"] = Field(
        default="point",
        description=(
            "What the simulated flight is engaged with (as companion sitl sends it with engage): "
            "'point', the course's goal point (1 m past its goal line, on the start line); 'course', "
            "no goal but the heading at the start (flown on along it)."
        ),
    )
    # -- scoring ---------------------------------------------------------------------------------
    held_after_s: float = Field(
        default=3.0,
        gt=0.0,
        le=120.0,
        description="Stopped (below held_speed_m_s, yaw rate below 3 deg/s) this long without a collision = held safely, seconds.",
    )
    held_speed_m_s: float = Field(
        default=0.05, gt=0.0, le=1.0, description="Speed below which the vehicle counts as stopped, m/s."
    )

    @model_validator(mode="after")
    def _check(self) -> SimConfig:
        lo, hi = self.exposure_gain_range
        if not 0.0 < lo <= hi <= 4.0:
            raise ValueError(f"exposure_gain_range must satisfy 0 < low <= high <= 4, got {[lo, hi]}")
        if self.physics_rate_hz < self.setpoint_rate_hz or self.physics_rate_hz < self.camera_rate_hz:
            raise ValueError(
                f"physics_rate_hz ({self.physics_rate_hz}) must be at least setpoint_rate_hz "
                f"({self.setpoint_rate_hz}) and camera_rate_hz ({self.camera_rate_hz})"
            )
        return self
