"""From a controller decision to a body-frame velocity setpoint (pure; time is passed in).

Course hold (goal seeking) is optional and off unless the caller passes the errors: the paper's
controller only avoids, so a vehicle that yawed away from an obstacle never came back to its course.
The caller (the service, the simulator) records the heading and altitude at engagement and passes,
per setpoint, the heading and altitude errors, the newest region depths and how long the decisions
have been straight and CLEAR (:func:`is_straight_clear`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from companion.core.types import REGION_INDEX, ZERO_SETPOINT, Decision, DecisionKind, VelocitySetpoint

if TYPE_CHECKING:
    from companion.config.core import CommandConfig

#: A CLEAR decision whose |yaw| and |pitch| are below this counts as flying straight (course hold may
#: act); anything larger is the controller steering, and course hold waits.
STRAIGHT_TOLERANCE = 0.01


def is_straight_clear(decision: Decision | None) -> bool:
    """True for a CLEAR decision that does not steer (|yaw|, |pitch| < :data:`STRAIGHT_TOLERANCE`).

    Callers time how long this has held and pass it to :func:`setpoint_for` as ``clear_for_s``.
    """
    return (
        decision is not None
        and decision.kind is DecisionKind.CLEAR
        and abs(decision.yaw) < STRAIGHT_TOLERANCE
        and abs(decision.pitch) < STRAIGHT_TOLERANCE
    )


def _side_open(region_depths_m: np.ndarray | None, side: str, clear_depth_m: float) -> bool:
    if region_depths_m is None:
        return True
    depth = float(region_depths_m[REGION_INDEX[side]])
    return depth >= clear_depth_m  # False for NaN: unknown blocks


def line_offset_m(position_ned_m: np.ndarray, origin_ned_m: np.ndarray, heading_rad: float) -> float:
    """Signed distance of a position (float ``(3,)`` NED metres) from the horizontal line through
    ``origin_ned_m`` along ``heading_rad``, metres: positive = the line lies to the right of the
    position (the vehicle is left of it)."""
    d = np.asarray(position_ned_m, dtype=np.float64) - np.asarray(origin_ned_m, dtype=np.float64)
    right_of_line = -math.sin(heading_rad) * d[0] + math.cos(heading_rad) * d[1]
    return float(-right_of_line)


def _heading_hold_deg_s(
    heading_error_rad: float | None,
    region_depths_m: np.ndarray | None,
    cmd: CommandConfig,
    line_offset: float | None = None,
) -> float:
    if heading_error_rad is None or cmd.heading_hold_gain_per_s == 0.0 or not math.isfinite(heading_error_rad):
        return 0.0
    err = (heading_error_rad + math.pi) % (2.0 * math.pi) - math.pi
    if line_offset is not None and math.isfinite(line_offset) and cmd.line_hold_gain_per_m > 0.0:
        limit = math.radians(cmd.max_line_hold_angle_deg)
        err += min(limit, max(-limit, math.atan(cmd.line_hold_gain_per_m * line_offset)))
    rate = math.degrees(cmd.heading_hold_gain_per_s * err)
    rate = min(cmd.max_heading_hold_rate_deg_s, max(-cmd.max_heading_hold_rate_deg_s, rate))
    if rate != 0.0 and not _side_open(region_depths_m, "right" if rate > 0 else "left", cmd.hold_clear_depth_m):
        return 0.0
    return rate


def _altitude_hold_down_m_s(
    altitude_error_m: float | None, region_depths_m: np.ndarray | None, cmd: CommandConfig
) -> float:
    if altitude_error_m is None or cmd.altitude_hold_gain_per_s == 0.0 or not math.isfinite(altitude_error_m):
        return 0.0
    down = -cmd.altitude_hold_gain_per_s * altitude_error_m
    down = min(cmd.max_altitude_hold_speed_m_s, max(-cmd.max_altitude_hold_speed_m_s, down))
    if down != 0.0 and not _side_open(region_depths_m, "down" if down > 0 else "up", cmd.hold_clear_depth_m):
        return 0.0
    return down


def brake_offset_body(position_ned_m: np.ndarray, brake_at_ned_m: np.ndarray, yaw_rad: float) -> np.ndarray:
    """Where the vehicle is relative to where its brake began, in the body frame (yaw only: forward,
    right, down), float ``(3,)`` metres, from NED positions (float ``(3,)`` metres) and the heading."""
    d = np.asarray(position_ned_m, dtype=np.float64) - np.asarray(brake_at_ned_m, dtype=np.float64)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])


class BrakeLatch:
    """Where the current brake began (brake position hold): latched at the first BRAKE decision,
    forgotten on any other decision or without a position and heading."""

    def __init__(self) -> None:
        self.at_ned_m: np.ndarray | None = None

    def reset(self) -> None:
        self.at_ned_m = None

    def offset_body(
        self, decision: Decision | None, position_ned_m: np.ndarray | None, yaw_rad: float | None
    ) -> np.ndarray | None:
        """The ``brake_offset_body_m`` for :func:`setpoint_for` (float ``(3,)`` metres, body frame),
        or None when not braking."""
        if decision is None or decision.kind is not DecisionKind.BRAKE or position_ned_m is None or yaw_rad is None:
            self.at_ned_m = None
            return None
        pos = np.asarray(position_ned_m, dtype=np.float64)
        if self.at_ned_m is None:
            self.at_ned_m = pos.copy()
        return brake_offset_body(pos, self.at_ned_m, yaw_rad)


def _brake_hold(offset_body_m: np.ndarray | None, cmd: CommandConfig) -> VelocitySetpoint:
    if offset_body_m is None or cmd.brake_hold_gain_per_s == 0.0:
        return ZERO_SETPOINT
    offset = np.asarray(offset_body_m, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(offset)):
        return ZERO_SETPOINT
    v = np.clip(-cmd.brake_hold_gain_per_s * offset, -cmd.brake_hold_max_speed_m_s, cmd.brake_hold_max_speed_m_s)
    return VelocitySetpoint(forward_m_s=float(v[0]), right_m_s=float(v[1]), down_m_s=float(v[2]), yaw_rate_deg_s=0.0)


def setpoint_for(
    decision: Decision | None,
    since_last_frame_s: float,
    cmd: CommandConfig,
    *,
    heading_error_rad: float | None = None,
    altitude_error_m: float | None = None,
    region_depths_m: np.ndarray | None = None,
    clear_for_s: float | None = None,
    brake_offset_body_m: np.ndarray | None = None,
    line_offset_m: float | None = None,
) -> VelocitySetpoint:
    """The setpoint to send for ``decision``, made ``since_last_frame_s`` seconds after its frame.

    * No decision, a frame older than ``cmd.stale_frame_timeout_s``, or a non-finite age: zero velocity.
    * BRAKE (or a decision carrying a non-finite number): zero velocity; with ``brake_offset_body_m``
      (float ``(3,)`` metres: the vehicle's position now minus where the brake began, in the body
      frame: forward, right, down) and ``cmd.brake_hold_gain_per_s`` > 0, the velocity back there
      instead: ``clip(-gain · offset, ±brake_hold_max_speed_m_s)`` per axis (brake position hold).
    * Otherwise forward = ``cruise_speed_m_s · speed_fraction`` (m/s), yaw rate =
      ``yaw · max_yaw_rate_deg_s`` (deg/s, positive turns right), down = ``-pitch · max_vertical_speed_m_s``
      (m/s; pitch up = climb = negative down). yaw and pitch are clipped to [-1, 1], the speed fraction
      to [0, 1]. Never a sideways velocity (right_m_s = 0).

    Course hold (all keyword inputs optional; ``None`` = off, the paper's behaviour). Only on a CLEAR
    decision, and only once ``clear_for_s`` (seconds the decisions have been straight and CLEAR; None
    = no wait) reaches ``cmd.hold_resume_delay_s``:

    * ``heading_error_rad`` (heading at engagement minus heading now, radians, positive = the course
      lies to the right): adds ``clip(heading_hold_gain_per_s · error, ±max_heading_hold_rate_deg_s)``
      deg/s of yaw rate, scaled by ``1 - |yaw|``;
    * ``line_offset_m`` (:func:`line_offset_m` of the vehicle from the line through the engagement
      point along the engagement heading): with ``cmd.line_hold_gain_per_m`` > 0, the heading aimed at
      turns toward the line by ``clip(atan(gain · offset), ±max_line_hold_angle_deg)``;
    * ``altitude_error_m`` (altitude at engagement minus altitude now, metres, positive = climb):
      adds ``clip(-altitude_hold_gain_per_s · error, ±max_altitude_hold_speed_m_s)`` m/s of down
      speed, scaled by ``1 - |pitch|``;
    * ``region_depths_m`` (float ``(9,)`` refined region depths, metres, NaN unknown): when given,
      the hold turns toward a side (right, left) or climbs/descends (up, down) only while that region
      is at least ``cmd.hold_clear_depth_m`` deep.
    """
    if decision is None or not math.isfinite(since_last_frame_s):
        return ZERO_SETPOINT
    if since_last_frame_s > cmd.stale_frame_timeout_s:
        return ZERO_SETPOINT
    if decision.kind is DecisionKind.BRAKE:
        return _brake_hold(brake_offset_body_m, cmd)
    yaw, pitch, speed = decision.yaw, decision.pitch, decision.speed_fraction
    if not (math.isfinite(yaw) and math.isfinite(pitch) and math.isfinite(speed)):
        return ZERO_SETPOINT
    yaw = min(1.0, max(-1.0, yaw))
    pitch = min(1.0, max(-1.0, pitch))
    speed = min(1.0, max(0.0, speed))
    yaw_rate_deg_s = yaw * cmd.max_yaw_rate_deg_s
    down_m_s = 0.0 - pitch * cmd.max_vertical_speed_m_s
    if decision.kind is DecisionKind.CLEAR and (clear_for_s is None or clear_for_s >= cmd.hold_resume_delay_s):
        yaw_rate_deg_s += (1.0 - abs(yaw)) * _heading_hold_deg_s(heading_error_rad, region_depths_m, cmd, line_offset_m)
        down_m_s += (1.0 - abs(pitch)) * _altitude_hold_down_m_s(altitude_error_m, region_depths_m, cmd)
    return VelocitySetpoint(
        forward_m_s=cmd.cruise_speed_m_s * speed,
        right_m_s=0.0,
        down_m_s=down_m_s,
        yaw_rate_deg_s=yaw_rate_deg_s,
    )
