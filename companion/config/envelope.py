"""The safety envelope (``[envelope]``): the limits no live change can leave.

The envelope is read from the config file only, at start and on a reload (SIGHUP, ``ctl reload``);
``set_config`` cannot change it. Every config, the file's and every live change's, is validated
against it (:func:`envelope_violations`): a speed above its limit, a timeout beyond its bound, a
safety feature switched off that the envelope does not let go, is an error naming the field and the
limit. While the service is engaged, ``live_changes_while_engaged`` says which fields a live change
may touch at all (the control plane enforces it, :mod:`companion.service.control`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field

from companion.config._base import StrictModel

if TYPE_CHECKING:
    from companion.config import CompanionConfig

LiveChanges = Literal["none", "tuning", "any"]


class EnvelopeConfig(StrictModel):
    """Limits that bound every other section; changed only by editing the file (read at start and reload)."""

    max_horizontal_speed_m_s: float = Field(
        default=4.0,
        gt=0.0,
        le=20.0,
        description=(
            "Upper bound of every horizontal speed the service may command, m/s: planner.cruise_speed_m_s, "
            "and the last limit on each setpoint (an override's too). 4 m/s: the local planner's 3 m/s cruise, plus the counter to motion the reported velocity "
            "does not explain (up to vehicle.odometry_drift_m_s, 0.5 m/s) that is added to it, plus "
            "headroom for the autopilot's velocity controller, so that the envelope clips no setpoint "
            "the planner meant."
        ),
    )
    max_vertical_speed_m_s: float = Field(
        default=1.0,
        gt=0.0,
        le=10.0,
        description="Upper bound of planner.max_vertical_speed_m_s and of every vertical speed commanded, m/s.",
    )
    max_yaw_rate_deg_s: float = Field(
        default=120.0,
        gt=0.0,
        le=720.0,
        description="Upper bound of planner.max_yaw_rate_deg_s and of every yaw rate commanded, deg/s.",
    )
    max_stale_frame_timeout_s: float = Field(
        default=0.5,
        gt=0.0,
        le=5.0,
        description="Upper bound of command.stale_frame_timeout_s (frames older than that: zero velocity), seconds.",
    )
    max_failsafe_timeout_s: float = Field(
        default=5.0,
        gt=0.0,
        le=60.0,
        description="Upper bound of command.failsafe_timeout_s (frames older than that: leave offboard to Hold), seconds.",
    )
    min_setpoint_rate_hz: float = Field(
        default=10.0,
        gt=0.0,
        le=100.0,
        description="Lower bound of vehicle.setpoint_rate_hz, Hz (PX4 leaves offboard below 2 Hz).",
    )
    max_override_duration_s: float = Field(
        default=10.0,
        gt=0.0,
        le=300.0,
        description="Upper bound of service.override_max_duration_s, the longest manual override, seconds.",
    )
    override_may_ignore_brake: bool = Field(
        default=False,
        description="Whether service.override_respects_brake may be false (an override flying on into something near).",
    )
    arming_check_may_be_off: bool = Field(
        default=False,
        description="Whether vehicle.require_armed_to_engage may be false (engage a disarmed vehicle: tests only).",
    )
    near_check_depth_m: float = Field(
        default=0.5,
        gt=0.0,
        le=5.0,
        description=(
            "Every config must see an obstacle this near as near: with 9 regions at this computed depth the "
            "controller must brake, and with only the centre there it must not fly on straight. A LUT, "
            "membership function or rule change that fails this is refused, metres."
        ),
    )
    live_changes_while_engaged: LiveChanges = Field(
        default="tuning",
        description=(
            "What a live change (set_config, reload) may touch while the service is engaged: none; tuning "
            "(the fuzzy controller and the lut, within this envelope; not the planner, the timeouts or "
            "the watchdog); any (every field, still within this envelope). "
            "The envelope itself changes only by a reload while not engaged."
        ),
    )


def envelope_violations(cfg: CompanionConfig) -> list[str]:
    """Every way ``cfg`` leaves its own envelope, one line each naming the field and the limit; [] = inside."""
    e = cfg.envelope
    c, p, v, s = cfg.command, cfg.planner, cfg.vehicle, cfg.service
    out: list[str] = []

    def above(field: str, value: float, limit_name: str, limit: float) -> None:
        if value > limit:
            out.append(f"{field} = {value:g} is above envelope.{limit_name} = {limit:g}")

    above("planner.cruise_speed_m_s", p.cruise_speed_m_s, "max_horizontal_speed_m_s", e.max_horizontal_speed_m_s)
    above("planner.max_vertical_speed_m_s", p.max_vertical_speed_m_s, "max_vertical_speed_m_s", e.max_vertical_speed_m_s)
    above("planner.max_yaw_rate_deg_s", p.max_yaw_rate_deg_s, "max_yaw_rate_deg_s", e.max_yaw_rate_deg_s)
    above("command.stale_frame_timeout_s", c.stale_frame_timeout_s, "max_stale_frame_timeout_s", e.max_stale_frame_timeout_s)
    above("command.failsafe_timeout_s", c.failsafe_timeout_s, "max_failsafe_timeout_s", e.max_failsafe_timeout_s)
    above("service.override_max_duration_s", s.override_max_duration_s, "max_override_duration_s", e.max_override_duration_s)
    if v.setpoint_rate_hz < e.min_setpoint_rate_hz:
        out.append(
            f"vehicle.setpoint_rate_hz = {v.setpoint_rate_hz:g} is below envelope.min_setpoint_rate_hz = "
            f"{e.min_setpoint_rate_hz:g}"
        )
    if not s.override_respects_brake and not e.override_may_ignore_brake:
        out.append("service.override_respects_brake = false, but envelope.override_may_ignore_brake is false")
    if not v.require_armed_to_engage and not e.arming_check_may_be_off:
        out.append("vehicle.require_armed_to_engage = false, but envelope.arming_check_may_be_off is false")
    return out
