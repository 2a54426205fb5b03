"""The safety filters after the planner: each a pure ``(setpoint, context) -> setpoint`` function, and
their order written once (:data:`CHAIN`).

1. :func:`stale_to_zero`: no frame newer than ``command.stale_frame_timeout_s``: zero velocity;
2. :func:`brake_hold`: holding (a dead end, the goal): no turn, and no faster than the slow way back
   to the held point; the fuzzy controller brakes (the centre near
   with no escape): no faster toward the centre than the speed law allows on the centre's depth
   (unknown counts as 0 m);
3. :func:`speed_law_limit`: the commanded velocity, and the component of it along the way the vehicle
   is actually moving (the autopilot follows late), no faster than the speed law on the free length
   the map sees along each, unless the vehicle can stop on the path it swings onto the command by;
   a command outside the camera's view slower still (fly where you look);
4. :func:`keep_off`: within ``stop_margin_m`` of the nearest surface seen (body to surface), no
   component toward it, and off it at the hold's gain: the map's inflation is the radius alone, and a
   vehicle beside a surface drifts by what the unexplained motion's measure has not caught yet;
5. :func:`counter_unexplained`: the motion the reported velocity does not explain (measured on the
   position's track, vertical too) taken off the setpoint, so that the vehicle moves as commanded;
6. :func:`floor_ceiling`: no descent below the floor nor climb above the ceiling, slowing on the last
   metre;
7. :func:`envelope`: the horizontal and vertical speed and the yaw rate within the safety envelope.

Setpoints are body-frame (FRD) :class:`~companion.core.types.VelocitySetpoint`; the context's yaw turns
them into NED where a filter needs it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from companion.config.planner import PlannerConfig
from companion.core.planner.local import HOLD_GAIN_PER_S, HOLD_MAX_M_S, speed_law, stopping_m
from companion.core.types import ZERO_SETPOINT, Decision, DecisionKind, VelocitySetpoint

#: Below this speed the vehicle's motion has no direction worth checking, m/s (a velocity
#: estimate's noise).
MOVING_M_S = 0.1
#: Within this of the floor or ceiling a climb or descent slows in proportion, metres.
BAND_SLOW_M = 1.0


def view_factor(off_axis_rad: float, view_half_rad: float) -> float:
    """The share of the speed law's speed a command may fly at ``off_axis_rad`` (radians, horizontal)
    from the camera's axis: 1 within the view's half-angle ``view_half_rad``, falling linearly to 0 at
    a right angle and beyond (the space there is only remembered, in a position estimate that drifts:
    the planner turns the camera to where it flies, and the speed comes as the way comes into view)."""
    a = abs(off_axis_rad)
    if a <= view_half_rad:
        return 1.0
    return max(0.0, (0.5 * math.pi - a) / max(0.5 * math.pi - view_half_rad, 1e-6))


@dataclass(frozen=True)
class SafetyContext:
    """What the filters know of the tick (frozen).

    Attributes:
        frame_age_s: age of the newest frame's decision, seconds (inf: none yet).
        stale_after_s: ``command.stale_frame_timeout_s``.
        holding: the planner holds (a dead end, the goal).
        decision: the newest fuzzy decision, or None.
        centre_depth_m: the centre region's depth, metres (NaN unknown).
        yaw_rad: heading, radians.
        altitude_m: altitude above the local origin, metres.
        velocity_ned_m_s: float ``(3,)`` the vehicle's motion, NED m/s: the reported velocity plus
            ``unexplained_ned_m_s``.
        unexplained_ned_m_s: float ``(3,)`` the motion of the reported position the reported velocity
            does not explain, NED m/s (zeros: none measured).
        free_along: the map's seen-free length (metres) along a unit NED direction (float ``(3,)``).
        free_swinging: the seen-free length (metres) of the path the vehicle flies from its motion onto
            a velocity command (float ``(3,)`` NED m/s): the command's line's, shortened to where the
            swing onto it enters a surface's inflation (the planner's predicted path); None: unknown
            (the motion is judged on its own line alone).
        planner: the planner section (speed law, floor, ceiling).
        max_horizontal_m_s, max_vertical_m_s, max_yaw_rate_deg_s: the safety envelope.
        view_half_rad: half the camera's horizontal view, radians.
        surface_gap_m: the gap between the body and the nearest surface seen, metres (inf: none
            within reach).
        surface_dir_ned: float ``(3,)`` unit NED direction toward that surface (None: none).
    """

    frame_age_s: float
    stale_after_s: float
    holding: bool
    decision: Decision | None
    centre_depth_m: float
    yaw_rad: float
    altitude_m: float
    velocity_ned_m_s: np.ndarray
    unexplained_ned_m_s: np.ndarray
    free_along: Callable[[np.ndarray], float]
    planner: PlannerConfig
    max_horizontal_m_s: float
    max_vertical_m_s: float
    max_yaw_rate_deg_s: float
    view_half_rad: float = math.radians(40.0)
    surface_gap_m: float = math.inf
    surface_dir_ned: np.ndarray | None = None
    free_swinging: Callable[[np.ndarray], float] | None = None


def to_ned(sp: VelocitySetpoint, yaw_rad: float) -> np.ndarray:
    """float64 ``(3,)`` NED velocity of a body-frame setpoint at heading ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([c * sp.forward_m_s - s * sp.right_m_s, s * sp.forward_m_s + c * sp.right_m_s, sp.down_m_s])


def from_ned(v: np.ndarray, yaw_rad: float, yaw_rate_deg_s: float) -> VelocitySetpoint:
    """The body-frame setpoint of NED velocity ``v`` (float ``(3,)`` m/s) at heading ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return VelocitySetpoint(
        forward_m_s=float(c * v[0] + s * v[1]),
        right_m_s=float(-s * v[0] + c * v[1]),
        down_m_s=float(v[2]),
        yaw_rate_deg_s=float(yaw_rate_deg_s),
    )


def stale_to_zero(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """Zero velocity without a frame newer than the stale timeout."""
    return ZERO_SETPOINT if not ctx.frame_age_s <= ctx.stale_after_s else sp


def brake_hold(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """While holding, no turn and at most :data:`HOLD_MAX_M_S` (the planner's way back to the held
    point); under the fuzzy controller's brake, the forward speed within the speed law on the centre
    region's depth (unknown: 0 m)."""
    if ctx.holding:
        n = math.sqrt(sp.forward_m_s**2 + sp.right_m_s**2 + sp.down_m_s**2)
        k = 1.0 if n <= HOLD_MAX_M_S else HOLD_MAX_M_S / n
        return VelocitySetpoint(sp.forward_m_s * k, sp.right_m_s * k, sp.down_m_s * k, 0.0)
    d = ctx.decision
    if d is not None and d.kind is DecisionKind.BRAKE:
        depth = ctx.centre_depth_m if math.isfinite(ctx.centre_depth_m) else 0.0
        cap = float(speed_law(depth, ctx.planner))
        if sp.forward_m_s > cap:
            return VelocitySetpoint(cap, sp.right_m_s, sp.down_m_s, sp.yaw_rate_deg_s)
    return sp


def speed_law_limit(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """The commanded speed within the speed law on the free length along it, times
    :func:`view_factor` of the command's bearing off the camera's axis; and its component along the
    vehicle's motion within the speed law on the free length along that, reversed where the vehicle
    cannot stop in that length even braking now. Holding, the command leads
    back to the held point, where the vehicle's body was (the way back need not have been seen): only
    the motion is bounded.

    Faster than the law on its line, the motion is not braked where the path the vehicle swings onto
    the command by leaves it room to stop from the faster of its speed and the command's
    (``free_swinging``): that is a way to stop too, the one the planner chose and checked. It keeps
    its speed along the line, and gains none there. Judged on its own straight line alone, a vehicle
    climbing over a box's top a degree shallower than the planner's climb, or turning past a pillar,
    was braked from 2.4 m/s to a crawl under a way seen free for 7 m."""
    v = to_ned(sp, ctx.yaw_rad)
    speed = float(np.linalg.norm(v))
    if speed > 1e-9 and not ctx.holding:
        cap = float(speed_law(ctx.free_along(v / speed), ctx.planner))
        h = math.hypot(sp.forward_m_s, sp.right_m_s)
        if h > 1e-9:  # the bearing off the axis: body frame, forward is the camera's axis
            cap *= view_factor(math.atan2(abs(sp.right_m_s), sp.forward_m_s), ctx.view_half_rad)
        if speed > cap:
            v = v * (cap / speed)
    m = np.asarray(ctx.velocity_ned_m_s, dtype=np.float64)
    ms = float(np.linalg.norm(m))
    if ms > MOVING_M_S:
        u = m / ms
        free_u = ctx.free_along(u)
        cap = float(speed_law(free_u, ctx.planner))
        if ms > cap:
            # Where it can stop on its swing onto the command (gaining no speed along this line), it
            # is not braked.
            keep = v - max(float(v @ u) - ms, 0.0) * u
            if _stops_on_swing(keep, ms, ctx):
                return from_ned(keep, ctx.yaw_rad, sp.yaw_rate_deg_s)
            # Faster than the law allows on this length: of the latency it budgets before braking at a,
            # only ``left`` is still there at this speed. A lagging vehicle (first order, time constant
            # within the latency) decelerates at once by the setpoint's shortfall over the latency, so
            # the setpoint drops a·(latency − left) below its speed: braking in proportion to the
            # latency spent, a when none is left: there ``left`` no longer falls (braking at a), and
            # the vehicle stops in the length.
            # All at once at the first excess, the setpoint stepped from cruise to zero each time the
            # speed reported crossed the law by a hair.
            p = ctx.planner
            a = p.braking_accel_m_s2
            room = max(free_u - p.stop_margin_m, 0.0)
            left = min(max((room - ms * ms / (2.0 * a)) / ms, 0.0), p.latency_s)
            cap = max(0.0, min(cap, ms - a * (p.latency_s - left)))
            # Too fast to stop even braking now: the setpoint reverses along the motion by the excess
            # of the reported velocity (at most the hold's speed), so that an autopilot's velocity
            # integrator is wound back too (told zero, PX4 creeps on for seconds); back is where the
            # body just was. The unexplained motion is counter_unexplained's.
            now = math.sqrt(2.0 * a * max(free_u - p.stop_margin_m, 0.0))
            reported = float((m - ctx.unexplained_ned_m_s) @ u)
            if reported > now:
                cap = -min(reported - now, HOLD_MAX_M_S)
        along = float(v @ u)
        if along > cap:
            v = v - (along - cap) * u
    return from_ned(v, ctx.yaw_rad, sp.yaw_rate_deg_s)


def _stops_on_swing(v: np.ndarray, motion_m_s: float, ctx: SafetyContext) -> bool:
    """Whether the vehicle moving at ``motion_m_s`` can stop on the path it swings onto the command
    ``v`` (float ``(3,)`` NED m/s) by: not holding, no surface within the stop margin (there the map
    judges a swing on surfaces alone, and :func:`keep_off` acts), and that path seen free for the
    stopping length of the faster of the two."""
    speed = float(np.linalg.norm(v))
    if ctx.holding or ctx.free_swinging is None or speed <= 1e-9:
        return False
    if ctx.surface_gap_m < ctx.planner.stop_margin_m:
        return False
    return ctx.free_swinging(v) >= stopping_m(max(motion_m_s, speed), ctx.planner)


def keep_off(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """Within ``stop_margin_m`` of the nearest surface seen (the gap between the body and it): no
    component toward it, and at least ``HOLD_GAIN_PER_S`` times the depth into the margin away from
    it (at most :data:`HOLD_MAX_M_S`). The map inflates surfaces by the radius alone, so a path may
    graze one; beside it the vehicle moves by what the unexplained motion's measure has not caught
    yet (a drift that changes within the measure's window and the autopilot's response), and a
    vehicle turning in place there has no speed law to stop it. The same margin as after a planned
    stop, sideways: where two surfaces are both within it (a doorway) the nearer pushes, and the
    vehicle settles between them. Not on stale frames (zero is zero)."""
    n = ctx.surface_dir_ned
    margin = ctx.planner.stop_margin_m
    if n is None or not ctx.surface_gap_m < margin or not ctx.frame_age_s <= ctx.stale_after_s:
        return sp
    v = to_ned(sp, ctx.yaw_rad)
    toward = float(v @ n)
    off = min(HOLD_GAIN_PER_S * (margin - ctx.surface_gap_m), HOLD_MAX_M_S)
    if toward <= -off:
        return sp
    return from_ned(v - (toward + off) * n, ctx.yaw_rad, sp.yaw_rate_deg_s)


def counter_unexplained(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """The unexplained motion taken off the setpoint, vertical too (the autopilot tracks its velocity
    estimate; the vehicle moves at the setpoint plus the estimate's error; PX4 drifted 0.4 m up in
    4 s under zero vertical speed). Holding too: the hold
    steers back to its point on the position, which alone lags a drift by its speed over the hold's
    gain. Not on stale frames (zero is zero)."""
    u = ctx.unexplained_ned_m_s
    if not ctx.frame_age_s <= ctx.stale_after_s or not np.any(u):
        return sp
    v = to_ned(sp, ctx.yaw_rad) - u
    return from_ned(v, ctx.yaw_rad, sp.yaw_rate_deg_s)


def floor_ceiling(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """No descent below the floor nor climb above the ceiling; within :data:`BAND_SLOW_M` of either,
    the speed toward it in proportion to the distance left."""
    p = ctx.planner
    down = sp.down_m_s
    vmax = ctx.max_vertical_m_s
    if down > 0.0:
        down = min(down, vmax * max(0.0, ctx.altitude_m - p.floor_m) / BAND_SLOW_M)
    elif down < 0.0:
        down = max(down, -vmax * max(0.0, p.ceiling_m - ctx.altitude_m) / BAND_SLOW_M)
    return sp if down == sp.down_m_s else VelocitySetpoint(sp.forward_m_s, sp.right_m_s, down, sp.yaw_rate_deg_s)


def envelope(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """Horizontal speed, vertical speed and yaw rate within the safety envelope."""
    h = math.hypot(sp.forward_m_s, sp.right_m_s)
    k = 1.0 if h <= ctx.max_horizontal_m_s else ctx.max_horizontal_m_s / h
    vz = max(-ctx.max_vertical_m_s, min(ctx.max_vertical_m_s, sp.down_m_s))
    r = max(-ctx.max_yaw_rate_deg_s, min(ctx.max_yaw_rate_deg_s, sp.yaw_rate_deg_s))
    return VelocitySetpoint(sp.forward_m_s * k, sp.right_m_s * k, vz, r)


#: The order, written once: the first filters may zero what the later ones would only trim.
CHAIN: tuple[Callable[[VelocitySetpoint, SafetyContext], VelocitySetpoint], ...] = (
    stale_to_zero,
    brake_hold,
    speed_law_limit,
    keep_off,
    counter_unexplained,
    floor_ceiling,
    envelope,
)


def apply_chain(sp: VelocitySetpoint, ctx: SafetyContext) -> VelocitySetpoint:
    """``sp`` through every filter of :data:`CHAIN`, in order."""
    return trace_chain(sp, ctx)[0]


def trace_chain(sp: VelocitySetpoint, ctx: SafetyContext) -> tuple[VelocitySetpoint, tuple[str, ...]]:
    """:func:`apply_chain`, and the names of the filters that changed the setpoint, in order (what
    made the vehicle fly otherwise than the planner chose: the health message's ``limited_by``)."""
    changed: list[str] = []
    for f in CHAIN:
        out = f(sp, ctx)
        if out != sp:
            changed.append(f.__name__)
        sp = out
    return sp, tuple(changed)
