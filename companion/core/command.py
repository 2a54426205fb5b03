"""From a controller decision to a body-frame velocity setpoint (pure; time is passed in)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from companion.core.types import ZERO_SETPOINT, Decision, DecisionKind, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config.core import CommandConfig


def setpoint_for(decision: Decision | None, since_last_frame_s: float, cmd: CommandConfig) -> VelocitySetpoint:
    """The setpoint to send for ``decision``, made ``since_last_frame_s`` seconds after its frame.

    * No decision, a frame older than ``cmd.stale_frame_timeout_s``, or a non-finite age: zero velocity.
    * BRAKE (or a decision carrying a non-finite number): zero velocity.
    * Otherwise forward = ``cruise_speed_m_s · speed_fraction`` (m/s), yaw rate =
      ``yaw · max_yaw_rate_deg_s`` (deg/s, positive turns right), down = ``-pitch · max_vertical_speed_m_s``
      (m/s; pitch up = climb = negative down). yaw and pitch are clipped to [-1, 1], the speed fraction
      to [0, 1]. Never a sideways velocity (right_m_s = 0).
    """
    if decision is None or not math.isfinite(since_last_frame_s):
        return ZERO_SETPOINT
    if since_last_frame_s > cmd.stale_frame_timeout_s or decision.kind is DecisionKind.BRAKE:
        return ZERO_SETPOINT
    yaw, pitch, speed = decision.yaw, decision.pitch, decision.speed_fraction
    if not (math.isfinite(yaw) and math.isfinite(pitch) and math.isfinite(speed)):
        return ZERO_SETPOINT
    yaw = min(1.0, max(-1.0, yaw))
    pitch = min(1.0, max(-1.0, pitch))
    speed = min(1.0, max(0.0, speed))
    return VelocitySetpoint(
        forward_m_s=cmd.cruise_speed_m_s * speed,
        right_m_s=0.0,
        down_m_s=0.0 - pitch * cmd.max_vertical_speed_m_s,
        yaw_rate_deg_s=yaw * cmd.max_yaw_rate_deg_s,
    )
