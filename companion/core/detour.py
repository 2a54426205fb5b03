"""The detour layer: a way round what the reactive controller cannot pass (pure; time is passed in).

The Mamdani controller (:mod:`companion.core.fuzzy.avoidance`) sees only its nine regions: in front of
a box or a wall wider than the view it brakes and holds, or steers round and is steered back into it
by course hold. The obstacle memory (:mod:`companion.core.memory`) holds what the camera saw round
the vehicle. The detour layer uses it to choose a way round, as the polar histogram of VFH+ (Ulrich &
Borenstein 1998) and PX4-Avoidance's local planner do, and stays above the controller: the
controller's brake is absolute, and a detour only turns the vehicle and slows it
(:func:`detour_setpoint`).

Phases (:class:`Phase`)::

    idle ──braked trigger_after_s, or no progress trigger_no_progress_s──▶ scan
    scan ──turned to the goal ± scan_half_angle_deg (or scan_timeout_s)──▶ choose
    choose ──the goal direction free──▶ handback ──facing it──▶ idle (course hold)
           ──a path parallel to it free a short slide aside──▶ handback (sliding there) ──▶ idle
           ──a free direction toward the goal──▶ fly (turning in place first) ──replan──▶ choose
           ──none──▶ dead end (a hold, reported)
    idle ──facing passing_away_deg or more from the goal, the goal direction free or an opening
           lined up with it on the map──▶ handback (a passing look)
         ──... the goal direction closed, no way through on the side headed along, one on the
           other──▶ fly round the other side (a passing look's turn back)

* **scan**: turn in place (holding the position where it began) to the goal direction minus and plus
  ``scan_half_angle_deg``, the nearer side first, at ``turn_rate_deg_s``: the camera fills the memory.
  None when the way round is already in view (within ``_IN_VIEW_DEG`` of the heading), or seen: on
  the side the memory favours, a sideways step of at most ``no_look_round_step_m`` opens the way (a
  box's end, seen on the approach); then it chooses at once. Facing the goal direction with turns
  still to go, it looks at the map once: the goal direction free, or an opening to line up with,
  hands back at once (the rest of the look would not change that choice).
* **choose**: the polar histogram of the memory's *trusted* points (:meth:`ObstacleMemory.map_points
  <companion.core.memory.ObstacleMemory.map_points>`) round the vehicle, every ``sector_deg`` within
  ``max_angle_deg`` of the goal direction. A direction is *free* when no trusted point lies within
  ``clearance_m`` of the path along it out to ``radius_m`` (VFH+'s enlarged obstacles; a point already
  nearer than that blocks only a path that would close on it). The goal direction free: hand back.
  Not free, but the path parallel to it from a point at most ``line_up_max_m`` to one side free with
  ``line_up_clearance_m`` (a door whose jambs the map smeared inward): **line up**, sliding there
  while facing the goal, and hand back. Else a side (left or right of the goal) is kept for the
  whole detour, chosen as the side where a shorter step square to the goal direction, on the map's
  free space, opens the way to the goal (within ``lookahead_m``: an opening, or the end of the
  wall: the shorter way round), then the free direction on that side nearest the goal, costing
  extra when it passes nearer than ``preferred_clearance_m`` to a point or back over the vehicle's
  own trail (``visited_*``). No free direction on the side: the other side, once; on
  neither: a **dead end**.
* **fly**: face the direction (turning in place beyond ``turn_in_place_deg``), then fly it at
  ``speed_m_s`` (the controller's yaw and slowing still act), choosing again every
  ``replan_interval_s``; a brake for ``trigger_after_s`` along it closes that direction from here.
  Farther than ``max_distance_m`` from where it began, or longer than ``max_time_s``: a dead end.
* **handback**: turn in place to the goal direction (lining up: and slide to the opening's middle,
  for at most ``_LINE_UP_SETTLE_S``), then course hold flies on.
* **passing look** (no detour under way): while the controller has the vehicle facing
  ``passing_away_deg`` or more from the goal direction (steering it along a wall, across a door's
  mouth, round a fence's end), the map is looked at every ``passing_interval_s``; the goal direction
  free, or an opening to line up with it, hands back there as a detour's choice would (turn to it,
  or slide and turn), once per ``passing_spacing_m`` flown. The side rules keep an office's CLEAR
  decisions turning, so course hold never got to turn the vehicle into the door it was passing.
  With the goal direction closed, when the side the vehicle heads along opens no way to the goal
  within ``lookahead_m`` (:attr:`Histogram.through_m`: a fence's pocket, a wall going on) and the
  other side does and has a free direction, it begins a detour round that side there
  (``passing_turn_back``; it counts toward ``max_detours_without_progress``): the side rules had
  flown the vehicle along a fence into the pocket the room's wall closes, 20-35 s lost there.

The layer remembers where it has been (a trail of positions) and which side it went round: a new
detour that starts within ``side_memory_m`` of the last one's end goes round the same side, so the
vehicle does not swing between two detours.

**Where the histogram is computed.** It costs tens of milliseconds with a full memory (20 000 points:
~40 ms on a 2-core VM), too long for the service's control loop. So a choice is split in two: a
*request* (:class:`HistogramRequest`: an immutable snapshot of the trusted points, the trail, the goal,
the vetoes, the config, the position and the time) and its *result* (:class:`HistogramResult`), which
:func:`compute_histogram` makes from the request alone. A planner built with ``defer=False`` (the
simulator, the tests) computes it at once, inside :meth:`DetourPlanner.update`: the same numbers, the
same steps as ever. With ``defer=True`` (the service) it exposes the request
(:attr:`DetourPlanner.pending_request`) and flies on safely meanwhile: at a first choice it holds where
it is, facing as it does; after a look round it keeps turning in place to the look's last heading;
during a replan it keeps flying the direction chosen before (the controller's brake stays absolute).
The caller computes the request elsewhere and hands the result back with :meth:`DetourPlanner.offer`;
a result that does not answer the latest request (the detour ended, was reset, a new goal) is dropped.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from companion.core.frames import finite_position
from companion.core.types import Decision, DecisionKind

if TYPE_CHECKING:
    from companion.config.detour import DetourConfig
    from companion.config.memory import MemoryConfig
    from companion.core.memory import ObstacleMemory

#: An AVOID decision climbing or descending at least this much (and more than it turns) is the
#: controller escaping vertically: the way over or under is free, so no detour (and one under way
#: stops while the vehicle faces the goal, :data:`_ESCAPE_FACING_DEG`). The side rules' slight climb
#: away from the ground (0.05-0.15) is not one.
VERTICAL_ESCAPE = 0.2
#: A vertical escape ends a detour only while the vehicle faces within this of the goal direction
#: (the way over or under is toward the goal): a climb while a look round or a way round faces a side
#: (a cabinet, a fence's top) says nothing of the way to the goal, and ending the detour there sent
#: the vehicle back to the brake that began it (office and forest timeouts), degrees.
_ESCAPE_FACING_DEG = 30.0
#: Within this of the floor (``command.min_altitude_m``) a descending AVOID is no escape under: the
#: floor stops it before it passes under anything (a "down" read through a fence's bars near the
#: floor would end the detour and sink the vehicle to the floor), metres.
FLOOR_MARGIN_M = 0.5
#: A scan target counts as reached within this, radians.
_SCAN_TOLERANCE_RAD = math.radians(6.0)
#: Nearer than the clearance to something, a path may come no nearer to anything than this less
#: than the vehicle is now, metres.
_NEAR_MARGIN_M = 0.05
#: A direction closed by a brake stays closed from within this distance of where it braked, metres.
_VETO_RADIUS_M = 1.0
#: ... for directions within this of the one it braked on, radians.
_VETO_HALF_ANGLE_RAD = math.radians(15.0)
#: Trail points kept (at ``visited_spacing_m``: 150 m).
_TRAIL_POINTS = 500
#: Keep the direction flown unless another costs this much less, degrees (no dithering).
_HYSTERESIS_DEG = 10.0
#: What the reason says while a deferred histogram is awaited.
_MAPPING = ": mapping the way round"
#: Lining up with an opening: the slide has ended within this of its target, metres ...
_LINE_UP_TOLERANCE_M = 0.1
#: ... or after this long, seconds.
_LINE_UP_SETTLE_S = 3.0
#: A direction this near the heading has been seen (the camera's view is about ±45°, its left
#: edge less): a detour toward it needs no look round first, degrees.
_IN_VIEW_DEG = 30.0


def wrap_pi(angle_rad: float) -> float:
    """``angle_rad`` wrapped to [-pi, pi)."""
    return (float(angle_rad) + math.pi) % (2.0 * math.pi) - math.pi


class Phase(str, enum.Enum):
    """What the detour layer is doing (health's ``detour.phase``)."""

    IDLE = "idle"  #: course hold flies (no detour)
    SCAN = "scan"  #: looking round, turning in place
    FLY = "fly"  #: flying the chosen direction (turning in place toward it first)
    HANDBACK = "handback"  #: the goal direction is free: turning to it, then course hold
    DEAD_END = "dead_end"  #: no free direction toward the goal: hold


@dataclass(frozen=True)
class DetourCommand:
    """What the detour layer asks of the setpoint (:func:`detour_setpoint`).

    Attributes:
        phase: the phase.
        target_yaw_rad: the heading to face (scan, handback) or fly (fly), radians; None: keep it.
        anchor_ned_m: float ``(3,)`` NED metres: hold this position while turning in place; None
            while flying.
        reason: one line for health.
    """

    phase: Phase
    target_yaw_rad: float | None
    anchor_ned_m: np.ndarray | None
    reason: str


@dataclass(frozen=True)
class Histogram:
    """The directions round the vehicle, from one look at the memory.

    Attributes:
        bearing_rad: float64 ``(K,)`` candidate headings, radians from north (the goal direction
            at index ``goal_index``).
        offset_rad: float64 ``(K,)`` each one's angle from the goal direction (+ right of it).
        free_m: float64 ``(K,)`` how far the path along each keeps ``clearance_m`` from every trusted
            point, metres (inf: as far as the map reaches).
        roomy_m: float64 ``(K,)`` the same with ``preferred_clearance_m``.
        tight_m: float64 ``(K,)`` the same with ``squeeze_clearance_m``.
        visited: bool ``(K,)`` the path passes back over the vehicle's trail.
        goal_index: where the goal direction is.
        through_m: how far a step sideways (square to the goal direction, on the map's free space)
            to the right and to the left opens the way to the goal, metres (inf: not within
            ``lookahead_m``): the shorter way round.
        line_up_m: where to slide sideways (square to the goal direction, + right) so that the
            path parallel to it is free (:func:`line_up_offset_m`), metres; None: not wanted (the
            goal direction is free from here) or none within ``line_up_max_m``.
        opening_m: for each side (+1 right, -1 left), the middle of the nearest opening the map
            closes at both ends, square to the goal direction, metres (inf: none within
            ``lookahead_m``; :func:`closed_openings_m`).
    """

    bearing_rad: np.ndarray
    offset_rad: np.ndarray
    free_m: np.ndarray
    roomy_m: np.ndarray
    tight_m: np.ndarray
    visited: np.ndarray
    goal_index: int
    through_m: dict[int, float]
    line_up_m: float | None = None
    opening_m: dict[int, float] = dataclasses.field(default_factory=lambda: {1: math.inf, -1: math.inf})


def _rays(dn: np.ndarray, de: np.ndarray, bearing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (north, east offsets from the vehicle, float ``(N,)`` metres) along and across the path
    along each bearing (float ``(K,)`` radians): float ``(K, N)`` metres each (across: + right)."""
    c, s = np.cos(bearing)[:, None], np.sin(bearing)[:, None]
    return c * dn[None, :] + s * de[None, :], -s * dn[None, :] + c * de[None, :]


def free_length_m(along: np.ndarray, across: np.ndarray, clearance_m: float) -> np.ndarray:
    """How far each path (rows of ``along``/``across``, float ``(K, N)`` metres, :func:`_rays`) goes
    before it comes within ``clearance_m`` of a point: float ``(K,)`` metres, inf for none."""
    inside = (along > 0.0) & (np.abs(across) < clearance_m)
    hit = along - np.sqrt(np.maximum(clearance_m * clearance_m - across * across, 0.0))
    hit = np.where(inside, np.maximum(hit, 0.0), np.inf)
    return hit.min(axis=1) if hit.shape[1] else np.full(hit.shape[0], np.inf)


def free_lengths_m(
    dn: np.ndarray,
    de: np.ndarray,
    bearing: np.ndarray,
    base_rad: float,
    step_rad: float,
    first_index: int,
    clearances_m: tuple[float, ...],
) -> list[np.ndarray]:
    """:func:`free_length_m` of the paths along each bearing (float ``(K,)`` radians, evenly spaced:
    ``bearing[i]`` is ``base_rad + (first_index + i) · step_rad``, up to whole turns) past points
    (north, east offsets from the vehicle, float ``(N,)`` metres), for each clearance (metres): the
    same numbers, bit for bit, without ``(K, N)`` arrays.

    A point at distance ``r`` comes within ``c`` of a path only when the path's bearing lies within
    ``asin(c / r)`` of the point's (any path ahead of it when ``r <= c``), so only those (path, point)
    pairs are formed (for the largest clearance, one bearing wider either side) and each is judged by
    :func:`free_length_m`'s arithmetic. A wall of thousands of points costs a few pairs per point
    instead of one per direction.
    """
    k = bearing.size
    outs = [np.full(k, np.inf) for _ in clearances_m]
    if dn.size == 0 or k == 0:
        return outs
    c_max = max(clearances_m)
    r = np.hypot(dn, de)
    half = np.full(r.shape, 0.5 * math.pi)
    far = r > c_max
    half[far] = np.arcsin(c_max / r[far])
    rel = (np.arctan2(de, dn) - base_rad + math.pi) % (2.0 * math.pi) - math.pi
    points, rays = [], []
    for turn in (-2.0 * math.pi, 0.0, 2.0 * math.pi):  # the bearings are compared on the circle
        lo = np.maximum(np.ceil((rel + turn - half) / step_rad).astype(np.int64) - 1 - first_index, 0)
        hi = np.minimum(np.floor((rel + turn + half) / step_rad).astype(np.int64) + 1 - first_index, k - 1)
        count = np.maximum(hi - lo + 1, 0)
        total = int(count.sum())
        if total == 0:
            continue
        point = np.repeat(np.arange(r.size), count)
        start = np.cumsum(count) - count
        points.append(point)
        rays.append(lo[point] + np.arange(total) - start[point])
    if not points:
        return outs
    point, ray = np.concatenate(points), np.concatenate(rays)
    cb, sb = np.cos(bearing)[ray], np.sin(bearing)[ray]
    along = cb * dn[point] + sb * de[point]
    across = -sb * dn[point] + cb * de[point]
    for out, c in zip(outs, clearances_m):
        inside = (along > 0.0) & (np.abs(across) < c)
        a, x = along[inside], across[inside]
        np.minimum.at(out, ray[inside], np.maximum(a - np.sqrt(np.maximum(c * c - x * x, 0.0)), 0.0))
    return outs


def polar_histogram(
    points_ne_m: np.ndarray,
    goal_bearing_rad: float,
    cfg: DetourConfig,
    map_depth_m: float,
    trail_ne_m: np.ndarray | None = None,
    goal_distance_m: float | None = None,
    start_goal_rad: float | None = None,
) -> Histogram:
    """The candidate directions round the vehicle (:class:`Histogram`) from trusted map points
    (float ``(N, 2)`` north, east offsets from the vehicle, metres), the direction to the goal (and
    the distance to a goal point, None for the course) and, for ``visited``, the trail (float
    ``(M, 2)`` offsets of where the vehicle has been, old enough to count).

    The directions are every ``sector_deg`` within ``max_angle_deg`` of the goal direction and, with
    ``start_goal_rad`` (radians from north: the goal direction when the detour began), within
    ``max_angle_deg`` of that too, never more than half a turn either side of the goal direction."""
    step = math.radians(cfg.sector_deg)
    n = int(math.floor(cfg.max_angle_deg / cfg.sector_deg + 1e-9))
    lo, hi = -n, n
    if start_goal_rad is not None and math.isfinite(start_goal_rad):
        shift = int(round(wrap_pi(start_goal_rad - goal_bearing_rad) / step))
        lo = max(min(lo, shift - n), -int(math.floor(180.0 / cfg.sector_deg + 1e-9)))
        hi = min(max(hi, shift + n), int(math.ceil(180.0 / cfg.sector_deg - 1e-9)) - 1)
    goal_index = -lo
    offsets = np.arange(lo, hi + 1, dtype=np.float64) * step
    bearing = np.array([wrap_pi(goal_bearing_rad + o) for o in offsets])
    k = offsets.size
    pts = np.asarray(points_ne_m, dtype=np.float64).reshape(-1, 2)
    free = np.full(k, np.inf)
    roomy = np.full(k, np.inf)
    tight = np.full(k, np.inf)
    through = {1: math.inf, -1: math.inf}
    opening = {1: math.inf, -1: math.inf}
    line_up = None
    if len(pts):
        dn, de = pts[:, 0], pts[:, 1]
        # A vehicle already nearer than the clearance to something may still fly a path that comes
        # no nearer to anything than it is now (less 5 cm): away from it, or along it.
        nearest = float(np.min(np.hypot(dn, de))) - _NEAR_MARGIN_M
        free, roomy, tight = free_lengths_m(
            dn,
            de,
            bearing,
            goal_bearing_rad,
            step,
            lo,
            tuple(max(0.0, min(c, nearest)) for c in (cfg.clearance_m, cfg.preferred_clearance_m, cfg.squeeze_clearance_m)),
        )
        through = _through(pts, goal_bearing_rad, goal_distance_m, cfg, max(0.0, min(cfg.clearance_m, nearest)), map_depth_m)
        need = cfg.radius_m if goal_distance_m is None else min(cfg.radius_m, goal_distance_m)
        if free[goal_index] < need and tight[goal_index] < need:
            line_up = line_up_offset_m(pts, goal_bearing_rad, need, cfg, nearest)
        opening = closed_openings_m(pts, goal_bearing_rad, need, cfg, max(0.0, min(cfg.clearance_m, nearest)), map_depth_m)
    visited = np.zeros(k, dtype=bool)
    if trail_ne_m is not None and len(trail_ne_m):
        tr = np.asarray(trail_ne_m, dtype=np.float64).reshape(-1, 2)
        along, across = _rays(tr[:, 0], tr[:, 1], bearing)
        reach = cfg.min_free_m + cfg.visited_clearance_m
        visited = np.any((along > 0.3) & (along < reach) & (np.abs(across) < cfg.visited_clearance_m), axis=1)
    return Histogram(bearing, offsets, free, roomy, tight, visited, goal_index, through, line_up, opening)


#: Lining up (:func:`line_up_offset_m`) tries sideways offsets this far apart, metres.
_LINE_UP_STEP_M = 0.05


def line_up_offset_m(
    points_ne_m: np.ndarray, goal_bearing_rad: float, need_m: float, cfg: DetourConfig, nearest_m: float = math.inf
) -> float | None:
    """Where to slide, square to the goal direction, to pass an opening the goal direction itself
    misses, metres (+ right of the goal direction); None: none, or lining up is off
    (``cfg.line_up_max_m`` 0).

    Sideways offsets every ``_LINE_UP_STEP_M`` within twice ``cfg.line_up_max_m`` are tried: from
    each, is the path parallel to the goal direction clear of every point (float ``(N, 2)`` north,
    east offsets from the vehicle, metres) by ``cfg.line_up_clearance_m`` for ``need_m``? A run of
    such offsets closed at both ends within the range is an opening (a door, a gap between two
    things), and its middle, if at most ``line_up_max_m`` off and reached by a slide that keeps the
    clearance (less 5 cm than ``nearest_m``, the nearest point now, where the vehicle is nearer
    than that already), is a place to slide to; the nearest such middle is the answer.

    An opening, not the free side of one thing: a line-up past a cabinet's edge handed an office
    flight back to course hold, which flew it along the far wall into a door jamb (kinematic,
    drift). The middle, not the nearest end: the run's ends are where the path grazes the jambs'
    smeared points, and the middle keeps the most room for the drift on the way through."""
    reach = cfg.line_up_max_m
    if reach <= 0.0:
        return None
    pts = np.asarray(points_ne_m, dtype=np.float64).reshape(-1, 2)
    c = cfg.line_up_clearance_m
    span = 2.0 * reach
    # Points farther than the path and the slide can reach cannot stop either (see _through).
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) <= need_m + span + 2.0 * c]
    count = int(math.floor(span / _LINE_UP_STEP_M + 1e-9))
    offsets = np.arange(-count, count + 1, dtype=np.float64) * _LINE_UP_STEP_M
    cg, sg = math.cos(goal_bearing_rad), math.sin(goal_bearing_rad)
    along = cg * pts[:, 0] + sg * pts[:, 1]
    across = -sg * pts[:, 0] + cg * pts[:, 1]
    # Each offset's parallel path at once: the same along, the across shifted by the offset; only
    # points ahead and within reach of some offset's path count.
    near = (along > 0.0) & (np.abs(across) < span + c)
    a, x = along[near], across[near]
    d = x[None, :] - offsets[:, None]
    ok = free_length_m(np.broadcast_to(a, d.shape), d, c) >= need_m
    if not ok.any():
        return None
    # How far the slide can go each way before it comes within the clearance of a point.
    slide_c = max(0.0, min(c, nearest_m - _NEAR_MARGIN_M))
    room = {}
    for side in (1, -1):
        along, across = _rays(pts[:, 0], pts[:, 1], np.array([goal_bearing_rad + side * 0.5 * math.pi]))
        room[side] = float(free_length_m(along, across, slide_c)[0])
    best: float | None = None
    i = 0
    while i < offsets.size:
        if not ok[i]:
            i += 1
            continue
        j = i
        while j + 1 < offsets.size and ok[j + 1]:
            j += 1
        middle = float(0.5 * (offsets[i] + offsets[j]))
        closed = i > 0 and j < offsets.size - 1
        if closed and abs(middle) <= reach + 1e-9 and abs(middle) <= room[1 if middle >= 0.0 else -1] + 1e-9:
            if best is None or abs(middle) < abs(best):
                best = middle
        i = j + 1
    return best


#: The side-step look-ahead (:func:`_through`) tries positions this far apart, metres.
_THROUGH_STEP_M = 0.5


def _through(
    pts: np.ndarray,
    goal_bearing_rad: float,
    goal_distance_m: float | None,
    cfg: DetourConfig,
    clearance_m: float,
    map_depth_m: float,
) -> dict[int, float]:
    """For each side (+1 right of the goal direction, -1 left): the shortest step square to the goal
    direction, along free space (``clearance_m``), after which the way to the goal keeps
    ``cfg.clearance_m`` (``cfg.squeeze_clearance_m`` with ``cfg.through_squeeze``) from every point
    for ``radius_m`` (or to the goal point); inf when none within
    ``lookahead_m`` (at most 0.8 of the map's depth: beyond it the map has not seen a wall go on)."""
    out = {1: math.inf, -1: math.inf}
    reach = min(cfg.lookahead_m, 0.8 * map_depth_m)
    way_m = cfg.squeeze_clearance_m if cfg.through_squeeze is True else cfg.clearance_m  # "auto" is resolved at load
    gn = gd = None
    if goal_distance_m is not None:
        gn, gd = goal_distance_m * math.cos(goal_bearing_rad), goal_distance_m * math.sin(goal_bearing_rad)
    for side in (1, -1):
        d = goal_bearing_rad + side * 0.5 * math.pi
        along, across = _rays(pts[:, 0], pts[:, 1], np.array([d]))
        room = float(free_length_m(along, across, clearance_m)[0])
        for k in np.arange(_THROUGH_STEP_M, reach + 1e-9, _THROUGH_STEP_M):
            if k > room:
                break
            sn, se = k * math.cos(d), k * math.sin(d)
            q = pts - np.array([sn, se])
            if gn is None:
                b, need = goal_bearing_rad, cfg.radius_m
            else:
                b = math.atan2(gd - se, gn - sn)
                need = min(cfg.radius_m, math.hypot(gn - sn, gd - se))
            # A point farther than need + 2 clearances cannot stop a path short of need (its nearest
            # hit lies beyond r - 2c): leaving it out changes no answer and most of a long wall.
            q = q[q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] <= (need + 2.0 * cfg.clearance_m) ** 2]
            # From there, any way between the goal and the goal direction from where the vehicle is
            # (an opening seen at a slant is flown square through), a sector either side: turning
            # farther out would look where the map has not been.
            lo, hi = sorted((0.0, wrap_pi(goal_bearing_rad - b)))
            fan = b + np.arange(lo - math.radians(cfg.sector_deg), hi + math.radians(cfg.sector_deg) + 1e-9, math.radians(cfg.sector_deg))
            al, ac = _rays(q[:, 0], q[:, 1], fan)
            if float(np.max(free_length_m(al, ac, way_m))) >= need:
                out[side] = float(k)
                break
    return out


#: The search for closed openings (:func:`closed_openings_m`) tries offsets this far apart, metres.
_OPENING_STEP_M = 0.05


def closed_openings_m(
    pts: np.ndarray,
    goal_bearing_rad: float,
    need_m: float,
    cfg: DetourConfig,
    slide_clearance_m: float,
    map_depth_m: float,
) -> dict[int, float]:
    """For each side (+1 right of the goal direction, -1 left): the middle of the nearest opening
    the map closes at both ends, as a sideways offset from the vehicle square to the goal
    direction, metres (inf: none).

    Offsets every :data:`_OPENING_STEP_M` out to ``lookahead_m`` (at most 0.8 of the map's depth,
    as :func:`_through`) are tried: from each, is the path parallel to the goal direction clear of
    every point (float ``(N, 2)`` north, east offsets from the vehicle, metres) by
    ``cfg.squeeze_clearance_m`` for ``need_m``? A run of such offsets with a blocked offset on
    both sides is an opening; its middle counts when the slide there, square to the goal direction,
    keeps ``slide_clearance_m`` from every point.

    Why: :func:`_through`'s 0.5 m steps with ``clearance_m`` miss an opening StereoBM's smeared
    jambs narrow to 1.0-1.25 m (kinematic detour kind, a 1.57 m opening 3 m to the right), while
    the other side "opens" where the look round stopped measuring the wall, which is not free but
    unseen. Closed at both ends, an opening is one the camera saw both sides of."""
    out = {1: math.inf, -1: math.inf}
    reach = min(cfg.lookahead_m, 0.8 * map_depth_m)
    c = cfg.squeeze_clearance_m
    count = int(math.floor(reach / _OPENING_STEP_M + 1e-9))
    if count < 3 or len(pts) == 0:
        return out
    cg, sg = math.cos(goal_bearing_rad), math.sin(goal_bearing_rad)
    along = cg * pts[:, 0] + sg * pts[:, 1]
    across = -sg * pts[:, 0] + cg * pts[:, 1]
    # Only points ahead, within reach of some offset's path, can block one.
    near = (along > 0.0) & (along < need_m + c) & (np.abs(across) < reach + c)
    a, x = along[near], across[near]
    # A point (along a, across x) stops the path at offset o short of need_m exactly when
    # |x - o| < w: w = c where a < need_m (free_length_m's hit is at most a), else
    # sqrt(c² - (a - need_m)²) (the hit a - sqrt(c² - (x - o)²) < need_m). So each point blocks one
    # interval of offsets, marked in O(points + offsets) instead of judging every (offset, point).
    w = np.where(a < need_m, c, np.sqrt(np.maximum(c * c - (a - need_m) ** 2, 0.0)))
    for side in (1, -1):
        offsets = side * np.arange(1, count + 1, dtype=np.float64) * _OPENING_STEP_M
        xs = side * x  # the side's offsets are k·step, k = 1..count
        lo = np.maximum(np.floor((xs - w) / _OPENING_STEP_M).astype(np.int64) + 1, 1)
        hi = np.minimum(np.ceil((xs + w) / _OPENING_STEP_M).astype(np.int64) - 1, count)
        keep = (hi >= lo) & (w > 0.0)
        edges = np.zeros(count + 2, dtype=np.int64)
        np.add.at(edges, lo[keep], 1)
        np.add.at(edges, hi[keep] + 1, -1)
        ok = np.cumsum(edges)[1 : count + 1] == 0
        side_along, side_across = _rays(pts[:, 0], pts[:, 1], np.array([goal_bearing_rad + side * 0.5 * math.pi]))
        room = float(free_length_m(side_along, side_across, slide_clearance_m)[0])
        blocked = np.flatnonzero(~ok)
        # A run of free offsets between two blocked ones: the first blocked offset past each
        # blocked one that is followed by a free one.
        for i in blocked:
            if i + 1 < ok.size and ok[i + 1]:
                later = blocked[blocked > i]
                if later.size == 0:
                    break  # open to the end of the reach: not closed
                middle = 0.5 * float(abs(offsets[i + 1]) + abs(offsets[later[0] - 1]))
                if middle <= room + 1e-9:
                    out[side] = middle
                break  # the nearest opening only: the slide to a farther one passes this one
    return out


@dataclass(frozen=True)
class HistogramRequest:
    """What one choice of the detour layer needs a histogram of: a snapshot that nothing changes, so
    that another thread may compute it (:func:`compute_histogram`) while the planner flies on.

    Attributes:
        seq: which request this is; a planner takes only the result of its latest
            (:meth:`DetourPlanner.offer`).
        asked_s: when it was asked, seconds (the planner's clock).
        position_ned_m: float64 ``(3,)`` NED metres: the vehicle then; the points, the trail and the
            vetoes' reach are from here.
        points_ne_m: float64 ``(N, 2)`` the memory's trusted points, north and east offsets from the
            vehicle, metres (read-only).
        trail_ne_m: float64 ``(M, 2)`` offsets of where the vehicle has been (old enough to count),
            metres (read-only), or None.
        goal_bearing_rad: the direction to the goal from here, radians from north.
        goal_distance_m: how far the goal point is, metres (None: the course, no point).
        vetoes: ``(north m, east m, bearing rad)`` of each direction a brake closed, from where.
        map_depth_m: ``memory.map_depth_m``, metres.
        cfg: the ``[detour]`` config (frozen).
        start_goal_rad: the goal direction when the detour began, radians from north, with
            ``detour.cone_from_start`` within ``cone_from_start_max_m`` of where it began (directions
            within ``max_angle_deg`` of it count too), else None.
    """

    seq: int
    asked_s: float
    position_ned_m: np.ndarray
    points_ne_m: np.ndarray
    trail_ne_m: np.ndarray | None
    goal_bearing_rad: float
    goal_distance_m: float | None
    vetoes: tuple[tuple[float, float, float], ...]
    map_depth_m: float
    cfg: DetourConfig
    start_goal_rad: float | None = None


@dataclass(frozen=True)
class HistogramResult:
    """The answer to a :class:`HistogramRequest` (:meth:`DetourPlanner.offer`).

    Attributes:
        seq: the request's ``seq``.
        histogram: :func:`compute_histogram` of it, or None when computing it failed.
        error: why it failed (one line), or None.
    """

    seq: int
    histogram: Histogram | None
    error: str | None = None


def compute_histogram(request: HistogramRequest) -> Histogram:
    """The histogram a request asks for (pure; any thread): :func:`polar_histogram` of its points,
    with the directions its vetoes close set to zero length."""
    r = request
    h = polar_histogram(
        r.points_ne_m, r.goal_bearing_rad, r.cfg, r.map_depth_m, r.trail_ne_m, r.goal_distance_m, r.start_goal_rad
    )
    return _close_vetoed(h, r.position_ned_m, r.vetoes)


def _close_vetoed(h: Histogram, pos: np.ndarray, vetoes) -> Histogram:
    """``h`` with the directions closed by a brake (``(north, east, bearing)``) near ``pos``
    (float ``(3,)`` NED metres) free for 0 m."""
    if not vetoes:
        return h
    free, roomy, tight = h.free_m.copy(), h.roomy_m.copy(), h.tight_m.copy()
    line_up = h.line_up_m
    for n, e, b in vetoes:
        if math.hypot(pos[0] - n, pos[1] - e) <= _VETO_RADIUS_M:
            closed = np.abs(np.array([wrap_pi(x - b) for x in h.bearing_rad])) <= _VETO_HALF_ANGLE_RAD
            free[closed] = roomy[closed] = tight[closed] = 0.0
            if closed[h.goal_index]:
                line_up = None  # a brake on the goal direction here: no lining up to fly it again
    return dataclasses.replace(h, free_m=free, roomy_m=roomy, tight_m=tight, line_up_m=line_up)


def _frozen(a: np.ndarray | None) -> np.ndarray | None:
    if a is not None:
        a.setflags(write=False)  # shared with another thread: nobody may change it
    return a


class DetourPlanner:
    """The detour layer's state for one flight (see the module doc). Built idle; :meth:`reset` on
    engage, a new goal, or resume.

    Args:
        defer: False: compute each histogram at once, inside :meth:`update` (the simulator, tests);
            True: expose it as :attr:`pending_request` and wait for :meth:`offer` (the service, which
            computes it off its control loop).
    """

    def __init__(self, defer: bool = False) -> None:
        self.defer = defer
        self._next_seq = 0  # kept across resets: a result for a request made before one never matches
        self.trail: deque[tuple[float, float, float]] = deque(maxlen=_TRAIL_POINTS)  # (north, east, time s)
        self._last_end: tuple[float, float, int] | None = None  # where the last detour ended, its side
        self._count_mark: float | None = None  # the progress mark the detours are counted at
        self._count = 0  # detours begun since the vehicle last made progress
        self._passing_asked_s = -math.inf  # when the map was last looked at in passing
        self._passing_from: tuple[float, float] | None = None  # where the last passing look handed back
        self.reset()

    def reset(self) -> None:
        """Back to idle, forgetting the current detour (the trail and the last side are kept)."""
        self.phase = Phase.IDLE
        self.reason = "no detour"
        self._blocked_since_s: float | None = None
        self._progress_mark_s: float | None = None  # the stall already answered by a detour
        self._since_s = 0.0
        self._start_ned_m: np.ndarray | None = None
        self._start_goal_rad: float | None = None  # the goal direction when the detour began
        self._anchor_ned_m: np.ndarray | None = None
        self._targets: list[float] = []
        self._target_rad: float | None = None
        self._side = 0  # +1 right of the goal, -1 left, 0 not chosen
        self._switched = False
        self._last_plan_s = -math.inf
        self._brake_since_s: float | None = None
        self._vetoes: list[tuple[float, float, float]] = []  # (north, east, bearing) closed by a brake
        self._scans = 0
        self._scan_goal_rad: float | None = None  # the goal direction the look round's turns are laid from
        self._goal_distance_m: float | None = None
        self._stall_mark: float | None = None
        self._course_down_m: float | None = None
        self._line_up_since_s: float | None = None  # when a slide to line up with an opening began
        self._drop_request()

    def _drop_request(self) -> None:
        """Forget the histogram asked for (deferred): a result for it is dropped when offered."""
        self._request: HistogramRequest | None = None
        self._awaiting: str | None = None  # what it is for: "begin", "peek", "choose" or "passing"
        self._answer: HistogramResult | None = None

    @property
    def pending_request(self) -> HistogramRequest | None:
        """The histogram the planner waits for (``defer``), not yet answered: compute it
        (:func:`compute_histogram`) and :meth:`offer` the result. None: none wanted."""
        return self._request if self._answer is None else None

    def offer(self, result: HistogramResult) -> bool:
        """The result of a :class:`HistogramRequest`, used at the next :meth:`update`. Only the answer
        to the latest request is taken (True); any other (the detour ended or was reset, a new goal,
        an answer already given) is dropped (False)."""
        if self._request is None or self._answer is not None or result.seq != self._request.seq:
            return False
        self._answer = result
        return True

    @property
    def active(self) -> bool:
        """A detour is under way (scanning, flying or handing back)."""
        return self.phase in (Phase.SCAN, Phase.FLY, Phase.HANDBACK)

    def status(self) -> dict[str, object]:
        """For health: ``phase``, ``reason``, ``heading_deg`` (the direction faced or flown, or None),
        ``side`` (``left``, ``right`` or None)."""
        return {
            "phase": self.phase.value,
            "reason": self.reason,
            "heading_deg": None if self._target_rad is None or not self.active else math.degrees(self._target_rad),
            "side": {1: "right", -1: "left"}.get(self._side),
        }

    # ------------------------------------------------------------------------------------ update

    def update(
        self,
        now_s: float,
        decision: Decision | None,
        position_ned_m: np.ndarray | None,
        yaw_rad: float | None,
        goal_bearing_rad: float | None,
        stalled_for_s: float | None,
        memory: ObstacleMemory | None,
        memory_cfg: MemoryConfig,
        cfg: DetourConfig,
        prefer_right: bool = True,
        goal_distance_m: float | None = None,
        stall_mark_m: float | None = None,
        course_down_m: float | None = None,
        regressing: bool = False,
        floor_down_m: float | None = None,
    ) -> DetourCommand | None:
        """Advance to ``now_s`` (seconds) with the decision in force (fresh), the vehicle's position
        (float ``(3,)`` NED metres) and heading (radians), the direction to the goal from here
        (radians from north), how long the vehicle has got no nearer its goal (seconds, None =
        unknown), and the memory. Returns what the setpoint must do, or None: no detour (course hold).
        ``prefer_right``: the side a tie goes to (``controller.preferred_yaw_side``);
        ``goal_distance_m``: how far the goal point is (None: the course, no point);
        ``stall_mark_m``: the progress the vehicle has stalled at (the watchdog's mark: a stall is
        answered by one detour); ``course_down_m``: NED down of the altitude course hold keeps, metres
        (the map holds only points in the height band of it and of the vehicle's,
        :meth:`~companion.core.memory.ObstacleMemory.map_points`; None: the vehicle's alone);
        ``regressing``: the vehicle is flying back from its goal
        (:attr:`~companion.core.command.ProgressWatch.regressing`); ``floor_down_m``: NED down of
        ``command.min_altitude_m``, metres (None: no floor), where a descent is no escape."""
        self._goal_distance_m = goal_distance_m
        self._course_down_m = course_down_m
        self._stall_mark = stall_mark_m
        if not cfg.on or memory is None or memory_cfg.duration_s <= 0.0:
            self.phase = Phase.IDLE
            self._drop_request()
            return None
        pos = finite_position(position_ned_m)
        if pos is None or yaw_rad is None or not math.isfinite(yaw_rad) or goal_bearing_rad is None:
            self._blocked_since_s = None
            if self.phase is Phase.DEAD_END:
                return DetourCommand(Phase.DEAD_END, None, self._anchor_ned_m, self.reason)
            if self.active:
                self.reset()
                self.reason = "detour abandoned: position or heading unknown"
            return None
        self._remember_trail(pos, now_s, cfg)
        at_floor = floor_down_m is not None and pos[2] >= floor_down_m - FLOOR_MARGIN_M
        if self.phase is Phase.DEAD_END:
            return DetourCommand(Phase.DEAD_END, None, self._anchor_ned_m, self.reason)
        if self._stall_mark is None or self._count_mark is None or abs(self._stall_mark - self._count_mark) > 1e-6:
            self._count_mark, self._count = self._stall_mark, 0  # progress since: count afresh
        if self.phase is Phase.IDLE:
            if not self._triggered(now_s, decision, yaw_rad, goal_bearing_rad, stalled_for_s, cfg, regressing, at_floor):
                return self._passing(now_s, decision, pos, yaw_rad, goal_bearing_rad, memory, memory_cfg, cfg, prefer_right)
            if self._count >= cfg.max_detours_without_progress:
                self.reason = (
                    f"{self.reason}, but {self._count} detours have brought no progress "
                    "(detour.max_detours_without_progress): the progress watchdog decides"
                )
                return None
            self._count += 1
            return self._begin(now_s, pos, yaw_rad, goal_bearing_rad, memory, memory_cfg, cfg, prefer_right)
        facing_goal = abs(wrap_pi(yaw_rad - goal_bearing_rad)) <= math.radians(_ESCAPE_FACING_DEG)
        if _vertical_escape(decision, at_floor) and facing_goal:
            self._end(pos, "the controller escapes over or under: no detour")
            return None
        elif now_s - self._since_s > cfg.max_time_s and self.phase is not Phase.HANDBACK:
            return self._dead_end(pos, f"no way round within {cfg.max_time_s:g} s (detour.max_time_s)")
        elif self._distance_from_start_m(pos) > cfg.max_distance_m and self.phase is not Phase.HANDBACK:
            return self._dead_end(pos, f"no way round within {cfg.max_distance_m:g} m (detour.max_distance_m)")
        if self._awaiting is not None:
            return self._await(now_s, decision, pos, yaw_rad, goal_bearing_rad, cfg, prefer_right)
        if self.phase is Phase.SCAN:
            return self._scan(now_s, pos, yaw_rad, goal_bearing_rad, memory, memory_cfg, cfg, prefer_right)
        if self.phase is Phase.HANDBACK:
            return self._handback(now_s, pos, yaw_rad, goal_bearing_rad, cfg)
        return self._fly(now_s, decision, pos, yaw_rad, goal_bearing_rad, memory, memory_cfg, cfg, prefer_right)

    # ------------------------------------------------------------------------------------ phases

    def _triggered(
        self,
        now_s: float,
        decision: Decision | None,
        yaw: float,
        goal: float,
        stalled_for_s: float | None,
        cfg: DetourConfig,
        regressing: bool = False,
        at_floor: bool = False,
    ) -> bool:
        braking = decision is not None and decision.kind is DecisionKind.BRAKE
        if not braking or _vertical_escape(decision, at_floor):
            self._blocked_since_s = None
        elif self._blocked_since_s is None:
            self._blocked_since_s = now_s
        if self._blocked_since_s is not None and now_s - self._blocked_since_s >= cfg.trigger_after_s:
            self.reason = f"braked for {cfg.trigger_after_s:g} s"
            return True
        away = abs(wrap_pi(yaw - goal))
        steering = decision is not None and decision.kind is not DecisionKind.CLEAR
        if cfg.trigger_away_deg > 0.0 and steering and away >= math.radians(cfg.trigger_away_deg):
            self.reason = f"steered {math.degrees(away):.0f} deg away from the goal"
            return True
        if stalled_for_s is None:
            self._progress_mark_s = None
            return False
        mark = self._stall_mark  # the progress the vehicle stalled at: one detour per stall
        fresh = self._progress_mark_s is None or mark is None or abs(mark - self._progress_mark_s) > 1e-6
        if cfg.trigger_on_regress and regressing and fresh:
            self._progress_mark_s = mark
            self.reason = "flying back from the goal"
            return True
        if cfg.trigger_no_progress_s > 0.0 and stalled_for_s >= cfg.trigger_no_progress_s and fresh:
            self._progress_mark_s = mark
            self.reason = f"no progress for {cfg.trigger_no_progress_s:g} s"
            return True
        return False

    def _begin(
        self,
        now_s: float,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        memory: ObstacleMemory,
        memory_cfg: MemoryConfig,
        cfg: DetourConfig,
        prefer_right: bool,
    ) -> DetourCommand | None:
        """Start a detour: choose at once when the way round is in view, else look round first."""
        self._start_detour(now_s, pos, goal)
        if self._last_end is not None and cfg.side_memory_m > 0.0:
            n, e, side = self._last_end
            if math.hypot(pos[0] - n, pos[1] - e) <= cfg.side_memory_m:
                self._side = side  # round the same side as the last detour nearby
        h = self._histogram(now_s, pos, goal, memory, memory_cfg, cfg, "begin")
        if h is None:
            # Deferred: hold here, facing as now, until the histogram comes (never fly a direction
            # not chosen).
            self.phase = Phase.SCAN
            self._anchor_ned_m = pos.copy()
            self._target_rad = None
            self.reason = f"{self.reason}{_MAPPING}"
            return DetourCommand(Phase.SCAN, None, self._anchor_ned_m, self.reason)
        return self._begin_with(h, now_s, pos, yaw, goal, cfg, prefer_right)

    def _start_detour(self, now_s: float, pos: np.ndarray, goal: float) -> None:
        """A detour's bookkeeping from its start at ``now_s`` (seconds), ``pos`` (NED metres), with
        the goal direction ``goal`` (radians): no side, switch, vetoes or look round yet."""
        self._since_s = now_s
        self._start_ned_m = pos.copy()
        self._start_goal_rad = goal
        self._switched = False
        self._vetoes = []
        self._scans = 0
        self._side = 0

    def _begin_with(
        self,
        h: Histogram,
        now_s: float,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        cfg: DetourConfig,
        prefer_right: bool,
        seen_from: np.ndarray | None = None,
    ) -> DetourCommand | None:
        """A detour's start, with the histogram from where it began (``seen_from``, NED metres; None:
        ``pos``): choose at once, or look round."""
        # Before a look round the map holds what the approach saw: the lean orders the look only,
        # and a closed opening (a gap between a box and a wall) leaning it the other way would
        # lengthen the look.
        lean = self._side or _pick_side(h, prefer_right, cfg, openings=False)
        k = _best(h, lean, cfg, None)
        in_view = k is not None and abs(wrap_pi(h.bearing_rad[k] - yaw)) <= math.radians(_IN_VIEW_DEG)
        # A step on the favoured side already opens the way (the map saw where the obstacle ends).
        seen = k is not None and h.through_m[lean] <= cfg.no_look_round_step_m
        if in_view or seen or h.line_up_m is not None:
            # The way round is in view, or seen: no need to look round. (The same snapshot: a
            # second histogram now would be the same numbers.)
            self.phase = Phase.SCAN
            return self._choose_with(h, now_s, pos, yaw, goal, cfg, prefer_right, seen_from)
        self._start_scan(now_s, pos, yaw, goal, cfg, lean)
        return DetourCommand(Phase.SCAN, self._target_rad, self._anchor_ned_m, self.reason)

    def _passing(
        self,
        now_s: float,
        decision: Decision | None,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        memory: ObstacleMemory,
        memory_cfg: MemoryConfig,
        cfg: DetourConfig,
        prefer_right: bool,
    ) -> DetourCommand | None:
        """No detour under way: the passing look (module doc). None: course hold flies on (also while
        a deferred histogram is awaited)."""
        if self._awaiting == "passing":
            if self._answer is None:
                return None
            request, result = self._request, self._answer
            self._drop_request()
            assert request is not None
            if result.histogram is None:
                # Nothing to see by: the vehicle flies on as without the look; health says why.
                self.reason = f"passing look: the histogram could not be computed ({result.error or 'no reason given'})"
                return None
            return self._passing_with(result.histogram, request.asked_s, pos, yaw, goal, cfg, prefer_right, request.position_ned_m)
        if not self._passing_due(now_s, decision, pos, yaw, goal, cfg):
            return None
        self._passing_asked_s = now_s
        h = self._histogram(now_s, pos, goal, memory, memory_cfg, cfg, "passing")
        if h is None:
            return None
        return self._passing_with(h, now_s, pos, yaw, goal, cfg, prefer_right)

    def _passing_due(
        self, now_s: float, decision: Decision | None, pos: np.ndarray, yaw: float, goal: float, cfg: DetourConfig
    ) -> bool:
        """Whether to look at the map in passing now: on, a fresh decision that is no brake, facing
        ``passing_away_deg`` or more from the goal, ``passing_interval_s`` since the last look, and
        ``passing_spacing_m`` from where the last one handed back."""
        if cfg.passing_away_deg <= 0.0 or decision is None or decision.kind is DecisionKind.BRAKE:
            return False
        if abs(wrap_pi(yaw - goal)) < math.radians(cfg.passing_away_deg):
            return False
        if now_s - self._passing_asked_s < cfg.passing_interval_s:
            return False
        last = self._passing_from
        return last is None or math.hypot(pos[0] - last[0], pos[1] - last[1]) >= cfg.passing_spacing_m

    def _passing_with(
        self,
        h: Histogram,
        asked_s: float,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        cfg: DetourConfig,
        prefer_right: bool,
        seen_from: np.ndarray | None = None,
    ) -> DetourCommand | None:
        """The passing look's answer, from the histogram asked for at ``asked_s`` from ``seen_from``:
        the goal direction free or an opening lined up with it: hand back there (:meth:`_choose_with`),
        as a detour begun here; closed, with the way through on the other side only
        (:meth:`_way_back_side`): a detour round that side; else None (course hold flies on)."""
        back_side = 0
        if not self._can_hand_back(h, cfg):
            back_side = self._way_back_side(h, yaw, goal, cfg)
            if back_side == 0:
                return None
        where = pos if seen_from is None else seen_from
        self._passing_from = (float(where[0]), float(where[1]))
        self._start_detour(asked_s, pos, goal)
        self._anchor_ned_m = None  # idle after detour.trigger_after_s was set to 0 keeps an old one
        self.phase = Phase.SCAN  # choosing, as after a look round
        if back_side != 0:
            self._count += 1
            self._side = back_side
        command = self._choose_with(h, asked_s, pos, yaw, goal, cfg, prefer_right, seen_from)
        closed = f"no way through on the {'left' if back_side > 0 else 'right'}: " if back_side else ""
        self.reason = f"in passing, {closed}{self.reason}"
        return None if command is None else dataclasses.replace(command, reason=self.reason)

    def _way_back_side(self, h: Histogram, yaw: float, goal: float, cfg: DetourConfig) -> int:
        """The passing look with the goal direction closed: the side (+1 right of the goal, -1 left)
        to turn back to, when the vehicle heads along a side whose step square to the goal opens no
        way within ``lookahead_m`` (a fence's pocket, a wall going on) while the other side's does
        and has a free direction; else 0 (course hold flies on)."""
        if not cfg.passing_turn_back or self._count >= cfg.max_detours_without_progress:
            return 0
        heading = 1 if wrap_pi(yaw - goal) > 0.0 else -1
        if math.isfinite(h.through_m[heading]) or not math.isfinite(h.through_m[-heading]):
            return 0
        return -heading if _best(h, -heading, cfg, None) is not None else 0

    def _start_scan(self, now_s: float, pos: np.ndarray, yaw: float, goal: float, cfg: DetourConfig, lean: int) -> None:
        """Look round: first to the side away from ``lean`` (the side the memory already favours),
        then to ``lean``'s, so the look ends facing the likelier way."""
        self.phase = Phase.SCAN
        self._scans += 1
        self._scan_since_s = now_s
        self._anchor_ned_m = pos.copy()
        half = math.radians(cfg.scan_half_angle_deg)
        self._scan_goal_rad = goal
        a, b = wrap_pi(goal - half), wrap_pi(goal + half)
        # Through the goal direction: every turn under 180 degrees, so it goes the way meant.
        self._targets = [a, goal, b] if lean > 0 else [b, goal, a]
        if abs(wrap_pi(self._targets[0] - yaw)) > math.radians(150.0):
            self._targets.insert(0, goal)
        self._target_rad = self._targets[0]
        self.reason = f"{self.reason}: looking round"

    def _scan(
        self,
        now_s: float,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        memory: ObstacleMemory,
        memory_cfg: MemoryConfig,
        cfg: DetourConfig,
        prefer_right: bool,
    ) -> DetourCommand | None:
        peek = False
        while self._targets and abs(wrap_pi(self._targets[0] - yaw)) <= _SCAN_TOLERANCE_RAD:
            reached = self._targets.pop(0)
            self._turn_sign = 0
            peek = bool(self._targets) and reached == self._scan_goal_rad
        if peek and now_s - self._scan_since_s <= cfg.scan_timeout_s:
            # Facing the goal with turns still to go: if the way to it is free, or an opening lines
            # up with it, the rest of the look round would change nothing of that choice.
            h = self._histogram(now_s, pos, goal, memory, memory_cfg, cfg, "peek")
            if h is None:
                return self._waiting(pos, yaw, cfg)
            chosen = self._peek_with(h, now_s, pos, yaw, goal, cfg, prefer_right)
            if chosen is not None:
                return chosen
        if self._targets and now_s - self._scan_since_s <= cfg.scan_timeout_s:
            return self._next_turn()
        return self._choose(now_s, pos, yaw, goal, memory, memory_cfg, cfg, prefer_right)

    def _next_turn(self) -> DetourCommand:
        """Look on: turn in place to the look round's next target (there is one)."""
        self._target_rad = self._targets[0]
        self.reason = f"looking round ({len(self._targets)} turn{'s' if len(self._targets) > 1 else ''} to go)"
        return DetourCommand(Phase.SCAN, self._target_rad, self._anchor_ned_m, self.reason)

    def _goal_free(self, h: Histogram, cfg: DetourConfig) -> bool:
        """Whether the goal direction is free far enough to hand back: ``radius_m`` (or to the goal
        point) with ``clearance_m``, or with ``squeeze_clearance_m`` (a door just wide enough)."""
        gd = self._goal_distance_m
        need = cfg.radius_m if gd is None else min(cfg.radius_m, gd)
        return bool(h.free_m[h.goal_index] >= need or h.tight_m[h.goal_index] >= need)

    def _can_hand_back(self, h: Histogram, cfg: DetourConfig) -> bool:
        """Whether a choice from ``h`` hands back (:meth:`_choose_with`): the goal direction free, or
        an opening to line up with it (the mid-look check's and the passing look's test)."""
        return self._goal_free(h, cfg) or h.line_up_m is not None

    def _peek_with(
        self,
        h: Histogram,
        asked_s: float,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        cfg: DetourConfig,
        prefer_right: bool,
        seen_from: np.ndarray | None = None,
    ) -> DetourCommand | None:
        """Mid look round, facing the goal: hand back (:meth:`_choose_with`) when the goal direction is
        free or an opening lines up with it; None: look on."""
        if not self._can_hand_back(h, cfg):
            return None
        return self._choose_with(h, asked_s, pos, yaw, goal, cfg, prefer_right, seen_from)

    def _choose(
        self,
        now_s: float,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        memory: ObstacleMemory,
        memory_cfg: MemoryConfig,
        cfg: DetourConfig,
        prefer_right: bool,
    ) -> DetourCommand | None:
        h = self._histogram(now_s, pos, goal, memory, memory_cfg, cfg, "choose")
        if h is None:
            self._last_plan_s = now_s  # asked: the next replan is due replan_interval_s from now
            if self.phase is Phase.SCAN:
                self.reason = f"looked round{_MAPPING}"
            return self._waiting(pos, yaw, cfg)
        return self._choose_with(h, now_s, pos, yaw, goal, cfg, prefer_right)

    def _choose_with(
        self,
        h: Histogram,
        asked_s: float,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        cfg: DetourConfig,
        prefer_right: bool,
        seen_from: np.ndarray | None = None,
    ) -> DetourCommand | None:
        """A choice from the histogram asked for at ``asked_s`` (seconds) from ``seen_from`` (float
        ``(3,)`` NED metres; None: ``pos``, where the vehicle is now)."""
        self._last_plan_s = asked_s
        # The goal direction free with squeeze_clearance_m is enough to hand back: a door just wide
        # enough for the vehicle (the office's 1.1-1.4 m, 0.55-0.7 m each side of its centre line) is
        # free with clearance_m only within a few centimetres of that line, and a detour that
        # waited for it flew to and fro along the wall past the door. The controller's brake and the
        # guard still act on the way through.
        if self._goal_free(h, cfg):
            self.phase = Phase.HANDBACK
            self._target_rad = goal
            if self._anchor_ned_m is None:  # turning in place already: hold where that began
                self._anchor_ned_m = pos.copy()
            self.reason = "the goal direction is free: turning to it"
            return self._handback(asked_s, pos, yaw, goal, cfg)
        if h.line_up_m is not None:
            # An opening the goal direction just misses (a door whose jambs the map smeared inward):
            # slide to where the path parallel to it is free, facing the goal, and hand back there.
            self.phase = Phase.HANDBACK
            self._target_rad = goal
            # The slide is measured from where the histogram was seen (deferred: a step or two ago).
            self._anchor_ned_m = np.array(pos if seen_from is None else seen_from, dtype=np.float64)
            self._anchor_ned_m[2] = pos[2]
            self._anchor_ned_m[0] -= h.line_up_m * math.sin(h.bearing_rad[h.goal_index])
            self._anchor_ned_m[1] += h.line_up_m * math.cos(h.bearing_rad[h.goal_index])
            self._line_up_since_s = asked_s
            side = "right" if h.line_up_m > 0.0 else "left"
            self.reason = f"lining up with an opening {abs(h.line_up_m):.2f} m to the {side}"
            return self._handback(asked_s, pos, yaw, goal, cfg)
        flying = self.phase is Phase.FLY
        if self._side == 0:
            self._side = _pick_side(h, prefer_right, cfg)
        k = _best(h, self._side, cfg, self._target_rad if flying else None)
        if k is None and flying:
            # Along the way the room narrows as the obstacle's end comes near, or in an opening just
            # wide enough: on the side chosen, a direction free for half min_free_m, then one free with
            # squeeze_clearance_m, still goes on; a look round (and a switch) asks for all of it.
            k = _best(h, self._side, cfg, self._target_rad, 0.5)
            if k is None:
                k = _best(h, self._side, cfg, self._target_rad, 0.5, tight=True)
        if k is None and not self._switched:
            self._switched = True
            self._side = -self._side
            k = _best(h, self._side, cfg, None)
        if k is None:
            # Before a dead end: a direction free for all of min_free_m with squeeze_clearance_m,
            # either side (a gap just wide enough, whose wall grazing-angle stereo smeared inward).
            for side in (self._side, -self._side):
                k = _best(h, side, cfg, None, 1.0, tight=True)
                if k is not None:
                    self._side = side
                    break
        if k is None:
            return self._dead_end(
                pos,
                f"dead end: no direction within {cfg.max_angle_deg:g} deg of the goal free for "
                f"{cfg.min_free_m:g} m (detour.min_free_m), either side",
            )
        # A new direction keeps the anchor: while the vehicle turns in place (a look round, or a turn
        # toward the direction before) it must hold where that turn began: re-anchoring at each replan
        # would let an unseen drift carry it on, 0.4 s at a time. Once it flies a direction there is
        # no anchor, and the next turn starts one.
        self.phase = Phase.FLY
        self._target_rad = float(h.bearing_rad[k])
        side = "right" if self._side > 0 else "left"
        self.reason = f"round the {side}: {math.degrees(abs(h.offset_rad[k])):.0f} deg off the goal direction"
        return self._fly_command(pos, yaw, cfg)

    def _fly(
        self,
        now_s: float,
        decision: Decision | None,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        memory: ObstacleMemory,
        memory_cfg: MemoryConfig,
        cfg: DetourConfig,
        prefer_right: bool,
    ) -> DetourCommand | None:
        self._note_brake(now_s, decision, yaw, pos, cfg)
        if now_s - self._last_plan_s >= cfg.replan_interval_s:
            return self._choose(now_s, pos, yaw, goal, memory, memory_cfg, cfg, prefer_right)
        return self._fly_command(pos, yaw, cfg)

    def _await(
        self,
        now_s: float,
        decision: Decision | None,
        pos: np.ndarray,
        yaw: float,
        goal: float,
        cfg: DetourConfig,
        prefer_right: bool,
    ) -> DetourCommand | None:
        """Deferred, a histogram asked for: fly on safely until it comes (:meth:`_waiting`), then
        go on as :meth:`_begin` or :meth:`_choose` would have with it."""
        if self._answer is None:
            if self.phase is Phase.FLY:
                self._note_brake(now_s, decision, yaw, pos, cfg)  # a brake meanwhile still closes the way
            return self._waiting(pos, yaw, cfg)
        request, purpose, result = self._request, self._awaiting, self._answer
        self._drop_request()
        assert request is not None
        if result.histogram is None:
            return self._dead_end(
                pos, f"dead end: the detour's histogram could not be computed ({result.error or 'no reason given'})"
            )
        # Directions a brake closed after the request was made are closed too.
        h = _close_vetoed(result.histogram, request.position_ned_m, tuple(self._vetoes[len(request.vetoes) :]))
        if purpose == "begin":
            self.reason = self.reason.removesuffix(_MAPPING)  # the trigger's reason, as without the wait
            return self._begin_with(h, now_s, pos, yaw, goal, cfg, prefer_right, request.position_ned_m)
        if purpose == "peek":
            chosen = self._peek_with(h, request.asked_s, pos, yaw, goal, cfg, prefer_right, request.position_ned_m)
            if chosen is not None or not self._targets:
                return chosen if chosen is not None else self._waiting(pos, yaw, cfg)
            return self._next_turn()
        return self._choose_with(h, request.asked_s, pos, yaw, goal, cfg, prefer_right, request.position_ned_m)

    def _waiting(self, pos: np.ndarray, yaw: float, cfg: DetourConfig) -> DetourCommand:
        """While a histogram is awaited: in FLY, the direction chosen before (the controller's brake
        stays absolute); else (a first choice, or after a look round) turn in place where the vehicle
        holds, to the heading asked before (None: keep it), never toward a direction not chosen."""
        if self.phase is Phase.FLY and self._target_rad is not None:
            return self._fly_command(pos, yaw, cfg)
        if self._anchor_ned_m is None:
            self._anchor_ned_m = pos.copy()
        return DetourCommand(Phase.SCAN, self._target_rad, self._anchor_ned_m, self.reason)

    def _note_brake(self, now_s: float, decision: Decision | None, yaw: float, pos: np.ndarray, cfg: DetourConfig) -> None:
        """Flying: a brake for ``trigger_after_s`` while facing the direction closes it from here."""
        braking = decision is not None and decision.kind is DecisionKind.BRAKE
        if not braking:
            self._brake_since_s = None
        elif self._brake_since_s is None:
            self._brake_since_s = now_s
        facing = self._target_rad is not None and abs(wrap_pi(self._target_rad - yaw)) <= math.radians(cfg.turn_in_place_deg)
        if self._brake_since_s is not None and facing and now_s - self._brake_since_s >= cfg.trigger_after_s:
            # The controller brakes on this direction: close it from here, and choose again.
            self._vetoes.append((float(pos[0]), float(pos[1]), float(self._target_rad)))
            self._brake_since_s = None
            self._last_plan_s = -math.inf

    def _fly_command(self, pos: np.ndarray, yaw: float, cfg: DetourConfig) -> DetourCommand:
        assert self._target_rad is not None
        if abs(wrap_pi(self._target_rad - yaw)) > math.radians(cfg.turn_in_place_deg):
            if self._anchor_ned_m is None:
                self._anchor_ned_m = pos.copy()  # turn in place here
            return DetourCommand(Phase.FLY, self._target_rad, self._anchor_ned_m, self.reason)
        self._anchor_ned_m = None
        return DetourCommand(Phase.FLY, self._target_rad, None, self.reason)

    def _handback(
        self, now_s: float, pos: np.ndarray, yaw: float, goal: float, cfg: DetourConfig
    ) -> DetourCommand | None:
        self._target_rad = goal
        facing = abs(wrap_pi(goal - yaw)) <= math.radians(cfg.turn_in_place_deg)
        if facing and self._line_up_since_s is not None:
            # Lining up: hand back once at the slide's end, or after _LINE_UP_SETTLE_S (the hold's
            # pull, 1/s, leaves a drift of 0.14 m/s 0.14 m off; gap centering goes on from there).
            assert self._anchor_ned_m is not None
            off = math.hypot(pos[0] - self._anchor_ned_m[0], pos[1] - self._anchor_ned_m[1])
            if off <= _LINE_UP_TOLERANCE_M or now_s - self._line_up_since_s >= _LINE_UP_SETTLE_S:
                self._end(pos, "handed back to course hold: lined up with an opening toward the goal")
                return None
            return DetourCommand(Phase.HANDBACK, goal, self._anchor_ned_m, self.reason)
        if facing:
            self._end(pos, "handed back to course hold: the goal direction is free")
            return None
        if self._anchor_ned_m is None:
            self._anchor_ned_m = pos.copy()
        return DetourCommand(Phase.HANDBACK, goal, self._anchor_ned_m, self.reason)

    def _end(self, pos: np.ndarray, reason: str) -> None:
        if self._side != 0:
            self._last_end = (float(pos[0]), float(pos[1]), self._side)
        mark = self._progress_mark_s
        self.reset()
        self._progress_mark_s = mark  # a stall answered once is not answered again
        self.reason = reason

    def _dead_end(self, pos: np.ndarray, reason: str) -> DetourCommand:
        self._drop_request()
        self.phase = Phase.DEAD_END
        self._anchor_ned_m = pos.copy()
        self._target_rad = None
        self.reason = reason
        return DetourCommand(Phase.DEAD_END, None, self._anchor_ned_m, reason)

    # ------------------------------------------------------------------------------------ helpers

    def _histogram(
        self,
        now_s: float,
        pos: np.ndarray,
        goal: float,
        memory: ObstacleMemory,
        memory_cfg: MemoryConfig,
        cfg: DetourConfig,
        purpose: str,
    ) -> Histogram | None:
        """The histogram from here now; deferred: None, and the request is left for the caller
        (:attr:`pending_request`), for ``purpose`` ("begin", "peek", "choose" or "passing")."""
        request = self._request_for(now_s, pos, goal, memory, memory_cfg, cfg)
        if not self.defer:
            return compute_histogram(request)
        self._request, self._awaiting, self._answer = request, purpose, None
        return None

    def _request_for(
        self, now_s: float, pos: np.ndarray, goal: float, memory: ObstacleMemory, memory_cfg: MemoryConfig, cfg: DetourConfig
    ) -> HistogramRequest:
        reach_m = max(cfg.radius_m, memory_cfg.map_depth_m)
        # a new array: no copy needed
        pts = memory.map_points(pos, now_s, memory_cfg, reach_m + cfg.clearance_m, self._course_down_m)
        pts = np.empty((0, 2)) if pts is None else pts
        trail = None
        if self.trail:
            tr = np.array(self.trail, dtype=np.float64)
            old = tr[:, 2] <= now_s - cfg.visited_age_s
            trail = tr[old, :2] - pos[:2]
        self._next_seq += 1
        return HistogramRequest(
            seq=self._next_seq,
            asked_s=float(now_s),
            position_ned_m=_frozen(pos.copy()),
            points_ne_m=_frozen(pts),
            trail_ne_m=_frozen(trail),
            goal_bearing_rad=goal,
            goal_distance_m=self._goal_distance_m,
            vetoes=tuple(self._vetoes),
            map_depth_m=float(memory_cfg.map_depth_m),
            cfg=cfg,
            start_goal_rad=self._start_goal_rad if self._start_cone(pos, cfg) else None,
        )

    def _remember_trail(self, pos: np.ndarray, now_s: float, cfg: DetourConfig) -> None:
        if not self.trail or math.hypot(pos[0] - self.trail[-1][0], pos[1] - self.trail[-1][1]) >= cfg.visited_spacing_m:
            self.trail.append((float(pos[0]), float(pos[1]), float(now_s)))

    def _start_cone(self, pos: np.ndarray, cfg: DetourConfig) -> bool:
        """Whether the start's goal direction widens the histogram here (``cone_from_start``, within
        ``cone_from_start_max_m`` of where the detour began)."""
        # only a resolved true widens it (the loader resolves "auto"; a model built without validation: off)
        return cfg.cone_from_start is True and self._distance_from_start_m(pos) <= cfg.cone_from_start_max_m

    def _distance_from_start_m(self, pos: np.ndarray) -> float:
        if self._start_ned_m is None:
            return 0.0
        return math.hypot(pos[0] - self._start_ned_m[0], pos[1] - self._start_ned_m[1])


def _pick_side(h: Histogram, prefer_right: bool, cfg: DetourConfig, openings: bool = True) -> int:
    """+1 (right of the goal) or -1: the side where a shorter step square to the goal direction opens
    the way to it (:attr:`Histogram.through_m`: an opening, or the end of the wall; and, with
    ``openings``, :attr:`Histogram.opening_m`: the middle of an opening closed at both ends, on a
    side with a free direction); when neither
    does within the look-ahead, the side with the free direction nearest the goal; a tie goes to the
    preferred side."""
    angle = np.abs(h.offset_rad)
    usable = h.free_m >= cfg.min_free_m
    best: dict[int, float] = {}
    for side in (1, -1):
        a = angle[(np.sign(h.offset_rad) == side) & usable]
        best[side] = float(a.min()) if a.size else math.inf
    step = dict(h.through_m)
    if openings:
        # An opening counts only where its side has a direction to fly now: choosing a side with none
        # would spend the detour's one switch at once and leave the next replan a dead end.
        step = {side: min(step[side], h.opening_m[side] if math.isfinite(best[side]) else math.inf) for side in (1, -1)}
    r, left = step[1], step[-1]
    if not (math.isinf(r) and math.isinf(left)) and abs(r - left) > 0.5 * _THROUGH_STEP_M:
        return 1 if r < left else -1
    if abs(best[1] - best[-1]) > 0.5 * math.radians(cfg.sector_deg):
        return 1 if best[1] < best[-1] else -1
    return 1 if prefer_right else -1


def _best(
    h: Histogram, side: int, cfg: DetourConfig, current_rad: float | None, share: float = 1.0, tight: bool = False
) -> int | None:
    """The index of the free direction (free for ``min_free_m``) on ``side`` of the goal, or within
    ``either_side_within_deg`` of it on the other side (costing half a sector more; the goal direction
    itself hands back instead), costing least:
    its angle off the goal, plus ``prefer_clear_cost_deg`` when it is not free for ``min_free_m`` with
    ``preferred_clearance_m`` and ``visited_cost_deg`` back over the trail; the direction flown now
    (``current_rad``, when it is one of the histogram's: while hovering or turning in place) keeps its
    place unless another costs :data:`_HYSTERESIS_DEG` less. None: none
    free on that side. ``share``: the part of ``min_free_m`` that counts as free; ``tight``: free with
    ``squeeze_clearance_m`` instead of ``clearance_m``."""
    free = h.tight_m if tight else h.free_m
    own = np.sign(h.offset_rad) == side
    near_goal = np.abs(h.offset_rad) <= math.radians(cfg.either_side_within_deg) + 1e-9
    on = (own | near_goal) & (h.offset_rad != 0.0) & (free >= share * cfg.min_free_m)
    if not np.any(on):
        return None
    cost = np.degrees(np.abs(h.offset_rad))
    cost = cost + np.where(h.roomy_m >= share * cfg.min_free_m, 0.0, cfg.prefer_clear_cost_deg)
    cost = cost + np.where(h.visited, cfg.visited_cost_deg, 0.0)
    # The side chosen wins a tie: the other side's directions near the goal are for an opening there.
    cost = cost + np.where(own, 0.0, 0.5 * cfg.sector_deg)
    cost = np.where(on, cost, np.inf)
    k = int(np.argmin(cost))
    if current_rad is not None:
        # The directions are laid out from the goal's bearing, which turns as the vehicle moves, so
        # this matches only while it hovers or turns in place; in flight every replan chooses afresh.
        # Matching the nearest within half a sector in flight too would fly past openings a fresh
        # choice turns into.
        near = np.abs(np.array([wrap_pi(b - current_rad) for b in h.bearing_rad]))
        j = int(np.argmin(near))
        if on[j] and near[j] < 1e-6 and cost[j] - cost[k] < _HYSTERESIS_DEG:
            return j
    return k


def _vertical_escape(decision: Decision | None, at_floor: bool = False) -> bool:
    """Whether ``decision`` escapes over or under (:data:`VERTICAL_ESCAPE`). ``at_floor``: the vehicle
    is within :data:`FLOOR_MARGIN_M` of ``command.min_altitude_m``, where a descent is no escape."""
    return (
        decision is not None
        and decision.kind is DecisionKind.AVOID
        and abs(decision.pitch) >= VERTICAL_ESCAPE
        and abs(decision.pitch) > abs(decision.yaw)
        and not (at_floor and decision.pitch < 0.0)
    )
