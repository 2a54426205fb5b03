"""Setpoints flown directly from a yaw, a climb and a forward speed share, with no map (pure).

* The operator's manual override (``companion ctl override``): a yaw, a climb and a speed share for a
  bounded time, then the flight is automatic again (:mod:`companion.core.supervisor`). It does not
  fly on into what the fuzzy controller brakes for unless the envelope lets it
  (``service.override_respects_brake``).
* A fuzzy decision read as a setpoint (:func:`decision_setpoint`), where there is no vehicle and no
  map to plan on: the offline tools (``companion process``, a recording's records) show what the
  paper's controller alone would command.

Both scale by the local planner's own limits (``planner.cruise_speed_m_s``, ``max_vertical_speed_m_s``,
``max_yaw_rate_deg_s``), each within the safety envelope.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from companion.core.types import ZERO_SETPOINT, Decision, DecisionKind, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.core.supervisor_io import FrameOutcome, Override


def override_refusal(o: Override, fresh: bool, age_s: float, max_duration_s: float) -> str | None:
    """Why the override ``o`` is refused now (None: it is not), given whether the newest frame is
    ``fresh`` and its age ``age_s`` (seconds) and ``service.override_max_duration_s``."""
    if not fresh:
        return f"frames are stale ({age_s:.2f} s); the way ahead is unknown"
    if not all(math.isfinite(x) for x in (o.yaw, o.pitch, o.speed_fraction, o.duration_s)):
        return "yaw, pitch, speed and duration_s must be finite"
    if not (-1.0 <= o.yaw <= 1.0 and -1.0 <= o.pitch <= 1.0 and 0.0 <= o.speed_fraction <= 1.0):
        return "yaw and pitch must be in [-1, 1], speed in [0, 1]"
    if not 0.0 < o.duration_s <= max_duration_s:
        return f"duration_s {o.duration_s:g} must be in (0, {max_duration_s:g}] (service.override_max_duration_s)"
    return None


def stick_setpoint(yaw: float, pitch: float, speed_fraction: float, cfg: CompanionConfig) -> VelocitySetpoint:
    """Forward ``speed_fraction`` (in [0, 1]) of ``planner.cruise_speed_m_s``, a climb of ``pitch``
    (in [-1, 1], + up) times ``planner.max_vertical_speed_m_s`` and a yaw rate of ``yaw`` (in [-1, 1],
    + right) times ``planner.max_yaw_rate_deg_s``, each at most the envelope's; no sideways speed.
    Out-of-range inputs are clipped."""
    p, env = cfg.planner, cfg.envelope
    yaw, pitch = min(1.0, max(-1.0, yaw)), min(1.0, max(-1.0, pitch))
    speed = min(1.0, max(0.0, speed_fraction))
    return VelocitySetpoint(
        forward_m_s=min(p.cruise_speed_m_s, env.max_horizontal_speed_m_s) * speed,
        right_m_s=0.0,
        down_m_s=0.0 - pitch * min(p.max_vertical_speed_m_s, env.max_vertical_speed_m_s),
        yaw_rate_deg_s=yaw * min(p.max_yaw_rate_deg_s, env.max_yaw_rate_deg_s),
    )


def decision_setpoint(decision: Decision, cfg: CompanionConfig) -> VelocitySetpoint:
    """The fuzzy decision flown directly (:func:`stick_setpoint` of its yaw, pitch and speed share): zero
    on BRAKE, and on a decision carrying a non-finite number."""
    values = (decision.yaw, decision.pitch, decision.speed_fraction)
    if decision.kind is DecisionKind.BRAKE or not all(math.isfinite(x) for x in values):
        return ZERO_SETPOINT
    return stick_setpoint(decision.yaw, decision.pitch, decision.speed_fraction, cfg)


def override_setpoint(o: Override, latest: FrameOutcome | None, cfg: CompanionConfig, respects_brake: bool) -> VelocitySetpoint:
    """The operator's override as a setpoint (:func:`stick_setpoint`). With ``respects_brake``, no
    forward speed while the newest decision brakes (or there is none): turning and climbing are
    allowed, going on is not."""
    sp = stick_setpoint(o.yaw, o.pitch, o.speed_fraction, cfg)
    if respects_brake and (latest is None or latest.decision.kind is DecisionKind.BRAKE):
        return VelocitySetpoint(0.0, sp.right_m_s, sp.down_m_s, sp.yaw_rate_deg_s)
    return sp
