"""Where a candidate leads (pure; arrays in, arrays out): its direction, the path it is scored along, and
the path the vehicle will fly to it.

A candidate is a straight line from the vehicle, but the cost scores where the line *leads*: a line
that ends where the vehicle would not stop is bent there and scored on, as a path of two legs (its
line to a knee, then straight on from the knee):

- a descent cut by the floor levels off there and flies on along it (:func:`bend_at_floor`);
- a level line that ends at a surface short of the goal turns, where the speed law would stop on it,
  onto the way to the goal round what was seen (:func:`bend_onto_way`): the vehicle slides along a
  wall toward the gap, it does not stop at the wall. Scored as stops, the lines toward either side
  of a box all look alike and short, and the planner turns between them.

The floor bounds the height; it is no surface to stop at. A descent that reaches it levels off (the
floor filter takes the descent off) and flies on, so its bent path is flown at the speed law's speed
on that path, and the vehicle's *motion*, which the safety chain judges, is judged the same way
(:func:`floor_bent_lengths`), not into the ground beyond it. A wall's bend is another matter: the
speed law flies only the line that ends at the wall, and the bend is what the cost hopes for beyond
it. The vehicle's own path to a candidate swings from its motion into the new direction
(:func:`predicted_paths`): that is what the map's clearance judges.
"""

from __future__ import annotations

import math

import numpy as np

from companion.config.planner import PlannerConfig
from companion.core.planner.localmap import LocalMap
from companion.core.planner.way import WayToGoal

#: Only a line within this of the way's bearing from the vehicle bends onto the way, radians: a line
#: that leads away from the way is no start of it.
BEND_MAX_RAD = math.pi / 2.0


def angle_diff(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """The absolute difference of angles ``a`` and ``b`` (radians), wrapped to [0, π]."""
    return np.abs((np.asarray(a) - np.asarray(b) + math.pi) % (2.0 * math.pi) - math.pi)


def directions(yaw_rad: np.ndarray, climb_rad: np.ndarray) -> np.ndarray:
    """Unit NED vectors float64 ``(K, 3)`` of yaws and climbs (radians, climb positive up)."""
    c = np.cos(climb_rad)
    return np.stack([c * np.cos(yaw_rad), c * np.sin(yaw_rad), -np.sin(climb_rad)], axis=-1)


#: Samples of a candidate's swing (the lagging part of its predicted path), per path.
SWING_SAMPLES = 32
#: The cheapest candidates (on their lines) whose predicted paths are checked each tick.
SWING_CANDIDATES = 24
#: The swing is followed for this many time constants (the velocity is then within 5 % of the command).
SWING_TIME_CONSTANTS = 3.0


def swing_profile(cfg: PlannerConfig, step_m: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The swing of :func:`predicted_paths`: its sample times ``t`` (float64 ``(M,)`` s, over
    :data:`SWING_TIME_CONSTANTS` time constants), the old velocity's share flown by each, ``τ(1 -
    exp(-t/τ))`` (float64 ``(M,)`` s), and the tail's samples, ``step_m`` apart to the map range."""
    tau = max(cfg.latency_s, 1e-3)
    t = (SWING_TIME_CONSTANTS * tau) * np.linspace(0.0, 1.0, SWING_SAMPLES + 1)[1:]
    lag = tau * (1.0 - np.exp(-t / tau))
    return t, lag, int(math.ceil(cfg.map_range_m / step_m))


def predicted_paths(
    velocity_ned_m_s: np.ndarray, dirs: np.ndarray, speed_m_s: np.ndarray, cfg: PlannerConfig, step_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where the vehicle will fly for each candidate: its velocity now (float ``(3,)`` NED m/s, or
    ``(K, 3)``, one per candidate) blending into the command ``dirs * speed_m_s`` (float ``(K, 3)``
    unit NED, ``(K,)`` m/s) as a first-order lag, then on along the candidate to the map range.

    The lag's time constant is ``latency_s`` (the planner's own response setting: a frame, the
    pipeline and the autopilot's velocity response), the old velocity decaying as ``exp(-t/τ)``:
    told to turn, the vehicle carries on along its motion about its speed times ``τ``.

    Returns ``(offsets, arc)``: float64 ``(K, S, 3)`` NED metres from the vehicle and ``(K, S)`` arc
    length from it, metres, increasing (NaN past the map range)."""
    v0 = np.broadcast_to(np.asarray(velocity_ned_m_s, dtype=np.float64), dirs.shape)
    vc = dirs * np.asarray(speed_m_s, dtype=np.float64)[:, None]
    dv = v0 - vc
    t, lag, n_tail = swing_profile(cfg, step_m)
    swing = vc[:, None, :] * t[None, :, None] + dv[:, None, :] * lag[None, :, None]  # (K, M, 3)
    tail = swing[:, -1:, :] + dirs[:, None, :] * (step_m * np.arange(1, n_tail + 1))[None, :, None]
    pts = np.concatenate([swing, tail], axis=1)
    seg = np.diff(np.concatenate([np.zeros((len(dirs), 1, 3)), pts], axis=1), axis=1)
    arc = np.cumsum(np.linalg.norm(seg, axis=2), axis=1)
    arc = np.where(arc <= cfg.map_range_m + 1e-9, arc, np.nan)
    return pts, arc


def along(
    pos: np.ndarray, dirs: np.ndarray, knee_m: np.ndarray, onward: np.ndarray, length_m: np.ndarray
) -> np.ndarray:
    """float64 ``(K, 3)`` NED m: the point ``length_m`` (float ``(K,)`` m) along each candidate's path
    from ``pos`` (float ``(3,)`` NED m): along its line ``dirs`` (unit, ``(K, 3)``) up to its knee
    ``knee_m`` (``(K,)`` m; at least its length where it does not bend), then along ``onward``."""
    first = np.minimum(length_m, knee_m)
    return pos + dirs * first[:, None] + onward * (length_m - first)[:, None]


def _bend(
    lmap: LocalMap,
    idx: np.ndarray,
    knee: np.ndarray,
    knees: np.ndarray,
    leg: np.ndarray,
    path_m: np.ndarray,
    knee_m: np.ndarray,
    onward: np.ndarray,
    only_longer: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Bend, in place, the candidates ``idx`` (int ``(N,)``) at ``knee`` (float ``(N,)`` m along their
    lines; the points ``knees``, float ``(N, 3)`` NED m) onto ``leg`` (unit NED, ``(N, 3)``): their
    knee, their direction on, and ``path_m`` the length of both legs within the map's range. With
    ``only_longer``, only those whose bent path is longer than ``path_m`` now.

    Returns the candidates bent (int) and, for each, whether its second leg ends at a surface short
    of the map's range (bool): the length compared is the unclipped one."""
    on = lmap.free_lengths_from(knees, leg)
    bent = knee + on.length_m
    keep = bent > path_m[idx] if only_longer else np.ones(len(idx), dtype=bool)
    idx, bent = idx[keep], bent[keep]
    path_m[idx] = np.minimum(bent, lmap.range_m)
    knee_m[idx] = knee[keep]
    onward[idx] = leg[keep]
    return idx, on.blocked[keep] & (bent < lmap.range_m)


def bend_at_floor(
    lmap: LocalMap,
    pos: np.ndarray,
    yaw: np.ndarray,
    dirs: np.ndarray,
    to_band_m: np.ndarray,
    band_cut: np.ndarray,
    path_m: np.ndarray,
    knee_m: np.ndarray,
    onward: np.ndarray,
) -> None:
    """Level off, in place, the descents cut by the floor (``band_cut`` and descending; ``to_band_m``
    float ``(K,)`` m to the band's edge along each line): the knee where the line meets the floor, on
    along it at the line's yaw, the path's length ``path_m`` that of both legs (within the map's range);
    ``band_cut`` stays only where the level leg ends at a surface short of the range (a wall down to the
    ground) and not where it passes on (under an overhead block)."""
    cut = np.flatnonzero(band_cut & (dirs[:, 2] > 0.0))
    if len(cut) == 0:
        return
    knee = to_band_m[cut]
    knees = pos + dirs[cut] * knee[:, None]
    level = directions(yaw[cut], np.zeros(len(cut)))
    cut, at_surface = _bend(lmap, cut, knee, knees, level, path_m, knee_m, onward, only_longer=False)
    band_cut[cut] = at_surface


def to_band(pos: np.ndarray, dirs: np.ndarray, floor_m: float, ceiling_m: float) -> np.ndarray:
    """How far each line from ``pos`` (float ``(3,)`` NED m) along ``dirs`` (unit NED ``(K, 3)``) stays
    between ``floor_m`` and ``ceiling_m`` (altitudes, m), float64 ``(K,)`` m: inf for a level line, 0
    for one already outside toward the side it heads to."""
    alt = -float(pos[2])
    vz = -dirs[:, 2]  # climb per metre flown
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(vz > 1e-6, (ceiling_m - alt) / vz, np.where(vz < -1e-6, (alt - floor_m) / -vz, np.inf))
    return np.maximum(d, 0.0)


def floor_bent_lengths(
    lmap: LocalMap, pos: np.ndarray, dirs: np.ndarray, free_m: np.ndarray, floor_m: float
) -> np.ndarray:
    """The length flown along each line before a surface, float64 ``(K,)`` m: ``free_m`` (float ``(K,)``
    m, the map's free length along ``dirs``, unit NED ``(K, 3)``, from ``pos``, NED m), except that a
    descent reaching the floor (``floor_m``, altitude m) before a surface levels off there and flies on
    (:func:`bend_at_floor`): the length of both legs. What the safety chain's speed law judges."""
    path = np.array(free_m, dtype=np.float64)
    to_floor = to_band(pos, dirs, floor_m, math.inf)
    cut = to_floor < path
    if np.any(cut):
        yaw = np.arctan2(dirs[:, 1], dirs[:, 0])
        bend_at_floor(lmap, pos, yaw, dirs, to_floor, cut, path, np.full(len(path), np.inf), dirs.copy())
    return path


def bend_onto_way(
    lmap: LocalMap,
    way: WayToGoal,
    pos: np.ndarray,
    yaw: np.ndarray,
    dirs: np.ndarray,
    may_bend: np.ndarray,
    way_yaw: float,
    goal_m: float,
    stop_m: float,
    blocked: np.ndarray,
    path_m: np.ndarray,
    knee_m: np.ndarray,
    onward: np.ndarray,
) -> None:
    """Bend, in place, the lines that ``may_bend`` (bool ``(K,)``: those level with the goal's
    altitude) within :data:`BEND_MAX_RAD` of the way's bearing ``way_yaw`` (radians) that end at a
    surface (``blocked``) short of the goal (``goal_m``, m): where the speed law stops on the line,
    ``stop_m`` (m) short of its end, onto the way's bearing from that knee. Where that path is longer
    than the line, ``path_m`` becomes its length (within the map's range) and ``blocked`` whether its
    second leg ends at a surface short of the range."""
    ends = np.flatnonzero(
        may_bend & blocked & (path_m > stop_m) & (path_m < goal_m) & (angle_diff(yaw, way_yaw) <= BEND_MAX_RAD)
    )
    if len(ends) == 0:
        return
    knee = path_m[ends] - stop_m
    knees = pos + dirs[ends] * knee[:, None]
    bearing = way.bearings(knees)
    ok = np.isfinite(bearing)
    if not np.any(ok):
        return
    ends, knee, knees, bearing = ends[ok], knee[ok], knees[ok], bearing[ok]
    leg = directions(bearing, np.zeros(len(ends)))
    ends, at_surface = _bend(lmap, ends, knee, knees, leg, path_m, knee_m, onward, only_longer=True)
    blocked[ends] = at_surface
