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

from companion.core.frames import ned_to_body_horizontal
from companion.core.memory import Gap, apply_guard, within_room
from companion.core.types import (
    REGION_INDEX,
    ZERO_SETPOINT,
    Decision,
    DecisionKind,
    VelocitySetpoint,
)

if TYPE_CHECKING:
    from companion.config.core import CommandConfig, MemoryConfig
    from companion.config.detour import DetourConfig
    from companion.core.detour import DetourCommand

#: The stand-off's push from a side region leans this far off straight back, radians (the middle of
#: the outer third of a ±44° view).
STANDOFF_SIDE_BEARING_RAD = math.radians(30.0)

#: A CLEAR decision whose |yaw| and |pitch| are below this counts as flying straight (course hold may
#: act); anything larger is the controller steering, and course hold waits.
STRAIGHT_TOLERANCE = 0.01


def is_heading_clear(decision: Decision | None) -> bool:
    """True for a CLEAR decision that does not turn (|yaw| < :data:`STRAIGHT_TOLERANCE`), whatever its
    pitch: a slight climb away from the ground seen by the down regions does not keep the heading
    hold from acting. Callers time how long this has held and pass it to :func:`setpoint_for` as
    ``heading_clear_for_s``."""
    return decision is not None and decision.kind is DecisionKind.CLEAR and abs(decision.yaw) < STRAIGHT_TOLERANCE


def is_straight_clear(decision: Decision | None) -> bool:
    """True for a CLEAR decision that does not steer (|yaw|, |pitch| < :data:`STRAIGHT_TOLERANCE`).

    Callers time how long this has held, and measure how far the vehicle has flown since, and pass
    them to :func:`setpoint_for` as ``clear_for_s`` and ``clear_for_m``.
    """
    return (
        decision is not None
        and decision.kind is DecisionKind.CLEAR
        and abs(decision.yaw) < STRAIGHT_TOLERANCE
        and abs(decision.pitch) < STRAIGHT_TOLERANCE
    )


def _side_open(
    region_depths_m: np.ndarray | None,
    side: str,
    clear_depth_m: float,
    remembered: tuple[bool, bool] | None = None,
) -> bool:
    if remembered is not None and ((side == "left" and remembered[0]) or (side == "right" and remembered[1])):
        return False  # something remembered near on that side, out of view
    if region_depths_m is None:
        return True
    depth = float(region_depths_m[REGION_INDEX[side]])
    return depth >= clear_depth_m  # False for NaN: unknown blocks


def _offset_along_heading(
    position_ned_m: np.ndarray, reference_ned_m: np.ndarray, heading_rad: float
) -> tuple[float, float, float]:
    """``position_ned_m - reference_ned_m`` (float ``(3,)`` NED metres) in the frame of
    ``heading_rad`` (yaw only): forward, right, down, metres."""
    d = np.asarray(position_ned_m, dtype=np.float64) - np.asarray(reference_ned_m, dtype=np.float64)
    forward, right = ned_to_body_horizontal(float(d[0]), float(d[1]), heading_rad)
    return forward, right, float(d[2])


def line_offset_m(position_ned_m: np.ndarray, origin_ned_m: np.ndarray, heading_rad: float) -> float:
    """Signed distance of a position (float ``(3,)`` NED metres) from the horizontal line through
    ``origin_ned_m`` along ``heading_rad``, metres: positive = the line lies to the right of the
    position (the vehicle is left of it)."""
    return -_offset_along_heading(position_ned_m, origin_ned_m, heading_rad)[1]


def along_course_m(position_ned_m: np.ndarray, origin_ned_m: np.ndarray, heading_rad: float) -> float:
    """How far (metres) a position (float ``(3,)`` NED metres) lies along the course: its horizontal
    component from ``origin_ned_m`` along ``heading_rad`` (negative = behind the origin)."""
    return _offset_along_heading(position_ned_m, origin_ned_m, heading_rad)[0]


#: The decision the progress watchdog substitutes while it holds (:class:`ProgressWatch`): a brake,
#: so the brake position and heading hold and the guard act as for any brake.
NO_PROGRESS_HOLD = Decision(
    kind=DecisionKind.BRAKE, yaw=0.0, pitch=0.0, speed_fraction=0.0, reason="no progress along the course: holding"
)


class ProgressWatch:
    """The progress watchdog's clock (``command.no_progress_timeout_s``): the time since the vehicle
    last got ``command.progress_step_m`` nearer its goal (farther along the course, :func:`along_course_m`,
    for the course at engagement; nearer the point, for a goal point), and whether it is flying back.

    The caller passes the progress (metres, growing toward the goal) and the time; :meth:`update`
    says whether the limit has passed: no progress for ``no_progress_timeout_s``, or (**regress**) a
    progress ``regress_distance_m`` below the best reached for ``regress_timeout_s`` (:attr:`why`
    says which). A position that is unknown or not finite restarts the clock (nothing is judged
    without it). ``pause``: the clock stands still (the detour layer turning in place to look round
    is not a vehicle getting nowhere; it is bounded by its own limits), and regress is not judged."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Start again (engage, resume, a new goal: anything that was not the automatic flight)."""
        self._mark_m: float | None = None
        self._since_s: float | None = None
        self._best_m: float | None = None
        self._regress_since_s: float | None = None
        self._last_s: float | None = None
        self.why: str | None = None  #: ``no_progress`` or ``regress`` once :meth:`update` said True

    def update(
        self,
        along_m: float | None,
        now_s: float,
        cmd: CommandConfig,
        *,
        pause: bool = False,
        regress: bool = True,
        timeout_s: float | None = None,
    ) -> bool:
        """Feed the progress now (metres; None = unknown) at ``now_s`` seconds; True once it has not
        grown by ``cmd.progress_step_m`` for more than ``cmd.no_progress_timeout_s``, or has stayed
        more than ``cmd.regress_distance_m`` below the best for ``cmd.regress_timeout_s`` (always
        False when ``no_progress_timeout_s`` is 0 or course hold is off). ``pause``: the clock stands
        still; ``regress`` False: regress is not judged now (a detour, bounded by its own limits).
        ``timeout_s``: the local planner's time in place of ``cmd.no_progress_timeout_s`` (its
        :attr:`~companion.config.planner.PlannerConfig.no_progress_timeout_s`; 0 = off, and course
        hold's gain does not switch it off)."""
        limit_s = cmd.no_progress_timeout_s if timeout_s is None else timeout_s
        if (
            limit_s <= 0.0
            or (timeout_s is None and cmd.heading_hold_gain_per_s == 0.0)
            or along_m is None
            or not math.isfinite(along_m)
            or not math.isfinite(now_s)
        ):
            self.reset()
            return False
        if pause and self._since_s is not None and self._last_s is not None:
            self._since_s += max(0.0, now_s - self._last_s)
        self._last_s = float(now_s)
        if self._mark_m is None or self._since_s is None or along_m >= self._mark_m + cmd.progress_step_m:
            self._mark_m, self._since_s = float(along_m), float(now_s)
        if self._best_m is None or along_m > self._best_m:
            self._best_m = float(along_m)
        if pause or not regress or cmd.regress_distance_m <= 0.0 or along_m >= self._best_m - cmd.regress_distance_m:
            self._regress_since_s = None
        elif self._regress_since_s is None:
            self._regress_since_s = float(now_s)
        if self._regress_since_s is not None and now_s - self._regress_since_s >= cmd.regress_timeout_s:
            self.why = "regress"
            return True
        if now_s - self._since_s > limit_s:
            self.why = "no_progress"
            return True
        return False

    def stalled_for_s(self, now_s: float) -> float | None:
        """Seconds since the progress last grew by ``progress_step_m`` (the clock), or None."""
        return None if self._since_s is None else max(0.0, now_s - self._since_s)

    @property
    def mark_m(self) -> float | None:
        """The progress (metres) the clock last restarted at, or None."""
        return self._mark_m

    @property
    def regressing(self) -> bool:
        """Whether the progress is ``regress_distance_m`` or more below the best now, the regress
        clock running (:meth:`update`: not while paused)."""
        return self._regress_since_s is not None

    @property
    def best_m(self) -> float | None:
        """The most progress reached (metres), or None."""
        return self._best_m


def _aim_error_rad(heading_error_rad: float | None, line_offset: float | None, cmd: CommandConfig) -> float | None:
    """How far (radians, positive = right) the heading course hold aims at lies from the heading now:
    the course heading, turned toward the line; None when course hold is off or has no heading."""
    if heading_error_rad is None or cmd.heading_hold_gain_per_s == 0.0 or not math.isfinite(heading_error_rad):
        return None
    err = (heading_error_rad + math.pi) % (2.0 * math.pi) - math.pi
    if line_offset is not None and math.isfinite(line_offset) and cmd.line_hold_gain_per_m > 0.0:
        limit = math.radians(cmd.max_line_hold_angle_deg)
        err += min(limit, max(-limit, math.atan(cmd.line_hold_gain_per_m * line_offset)))
    return err


def _heading_hold_deg_s(
    heading_error_rad: float | None,
    region_depths_m: np.ndarray | None,
    cmd: CommandConfig,
    line_offset: float | None = None,
    remembered: tuple[bool, bool] | None = None,
) -> float:
    err = _aim_error_rad(heading_error_rad, line_offset, cmd)
    if err is None:
        return 0.0
    rate = math.degrees(cmd.heading_hold_gain_per_s * err)
    rate = min(cmd.max_heading_hold_rate_deg_s, max(-cmd.max_heading_hold_rate_deg_s, rate))
    if rate != 0.0 and not _side_open(region_depths_m, "right" if rate > 0 else "left", cmd.hold_clear_depth_m, remembered):
        return 0.0
    return rate


def _line_hold_right_m_s(
    line_offset: float | None,
    heading_error_rad: float | None,
    region_depths_m: np.ndarray | None,
    cmd: CommandConfig,
    remembered: tuple[bool, bool] | None = None,
) -> float:
    if line_offset is None or cmd.line_hold_lateral_gain_per_s == 0.0 or not math.isfinite(line_offset):
        return 0.0
    if heading_error_rad is None or not math.isfinite(heading_error_rad):
        return 0.0
    limit = cmd.max_line_hold_lateral_speed_m_s
    # Toward the line is the body's right only while facing along the course: scale by the cosine of
    # the heading error (0 when crossing the line at right angles, reversed when facing back).
    right = min(limit, max(-limit, cmd.line_hold_lateral_gain_per_s * line_offset)) * math.cos(heading_error_rad)
    aim = _aim_error_rad(heading_error_rad, line_offset, cmd)
    taper = cmd.line_hold_lateral_max_aim_error_deg
    if aim is not None and taper < 180.0:
        # still turning toward the aim: the body would slide into what the camera has not seen yet
        right *= max(0.0, 1.0 - abs(math.degrees(aim)) / taper)
    side = "right" if right > 0 else "left"
    if right != 0.0 and not _side_open(region_depths_m, side, cmd.line_hold_lateral_clear_depth_m, remembered):
        return 0.0
    return right


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


def _altitude_return_m_s(
    altitude_error_m: float | None,
    region_depths_m: np.ndarray | None,
    pitch: float,
    below_clear: bool | None,
    cmd: CommandConfig,
    *,
    waited: bool,
) -> float:
    """The altitude hold's down speed (m/s, + down) that acts now: all of it once ``waited``; else a
    climb back while the decision does not descend (``pitch`` > -:data:`STRAIGHT_TOLERANCE`), or a
    descent while it does not climb (``pitch`` < :data:`STRAIGHT_TOLERANCE`) and ``below_clear`` is
    True; else 0."""
    down = _altitude_hold_down_m_s(altitude_error_m, region_depths_m, cmd)
    if waited:
        return down
    # Level within STRAIGHT_TOLERANCE, as is_straight_clear has it: the defuzzified pitch of a level
    # CLEAR decision is a hair off zero either way (-1e-4), and a strict sign test would let that
    # block the climb back while the vehicle sinks.
    if down < 0.0 and pitch > -STRAIGHT_TOLERANCE:
        return down
    if down > 0.0 and pitch < STRAIGHT_TOLERANCE and below_clear is True:
        return down
    return 0.0


def _clear_altitude_return_m_s(
    altitude_error_m: float | None,
    region_depths_m: np.ndarray | None,
    pitch: float,
    below_clear: bool | None,
    clear_for_s: float | None,
    clear_for_m: float | None,
    cmd: CommandConfig,
) -> float:
    """The altitude hold's down speed (m/s, + down) on a CLEAR decision of pitch ``pitch`` (in
    [-1, 1]), scaled by ``1 - |pitch|``: all of :func:`_altitude_return_m_s` once the decisions have
    been straight and CLEAR for ``cmd.hold_resume_delay_s`` (``clear_for_s``) and
    ``cmd.hold_resume_distance_m`` (``clear_for_m``; None = no wait), before that only its climb back
    or its descent over nothing remembered (:func:`setpoint_for`)."""
    waited = (clear_for_s is None or clear_for_s >= cmd.hold_resume_delay_s) and (
        clear_for_m is None or clear_for_m >= cmd.hold_resume_distance_m
    )
    return (1.0 - abs(pitch)) * _altitude_return_m_s(altitude_error_m, region_depths_m, pitch, below_clear, cmd, waited=waited)


def horizontal_distance_m(a_ned_m: np.ndarray | None, b_ned_m: np.ndarray | None) -> float | None:
    """Horizontal distance between two NED positions (float ``(3,)`` metres), metres; None when
    either is missing or the distance is not finite."""
    if a_ned_m is None or b_ned_m is None:
        return None
    d = float(math.hypot(float(b_ned_m[0]) - float(a_ned_m[0]), float(b_ned_m[1]) - float(a_ned_m[1])))
    return d if math.isfinite(d) else None


def brake_offset_body(position_ned_m: np.ndarray, brake_at_ned_m: np.ndarray, yaw_rad: float) -> np.ndarray:
    """Where the vehicle is relative to where its brake began, in the body frame (yaw only: forward,
    right, down), float ``(3,)`` metres, from NED positions (float ``(3,)`` metres) and the heading."""
    return np.array(_offset_along_heading(position_ned_m, brake_at_ned_m, yaw_rad))


def horizontal_velocity_body_m_s(velocity_ned_m_s: np.ndarray | None, yaw_rad: float | None) -> tuple[float, float] | None:
    """A NED velocity (float ``(3,)`` m/s) as the body frame's horizontal (forward, right) m/s at
    heading ``yaw_rad``, for :func:`setpoint_for`'s ``velocity_body_m_s``; None when either is
    missing or not finite."""
    if velocity_ned_m_s is None or yaw_rad is None:
        return None
    v = np.asarray(velocity_ned_m_s, dtype=np.float64).reshape(-1)
    if v.size < 2 or not (math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(yaw_rad)):
        return None
    return ned_to_body_horizontal(float(v[0]), float(v[1]), yaw_rad)


class BrakeLatch:
    """Where and facing which way the current brake began (brake position and heading hold): latched
    at the first BRAKE decision, forgotten on any other decision or without a position and heading."""

    def __init__(self) -> None:
        self.at_ned_m: np.ndarray | None = None
        self.yaw_rad: float | None = None

    def reset(self) -> None:
        self.at_ned_m = None
        self.yaw_rad = None

    def heading_error_rad(self, yaw_rad: float | None) -> float | None:
        """The heading the brake began with minus ``yaw_rad`` (radians, wrapped to [-pi, pi),
        positive = turn right to get back), or None when not braking or without a heading."""
        if self.yaw_rad is None or yaw_rad is None or not math.isfinite(yaw_rad):
            return None
        return (self.yaw_rad - yaw_rad + math.pi) % (2.0 * math.pi) - math.pi

    def offset_body(
        self, decision: Decision | None, position_ned_m: np.ndarray | None, yaw_rad: float | None
    ) -> np.ndarray | None:
        """The ``brake_offset_body_m`` for :func:`setpoint_for` (float ``(3,)`` metres, body frame),
        or None when not braking."""
        if decision is None or decision.kind is not DecisionKind.BRAKE or position_ned_m is None or yaw_rad is None:
            self.reset()
            return None
        pos = np.asarray(position_ned_m, dtype=np.float64)
        if self.at_ned_m is None:
            self.at_ned_m = pos.copy()
            self.yaw_rad = float(yaw_rad)
        return brake_offset_body(pos, self.at_ned_m, yaw_rad)


class OverheadMemory:
    """Where the up region was last seen nearer than ``hold_clear_depth_m`` (or unknown): under a block
    the camera cannot see straight up, so the block's rear edge is out of view while it is overhead.
    :meth:`update` returns the horizontal distance flown since, for :func:`setpoint_for`'s
    ``since_up_near_m`` (no climbing until it reaches ``hold_resume_distance_m``)."""

    def __init__(self) -> None:
        self.at_ned_m: np.ndarray | None = None

    def reset(self) -> None:
        self.at_ned_m = None

    def update(
        self, region_depths_m: np.ndarray | None, position_ned_m: np.ndarray | None, clear_depth_m: float
    ) -> float | None:
        """Latch the position when the up region (float ``(9,)`` refined depths, metres, NaN unknown) is
        nearer than ``clear_depth_m`` metres; return metres flown horizontally since (float ``(3,)`` NED
        positions), or None when never latched or without a position."""
        if position_ned_m is None:
            return None
        pos = np.asarray(position_ned_m, dtype=np.float64)
        if region_depths_m is not None:
            up = float(np.asarray(region_depths_m, dtype=np.float64)[REGION_INDEX["up"]])
            if not up >= clear_depth_m:  # NaN (unknown) latches too
                self.at_ned_m = pos.copy()
        return horizontal_distance_m(self.at_ned_m, pos)


def _brake_hold(offset_body_m: np.ndarray | None, heading_error_rad: float | None, cmd: CommandConfig) -> VelocitySetpoint:
    gain = cmd.brake_hold_gain_per_s
    if gain == 0.0:
        return ZERO_SETPOINT
    v = np.zeros(3)
    if offset_body_m is not None:
        offset = np.asarray(offset_body_m, dtype=np.float64).reshape(3)
        if np.all(np.isfinite(offset)):
            v = np.clip(-gain * offset, -cmd.brake_hold_max_speed_m_s, cmd.brake_hold_max_speed_m_s)
    yaw_rate = 0.0
    if heading_error_rad is not None and math.isfinite(heading_error_rad):
        # A multicopter keeps turning for a moment after a zero yaw rate (PX4: ~0.4 s), and the new
        # view can open a false escape: turn back to the heading the brake began with.
        limit = cmd.max_heading_hold_rate_deg_s
        yaw_rate = min(limit, max(-limit, math.degrees(gain * heading_error_rad)))
    return VelocitySetpoint(forward_m_s=float(v[0]), right_m_s=float(v[1]), down_m_s=float(v[2]), yaw_rate_deg_s=yaw_rate)


def setpoint_for(
    decision: Decision | None,
    since_last_frame_s: float,
    cmd: CommandConfig,
    *,
    heading_error_rad: float | None = None,
    altitude_error_m: float | None = None,
    region_depths_m: np.ndarray | None = None,
    clear_for_s: float | None = None,
    clear_for_m: float | None = None,
    heading_clear_for_s: float | None = None,
    any_clear_for_s: float | None = None,
    brake_offset_body_m: np.ndarray | None = None,
    brake_heading_error_rad: float | None = None,
    line_offset_m: float | None = None,
    since_up_near_m: float | None = None,
    guard_m: np.ndarray | None = None,
    guard_cfg: MemoryConfig | None = None,
    remembered_sides: tuple[bool, bool] | None = None,
    velocity_body_m_s: tuple[float, float] | None = None,
    gap: Gap | None = None,
    below_clear: bool | None = None,
    path_ahead_m: float | None = None,
) -> VelocitySetpoint:
    """The setpoint to send for ``decision``, made ``since_last_frame_s`` seconds after its frame.

    * No decision, a frame older than ``cmd.stale_frame_timeout_s``, or a non-finite age: zero velocity.
    * BRAKE (or a decision carrying a non-finite number): zero velocity; with ``brake_offset_body_m``
      (float ``(3,)`` metres: the vehicle's position now minus where the brake began, in the body
      frame: forward, right, down) and ``cmd.brake_hold_gain_per_s`` > 0, the velocity back there
      instead: ``clip(-gain · offset, ±brake_hold_max_speed_m_s)`` per axis (brake position hold);
      with ``brake_heading_error_rad`` (the heading the brake began with minus the heading now,
      radians, positive = turn right), a yaw rate of ``clip(gain · error, ±max_heading_hold_rate_deg_s)``
      back to it (brake heading hold).
    * Otherwise forward = ``cruise_speed_m_s · speed_fraction`` (m/s), yaw rate =
      ``yaw · max_yaw_rate_deg_s`` (deg/s, positive turns right), down = ``-pitch · max_vertical_speed_m_s``
      (m/s; pitch up = climb = negative down). yaw and pitch are clipped to [-1, 1], the speed fraction
      to [0, 1]. No sideways velocity (right_m_s = 0) but the line hold's below.

    ``since_up_near_m`` (metres flown horizontally since the up region was last nearer than
    ``cmd.hold_clear_depth_m``, :class:`OverheadMemory`; None = off): below ``cmd.hold_resume_distance_m``
    no climb is commanded at all (neither by a rule nor by the altitude hold), since the camera cannot
    see what is straight overhead.

    ``guard_m`` (:meth:`~companion.core.memory.ObstacleMemory.guard`: remembered points out of view
    near the vehicle) with ``guard_cfg``: on any fresh decision, BRAKE included, a push away from each
    is added and the horizontal velocity toward those on the path removed; with
    ``velocity_body_m_s`` (the vehicle's horizontal velocity now, body frame: forward, right, m/s),
    the motion toward a point on the path it is actually flying is removed too (and, with
    ``counter_velocity_fraction``, leaned against) (:func:`~companion.core.memory.apply_guard`).

    Course hold (all keyword inputs optional; ``None`` = off, the paper's behaviour). Only on a CLEAR
    decision. The heading, line and turning back wait until ``heading_clear_for_s`` (seconds the
    decisions have been CLEAR without turning, :func:`is_heading_clear`; None = ``clear_for_s``)
    reaches ``cmd.hold_resume_delay_s`` (turning back also once ``any_clear_for_s``, seconds they
    have been CLEAR turning or not, reaches ``cmd.turn_back_after_clear_s``: a side rule along a wall
    can keep a CLEAR decision turning for good); the altitude hold until ``clear_for_s`` (seconds they have
    been CLEAR without turning or climbing, :func:`is_straight_clear`; None = no wait) does, and
    ``clear_for_m`` (metres flown horizontally since then; None = no wait) reaches
    ``cmd.hold_resume_distance_m``:

    * ``heading_error_rad`` (heading at engagement minus heading now, radians, positive = the course
      lies to the right): adds ``clip(heading_hold_gain_per_s · error, ±max_heading_hold_rate_deg_s)``
      deg/s of yaw rate, scaled by ``1 - |yaw|``;
    * ``line_offset_m`` (:func:`line_offset_m` of the vehicle from the line through the engagement
      point along the engagement heading): with ``cmd.line_hold_gain_per_m`` > 0, the heading aimed at
      turns toward the line by ``clip(atan(gain · offset), ±max_line_hold_angle_deg)``; with
      ``cmd.line_hold_lateral_gain_per_s`` > 0 the vehicle also flies sideways toward it at
      ``clip(gain · offset, ±max_line_hold_lateral_speed_m_s) · cos(heading error)`` m/s (right
      positive; needs ``heading_error_rad``; only toward a side region at least
      ``cmd.line_hold_lateral_clear_depth_m`` deep), tapered to 0 as the heading aimed at lies
      ``cmd.line_hold_lateral_max_aim_error_deg`` from the heading now, and scaled by ``1 - |yaw|``;
    * ``altitude_error_m`` (altitude at engagement minus altitude now, metres, positive = climb):
      adds ``clip(-altitude_hold_gain_per_s · error, ±max_altitude_hold_speed_m_s)`` m/s of down
      speed, scaled by ``1 - |pitch|``; a descent does not wait (for ``clear_for_s`` or
      ``clear_for_m``) when ``below_clear`` is True (:meth:`~companion.core.memory.ObstacleMemory.clear_below`:
      nothing remembered below the vehicle down to that altitude): what it climbed over was seen
      on the way there, and an office never gives 1.5 m of straight, clear flight. A climb back
      (below that altitude, the decision level or climbing) waits for neither: PX4 sags 0.2-0.3 m
      as it speeds up, and the controller's small climbs on a CLEAR reset the clear timers, so it
      would fly low until a low wall's top filled the up regions.
      What was overhead still stops it (``since_up_near_m``). With ``cmd.altitude_hold_on_avoid``, on
      an AVOID decision (steering round something; an office's walls never let the CLEAR wait end)
      the same climb back and descent over nothing remembered act, never against the decision's
      own climb or descent;
    * turning back: when the heading aimed at (the two above) lies more than ``cmd.turn_back_angle_deg``
      away, none of this: forward and sideways speed 0, and a yaw rate of
      ``±max_heading_hold_rate_deg_s`` toward it, whatever the side regions read (the decision's
      own climb or descent is kept, the altitude hold waits);
    * ``region_depths_m`` (float ``(9,)`` refined region depths, metres, NaN unknown): when given,
      the hold turns toward a side (right, left) or climbs/descends (up, down) only while that region
      is at least ``cmd.hold_clear_depth_m`` deep;
    * ``remembered_sides`` (:meth:`~companion.core.memory.ObstacleMemory.sides_near`: (left, right),
      True where a remembered point lies near on that side): the hold neither turns nor slides
      toward such a side (an obstacle just passed is beside or behind the vehicle, out of view).

    Stand-off: with ``region_depths_m``, every setpoint but the stale one's zero gets
    :func:`standoff_push_m_s` added (a middle-row region nearer than ``cmd.standoff_depth_m`` pushes
    the vehicle away from it), before the guard; then, with ``velocity_body_m_s`` too,
    :func:`motion_brake` (the vehicle's own motion toward what the camera reads near, beyond what it
    can stop short of, is leaned against).

    Gap centering: ``gap`` (:func:`~companion.core.memory.find_gap`: where the middle of a narrow
    gap between remembered points lies, sideways, metres, positive = right, and its width; None = no
    gap) with ``guard_cfg``: on a CLEAR decision (not turning back) the sideways speed is
    ``clip(gap_centering_gain_per_s · offset, ±max_gap_centering_speed_m_s)``, scaled by ``1 - |yaw|``,
    instead of the line hold's, at once (no wait): the centre region sees through a gap the vehicle is
    off-centre in, and the line need not run through the gap's middle. The forward speed is scaled by
    :func:`gap_lineup_fraction`: the vehicle lines up before it flies on into the gap.

    Slowing for the path: ``path_ahead_m`` (:func:`~companion.core.memory.path_ahead_m`: how far ahead
    the nearest remembered point in the vehicle's path lies, metres; None = none) with ``guard_cfg``:
    on CLEAR and AVOID decisions the forward speed is at most ``(path_ahead_m - path_stop_m) /
    path_slow_time_s`` (never below 0; :func:`path_speed_limit_m_s`).
    """
    if decision is None or not math.isfinite(since_last_frame_s):
        return ZERO_SETPOINT
    if since_last_frame_s > cmd.stale_frame_timeout_s:
        return ZERO_SETPOINT
    if decision.kind is DecisionKind.BRAKE:
        return _guarded(
            _brake_hold(brake_offset_body_m, brake_heading_error_rad, cmd), guard_m, guard_cfg, velocity_body_m_s, region_depths_m, cmd
        )
    yaw, pitch, speed = decision.yaw, decision.pitch, decision.speed_fraction
    if not (math.isfinite(yaw) and math.isfinite(pitch) and math.isfinite(speed)):
        return _guarded(ZERO_SETPOINT, guard_m, guard_cfg, velocity_body_m_s, region_depths_m, cmd)
    yaw = min(1.0, max(-1.0, yaw))
    pitch = min(1.0, max(-1.0, pitch))
    speed = min(1.0, max(0.0, speed))
    yaw_rate_deg_s = yaw * cmd.max_yaw_rate_deg_s
    down_m_s = 0.0 - pitch * cmd.max_vertical_speed_m_s
    right_m_s = 0.0
    forward_m_s = cmd.cruise_speed_m_s * speed
    clear = decision.kind is DecisionKind.CLEAR
    heading_wait_s = heading_clear_for_s if heading_clear_for_s is not None else clear_for_s
    waited = heading_wait_s is None or heading_wait_s >= cmd.hold_resume_delay_s
    turning_back = False
    aim = _aim_error_rad(heading_error_rad, line_offset_m, cmd) if clear else None
    facing_away = aim is not None and abs(aim) > math.radians(cmd.turn_back_angle_deg) and cmd.turn_back_angle_deg < 180.0
    if facing_away and (waited or (any_clear_for_s is not None and any_clear_for_s >= cmd.turn_back_after_clear_s)):
        # Facing away from the course: stop and turn back in place (module doc, turning back).
        forward_m_s, yaw_rate_deg_s = 0.0, math.copysign(cmd.max_heading_hold_rate_deg_s, aim)
        turning_back = True
    elif clear and waited:
        yaw_rate_deg_s += (1.0 - abs(yaw)) * _heading_hold_deg_s(
            heading_error_rad, region_depths_m, cmd, line_offset_m, remembered_sides
        )
        right_m_s = (1.0 - abs(yaw)) * _line_hold_right_m_s(
            line_offset_m, heading_error_rad, region_depths_m, cmd, remembered_sides
        )
    if clear and not turning_back:
        down_m_s += _clear_altitude_return_m_s(
            altitude_error_m, region_depths_m, pitch, below_clear, clear_for_s, clear_for_m, cmd
        )
    elif decision.kind is DecisionKind.AVOID and cmd.altitude_hold_on_avoid:
        # Steering round something, the vehicle still goes back to its altitude where that does not
        # fight the controller's own climb or descent: an office's AVOIDs never let the CLEAR wait
        # end, and PX4 SITL reached its doors 0.3-0.7 m above the engaged altitude, the lintel
        # within the memory's height band (the door closed on the map).
        down_m_s += (1.0 - abs(pitch)) * _altitude_return_m_s(
            altitude_error_m, region_depths_m, pitch, below_clear, cmd, waited=False
        )
    gap_on = gap is not None and guard_cfg is not None and guard_cfg.gap_centering_gain_per_s > 0.0
    if clear and not turning_back and gap_on and math.isfinite(gap.offset_m) and math.isfinite(gap.width_m):
        limit = guard_cfg.max_gap_centering_speed_m_s
        right_m_s = (1.0 - abs(yaw)) * min(limit, max(-limit, guard_cfg.gap_centering_gain_per_s * gap.offset_m))
        # not faster toward a side than the camera's reading of it allows
        right_m_s = within_room(right_m_s, 0.0, side_room_m_s(region_depths_m, cmd))
        forward_m_s *= gap_lineup_fraction(gap, guard_cfg)
    if since_up_near_m is not None and since_up_near_m < cmd.hold_resume_distance_m and down_m_s < 0.0:
        down_m_s = 0.0  # something was overhead within the last metres: it may still be, out of view
    forward_m_s = min(forward_m_s, path_speed_limit_m_s(path_ahead_m, guard_cfg))
    sp = VelocitySetpoint(
        forward_m_s=forward_m_s,
        right_m_s=right_m_s,
        down_m_s=down_m_s,
        yaw_rate_deg_s=yaw_rate_deg_s,
    )
    return _guarded(sp, guard_m, guard_cfg, velocity_body_m_s, region_depths_m, cmd)


def path_speed_limit_m_s(path_ahead_m: float | None, cfg: MemoryConfig | None) -> float:
    """The forward speed allowed with the nearest remembered point in the path ``path_ahead_m`` ahead
    (metres; None: none): ``max(0, (path_ahead_m - path_stop_m) / path_slow_time_s)`` m/s, inf when
    off or nothing is in the path: the vehicle can stop short of it though the autopilot follows a
    setpoint late."""
    if path_ahead_m is None or cfg is None or cfg.path_slow_time_s <= 0.0 or not math.isfinite(path_ahead_m):
        return math.inf
    return max(0.0, (path_ahead_m - cfg.path_stop_m) / cfg.path_slow_time_s)


def gap_lineup_fraction(gap: Gap, cfg: MemoryConfig) -> float:
    """The share of the forward speed, in [0, 1], that flies on into ``gap`` (metres, body frame):
    all of it while the vehicle is within ``slack = max(gap_lineup_min_slack_m, width / 2 -
    gap_pass_clearance_m)`` of the gap's middle, falling linearly to 0 at ``gap_lineup_ramp_m`` beyond
    that; 1 with ``gap_pass_clearance_m`` = 0. The sideways slide of gap centering goes on
    meanwhile: a vehicle off the middle of a door stops short of it, lines up, then flies through,
    instead of reaching the jamb before the slide (PX4 follows a setpoint ~0.85 s late) has moved it."""
    if cfg.gap_pass_clearance_m == 0.0:
        return 1.0
    slack = max(cfg.gap_lineup_min_slack_m, 0.5 * gap.width_m - cfg.gap_pass_clearance_m)
    excess = abs(gap.offset_m) - slack
    return min(1.0, max(0.0, 1.0 - excess / cfg.gap_lineup_ramp_m))


def standoff_push_m_s(region_depths_m: np.ndarray | None, cmd: CommandConfig) -> tuple[float, float]:
    """The stand-off's push, body-frame (forward, right) m/s: for each middle-row region (left,
    center, right; float ``(9,)`` refined depths, metres, NaN unknown) nearer than
    ``cmd.standoff_depth_m``, ``standoff_gain_per_s · (standoff_depth_m - depth)`` away from it
    (straight back for the center, :data:`STANDOFF_SIDE_BEARING_RAD` off straight back for a side,
    toward the other side), summed and capped at ``max_standoff_speed_m_s``. (0, 0) when off, without
    depths, or for unknown regions.

    It closes the loop on what the camera measures, not on the velocity estimate, which is what a
    drifting estimate needs (:class:`~companion.config.command.CommandConfig`, ``standoff_depth_m``)."""
    if region_depths_m is None or cmd.standoff_depth_m <= 0.0 or cmd.standoff_gain_per_s <= 0.0:
        return 0.0, 0.0
    d = np.asarray(region_depths_m, dtype=np.float64)
    c, s = math.cos(STANDOFF_SIDE_BEARING_RAD), math.sin(STANDOFF_SIDE_BEARING_RAD)
    forward = right = 0.0
    for name, (uf, ur) in (("left", (c, -s)), ("center", (1.0, 0.0)), ("right", (c, s))):
        depth = float(d[REGION_INDEX[name]])
        if math.isfinite(depth) and depth < cmd.standoff_depth_m:
            push = cmd.standoff_gain_per_s * (cmd.standoff_depth_m - depth)
            forward -= push * uf
            right -= push * ur
    n = math.hypot(forward, right)
    if n > cmd.max_standoff_speed_m_s:
        k = cmd.max_standoff_speed_m_s / n
        forward, right = forward * k, right * k
    return forward, right


def _guarded(
    sp: VelocitySetpoint,
    guard_m: np.ndarray | None,
    cfg: MemoryConfig | None,
    velocity_body_m_s: tuple[float, float] | None,
    region_depths_m: np.ndarray | None = None,
    cmd: CommandConfig | None = None,
) -> VelocitySetpoint:
    """``sp`` with the stand-off's push (:func:`standoff_push_m_s`, with ``region_depths_m`` and
    ``cmd``) added, braked for where the vehicle is actually going (:func:`motion_brake`), then the
    memory's guard applied (:func:`~companion.core.memory.apply_guard`), never faster toward a side
    than the camera's reading of it allows (:func:`side_room_m_s`), and last never faster forward than
    the vehicle can stop short of what the centre region reads (:func:`within_forward_room`)."""
    if cmd is not None:
        push_f, push_r = standoff_push_m_s(region_depths_m, cmd)
        if push_f != 0.0 or push_r != 0.0:
            sp = VelocitySetpoint(sp.forward_m_s + push_f, sp.right_m_s + push_r, sp.down_m_s, sp.yaw_rate_deg_s)
        sp = motion_brake(sp, region_depths_m, velocity_body_m_s, cmd)
    if guard_m is not None and cfg is not None and len(guard_m) > 0:
        room = side_room_m_s(region_depths_m, cmd)
        forward, right = apply_guard(sp.forward_m_s, sp.right_m_s, guard_m, cfg, velocity_body_m_s, room)
        sp = VelocitySetpoint(forward_m_s=forward, right_m_s=right, down_m_s=sp.down_m_s, yaw_rate_deg_s=sp.yaw_rate_deg_s)
    return sp if cmd is None else within_forward_room(sp, region_depths_m, cmd)


def stoppable_speed_m_s(range_m: float, cmd: CommandConfig) -> float:
    """The speed, m/s, at which the vehicle still stops short of something ``range_m`` metres away, less
    ``cmd.motion_brake_clearance_m``, within ``cmd.motion_brake_lag_s``: ``max(0, (range -
    clearance) / lag)`` (the motion brake's rule, and the forward room's)."""
    return max(0.0, (range_m - cmd.motion_brake_clearance_m) / cmd.motion_brake_lag_s)


def within_forward_room(sp: VelocitySetpoint, region_depths_m: np.ndarray | None, cmd: CommandConfig) -> VelocitySetpoint:
    """``sp`` with its forward speed at most ``max(0, (centre - motion_brake_clearance_m) /
    motion_brake_lag_s)`` m/s, ``centre`` the centre region's depth (metres, from ``region_depths_m``,
    float ``(9,)``): what the vehicle can stop short of. The controller's own forward speed is already
    slower than this with the centre at 0.56 m or more (nearer, its creep of avoid_speed_fraction ·
    cruise stops and it turns in place); what it catches is the rest of a setpoint, which does not
    look ahead: the memory's push away from a wall behind, a hold's pull back to its anchor (looking
    round close to a box with a wall behind, the push would send the vehicle forward into the box
    the camera reads). Unchanged when the motion brake is
    off, without depths or where the centre cannot be read (the controller counts it as near)."""
    if cmd.motion_brake_clearance_m <= 0.0 or region_depths_m is None or sp.forward_m_s <= 0.0:
        return sp
    centre = float(np.asarray(region_depths_m, dtype=np.float64)[REGION_INDEX["center"]])
    if not math.isfinite(centre):
        return sp
    allowed = stoppable_speed_m_s(centre, cmd)
    if sp.forward_m_s <= allowed:
        return sp
    return VelocitySetpoint(allowed, sp.right_m_s, sp.down_m_s, sp.yaw_rate_deg_s)


#: The middle row's regions by bearing from the nose, degrees (a ~90° view in thirds): the centre
#: within this, left and right out to :data:`MOTION_VIEW_HALF_DEG`; beyond it the memory guards.
MOTION_CENTRE_HALF_DEG = 15.0
MOTION_VIEW_HALF_DEG = 45.0


def motion_brake(
    sp: VelocitySetpoint,
    region_depths_m: np.ndarray | None,
    velocity_body_m_s: tuple[float, float] | None,
    cmd: CommandConfig,
) -> VelocitySetpoint:
    """``sp`` braked for where the vehicle is actually going (``command.motion_brake_*``).

    ``velocity_body_m_s`` (the vehicle's measured horizontal velocity, body frame: forward, right,
    m/s) picks the middle-row region it points into (``region_depths_m``, float ``(9,)`` refined
    depths, metres; the centre within :data:`MOTION_CENTRE_HALF_DEG` of the nose, left or right out
    to :data:`MOTION_VIEW_HALF_DEG`); the range along it is that depth over the cosine of the
    bearing. At a speed above ``(range - motion_brake_clearance_m) / motion_brake_lag_s`` (at least
    0) the setpoint loses its own motion along the velocity and gets the excess against it, the
    horizontal speed capped at ``cruise_speed_m_s``. Unchanged when off, without a velocity or
    depths, when moving backwards or out of the view's sides (the memory's guard acts there), or
    when that region cannot be read (the controller already counts it as near).

    A first-order lag of ``lag`` stops a vehicle moving at ``v`` in about ``v · lag``; leaning
    against the excess shortens it, as the memory's counter-velocity lean does for what is out of
    view."""
    if cmd.motion_brake_clearance_m <= 0.0 or region_depths_m is None or velocity_body_m_s is None:
        return sp
    vf, vr = float(velocity_body_m_s[0]), float(velocity_body_m_s[1])
    speed = math.hypot(vf, vr)
    if not math.isfinite(speed) or speed < 1e-3 or vf <= 0.0:
        return sp
    bearing = math.atan2(vr, vf)
    half = math.radians(MOTION_CENTRE_HALF_DEG)
    if abs(bearing) < half:
        name = "center"
    elif abs(bearing) < math.radians(MOTION_VIEW_HALF_DEG):
        name = "right" if bearing > 0.0 else "left"
    else:
        return sp
    depth = float(np.asarray(region_depths_m, dtype=np.float64)[REGION_INDEX[name]])
    if not math.isfinite(depth):
        return sp
    allowed = stoppable_speed_m_s(depth / math.cos(bearing), cmd)
    if speed <= allowed:
        return sp
    uf, ur = vf / speed, vr / speed
    toward = max(0.0, sp.forward_m_s * uf + sp.right_m_s * ur)
    k = toward + (speed - allowed)
    forward, right = sp.forward_m_s - k * uf, sp.right_m_s - k * ur
    n = math.hypot(forward, right)
    if n > cmd.cruise_speed_m_s > 0.0:
        forward, right = forward * cmd.cruise_speed_m_s / n, right * cmd.cruise_speed_m_s / n
    return VelocitySetpoint(forward, right, sp.down_m_s, sp.yaw_rate_deg_s)


#: Descending toward ``command.min_altitude_m``, the down speed is at most this times the height left
#: above it, m/s per metre: a first-order approach, so the autopilot's lag (PX4 SIH: ~0.85 s) does not
#: carry the vehicle through the floor.
FLOOR_GAIN_PER_S = 2.0

#: Below the floor, the climb back is refused only where the up region reads nearer than this,
#: metres. An unknown up region does not refuse it: the ground under the floor is measured (the
#: altitude), the up region is what lies ahead and above, not overhead, and the climb goes no higher
#: than the floor the user set (in front of a plain wall the up region reads unknown, and refusing
#: would let the vehicle sink to the ground).
FLOOR_CLIMB_UP_CLEAR_M = 1.0


def above_floor(
    sp: VelocitySetpoint,
    position_ned_m: np.ndarray | None,
    cmd: CommandConfig,
    region_depths_m: np.ndarray | None = None,
    climb_back: bool = False,
    velocity_ned_m_s: np.ndarray | None = None,
) -> VelocitySetpoint:
    """``sp`` with its descent capped at ``FLOOR_GAIN_PER_S · (altitude - cmd.min_altitude_m)`` m/s
    (0 at or below the floor), the altitude being ``-down`` of ``position_ned_m`` (float ``(3,)`` NED
    metres from the autopilot's local origin), less what a sink of ``velocity_ned_m_s`` (float
    ``(3,)`` NED m/s, or None) covers in ``cmd.motion_brake_lag_s``: the autopilot's lag otherwise
    carries a fast descent through the floor. With ``climb_back`` (a fresh decision's setpoint), below
    the floor (so reckoned) it climbs at ``FLOOR_GAIN_PER_S`` times the shortfall (at most
    ``cmd.max_altitude_hold_speed_m_s``; a faster climb in ``sp`` is kept) unless the up region of
    ``region_depths_m`` (float ``(9,)`` metres, NaN unknown; None: not known, no climb) reads nearer than
    :data:`FLOOR_CLIMB_UP_CLEAR_M`: PX4 in offboard velocity control holds a vertical speed, not a
    height, and drifts under a setpoint that asks for none, so only a climb back keeps it off the
    ground. Unchanged when off or without a finite position."""
    if cmd.min_altitude_m <= 0.0 or position_ned_m is None:
        return sp
    altitude = -float(np.asarray(position_ned_m, dtype=np.float64).reshape(-1)[2])
    if not math.isfinite(altitude):
        return sp
    if velocity_ned_m_s is not None:
        sink = float(np.asarray(velocity_ned_m_s, dtype=np.float64).reshape(-1)[2])
        if math.isfinite(sink) and sink > 0.0:
            altitude -= sink * cmd.motion_brake_lag_s
    short = cmd.min_altitude_m - altitude
    if (
        climb_back
        and short > 0.0
        and region_depths_m is not None
        and not _reads_near(region_depths_m, "up", FLOOR_CLIMB_UP_CLEAR_M)
    ):
        climb = min(cmd.max_altitude_hold_speed_m_s, FLOOR_GAIN_PER_S * short)
        if sp.down_m_s > -climb:
            return VelocitySetpoint(sp.forward_m_s, sp.right_m_s, -climb, sp.yaw_rate_deg_s)
        return sp
    if sp.down_m_s <= 0.0:
        return sp
    limit = FLOOR_GAIN_PER_S * max(0.0, -short)
    if sp.down_m_s <= limit:
        return sp
    return VelocitySetpoint(sp.forward_m_s, sp.right_m_s, limit, sp.yaw_rate_deg_s)


def _reads_near(region_depths_m: np.ndarray, side: str, depth_m: float) -> bool:
    """Whether region ``side`` of ``region_depths_m`` measured something nearer than ``depth_m``
    (False for an unknown region)."""
    depth = float(region_depths_m[REGION_INDEX[side]])
    return math.isfinite(depth) and depth < depth_m


#: Below ``memory.clearance_below_m`` over a remembered point, the vehicle climbs at this times the
#: shortfall, m/s per metre: PX4 SIH sagged 0.1-0.2 m/s while braking over a wall's top.
BELOW_CLIMB_GAIN_PER_S = 2.0


def clear_of_below(
    sp: VelocitySetpoint,
    gap_below_m: float | None,
    region_depths_m: np.ndarray | None,
    clearance_m: float,
    cmd: CommandConfig,
) -> VelocitySetpoint:
    """``sp`` climbing at least ``BELOW_CLIMB_GAIN_PER_S · (clearance_m - gap_below_m)`` m/s (at most
    ``cmd.max_altitude_hold_speed_m_s``) when the highest remembered point below the vehicle
    (:meth:`~companion.core.memory.ObstacleMemory.gap_below_m`, metres) is nearer than
    ``clearance_m``, and only while the up region (float ``(9,)`` refined depths, metres, NaN
    unknown) is open (``cmd.hold_clear_depth_m``). A faster climb in ``sp`` is kept; unchanged when
    off, without a gap, or clear."""
    if clearance_m <= 0.0 or gap_below_m is None or not math.isfinite(gap_below_m) or gap_below_m >= clearance_m:
        return sp
    if not _side_open(region_depths_m, "up", cmd.hold_clear_depth_m):
        return sp
    climb = min(cmd.max_altitude_hold_speed_m_s, BELOW_CLIMB_GAIN_PER_S * (clearance_m - gap_below_m))
    if sp.down_m_s <= -climb:
        return sp
    return VelocitySetpoint(sp.forward_m_s, sp.right_m_s, -climb, sp.yaw_rate_deg_s)


#: Sideways, the memory may move the vehicle toward a side reading ``depth`` (< the threshold D,
#: ``command.sideways_clear_depth_m``) at ``SIDE_ROOM_GAIN_PER_S · (depth - D/2)`` m/s at most.
SIDE_ROOM_GAIN_PER_S = 1.0


def side_room_m_s(region_depths_m: np.ndarray | None, cmd: CommandConfig | None) -> tuple[float, float] | None:
    """(left, right): the largest sideways speed, m/s, at which the memory's guard (its push, its lean,
    its slide past a point) and gap centering may move the vehicle toward that side, from the
    middle-row region's depth (float ``(9,)`` refined depths, metres, NaN unknown): unlimited (inf) at
    or beyond ``D = cmd.sideways_clear_depth_m`` and where the region reads at least as deep as the
    other side's; else ``SIDE_ROOM_GAIN_PER_S · (depth - D/2)``, 0 from D/2 in and where the region
    cannot be read (an unknown side is never the deeper one). None when off or without depths.

    The memory places what it saw with a position estimate that wanders; the camera does not. The
    deeper side is not limited: in a dead end both sides read near, and the push away from the wall
    the vehicle drifts toward is what keeps it off that wall."""
    if region_depths_m is None or cmd is None or cmd.sideways_clear_depth_m <= 0.0:
        return None
    half = 0.5 * cmd.sideways_clear_depth_m
    left = float(region_depths_m[REGION_INDEX["left"]])
    right = float(region_depths_m[REGION_INDEX["right"]])

    def room(side: str, depth: float, other: float) -> float:
        if _side_open(region_depths_m, side, cmd.sideways_clear_depth_m) or depth >= other:  # NaN: False
            return math.inf
        return SIDE_ROOM_GAIN_PER_S * (depth - half) if depth > half else 0.0  # NaN: 0

    return room("left", left, right), room("right", right, left)


#: A turn in place keeps its side while its target lies within this of right behind, degrees
#: (:func:`detour_setpoint`): more than the yaw a step and the autopilot's lag move it back across.
TURN_SIDE_KEEP_DEG = 30.0


def detour_setpoint(
    command: DetourCommand,
    decision: Decision | None,
    since_last_frame_s: float,
    cmd: CommandConfig,
    detour_cfg: DetourConfig,
    *,
    position_ned_m: np.ndarray | None,
    yaw_rad: float | None,
    brake_offset_body_m: np.ndarray | None = None,
    brake_heading_error_rad: float | None = None,
    guard_m: np.ndarray | None = None,
    guard_cfg: MemoryConfig | None = None,
    velocity_body_m_s: tuple[float, float] | None = None,
    region_depths_m: np.ndarray | None = None,
    turn_sign: float = 0.0,
    altitude_error_m: float | None = None,
    below_clear: bool | None = None,
    clear_for_s: float | None = None,
    clear_for_m: float | None = None,
    since_up_near_m: float | None = None,
    path_ahead_m: float | None = None,
) -> VelocitySetpoint:
    """The setpoint while the detour layer acts (:class:`~companion.core.detour.DetourCommand`).

    The reactive layer stays absolute: the detour only turns the vehicle, and holds or slows it.

    * No decision, or a frame older than ``cmd.stale_frame_timeout_s``: zero velocity, as always.
    * Turning in place (the command has an anchor: looking round, turning toward a detour's direction
      or back to the goal): the brake's position hold toward the anchor (where the vehicle was when
      the turn began; ``clip(-brake_hold_gain_per_s · offset, ±brake_hold_max_speed_m_s)``) and a yaw
      rate toward the target, ``turn_rate_deg_s``, proportionally less within 15° of it. A turn in
      place moves the vehicle toward nothing, so it goes on whatever the decision is, a brake
      included; the guard still acts. ``turn_sign`` (+1 right, -1 left, 0 none: the side this turn
      has been turning) keeps that side while the target lies more than 180° -
      :data:`TURN_SIDE_KEEP_DEG` away: a target right behind is as near either way, and choosing
      afresh each step turned the vehicle back and forth across it.
    * Flying a direction: a BRAKE decision is the reactive setpoint itself (the brake's holds);
      otherwise the reactive setpoint (:func:`setpoint_for` of the decision alone: the controller's
      yaw, pitch and slowing) with its forward speed scaled by ``min(1, speed_m_s / cruise_speed_m_s)
      · max(0, cos(heading error))`` (never faster, never sideways or up or down beyond it), and a yaw
      rate toward the direction of ``clip(heading_hold_gain_per_s · error, ±turn_rate_deg_s)``,
      scaled by ``1 - |yaw|`` (the controller's own turn comes first). On a CLEAR decision the
      altitude hold acts as in course hold (``altitude_error_m``, ``below_clear``, ``clear_for_s``,
      ``clear_for_m``, ``since_up_near_m``: :func:`setpoint_for`): without it a detour flies on at
      whatever height the vehicle has drifted to, where a door's lintel can fall within the memory's
      height band and close the door on the map. Flying, the forward speed is also held to
      :func:`path_speed_limit_m_s` of ``path_ahead_m``, as in :func:`setpoint_for`.

    ``region_depths_m`` (float ``(9,)`` metres, NaN unknown): the stand-off's push acts here too
    (:func:`standoff_push_m_s`).
    """
    if decision is None or not math.isfinite(since_last_frame_s) or since_last_frame_s > cmd.stale_frame_timeout_s:
        return ZERO_SETPOINT
    yaw = None if yaw_rad is None or not math.isfinite(yaw_rad) else float(yaw_rad)
    err = None
    if command.target_yaw_rad is not None and yaw is not None:
        err = (command.target_yaw_rad - yaw + math.pi) % (2.0 * math.pi) - math.pi
    limit = detour_cfg.turn_rate_deg_s
    if command.anchor_ned_m is not None:
        offset = None
        if position_ned_m is not None and yaw is not None:
            offset = brake_offset_body(np.asarray(position_ned_m, dtype=np.float64), command.anchor_ned_m, yaw)
        hold = _brake_hold(offset, None, cmd)
        rate = 0.0 if err is None else limit * max(-1.0, min(1.0, err / math.radians(15.0)))
        if err is not None and turn_sign != 0.0 and abs(err) > math.pi - math.radians(TURN_SIDE_KEEP_DEG):
            rate = math.copysign(limit, turn_sign)
        sp = VelocitySetpoint(hold.forward_m_s, hold.right_m_s, hold.down_m_s, rate)
        return _guarded(sp, guard_m, guard_cfg, velocity_body_m_s, region_depths_m, cmd)
    if decision.kind is DecisionKind.BRAKE:
        return setpoint_for(
            decision,
            since_last_frame_s,
            cmd,
            brake_offset_body_m=brake_offset_body_m,
            brake_heading_error_rad=brake_heading_error_rad,
            guard_m=guard_m,
            guard_cfg=guard_cfg,
            velocity_body_m_s=velocity_body_m_s,
            region_depths_m=region_depths_m,
        )
    reactive = setpoint_for(decision, since_last_frame_s, cmd)
    if not (math.isfinite(decision.yaw) and math.isfinite(decision.pitch) and math.isfinite(decision.speed_fraction)):
        return _guarded(reactive, guard_m, guard_cfg, velocity_body_m_s, region_depths_m, cmd)
    scale = 0.0 if cmd.cruise_speed_m_s <= 0.0 else min(1.0, detour_cfg.speed_m_s / cmd.cruise_speed_m_s)
    rate = reactive.yaw_rate_deg_s
    if err is not None:
        scale *= max(0.0, math.cos(err))
        turn = min(limit, max(-limit, math.degrees(cmd.heading_hold_gain_per_s * err)))
        rate += (1.0 - min(1.0, abs(decision.yaw))) * turn
    down = reactive.down_m_s
    if decision.kind is DecisionKind.CLEAR:
        hold = _clear_altitude_return_m_s(
            altitude_error_m, region_depths_m, min(1.0, max(-1.0, decision.pitch)), below_clear, clear_for_s, clear_for_m, cmd
        )
        if not (hold < 0.0 and since_up_near_m is not None and since_up_near_m < cmd.hold_resume_distance_m):
            down += hold  # no climb back where something was overhead, out of view now
    forward = min(reactive.forward_m_s * scale, path_speed_limit_m_s(path_ahead_m, guard_cfg))
    sp = VelocitySetpoint(forward, reactive.right_m_s, down, rate)
    return _guarded(sp, guard_m, guard_cfg, velocity_body_m_s, region_depths_m, cmd)
