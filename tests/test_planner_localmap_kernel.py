"""The local map's compiled queries against a NumPy statement of the same query: for the free lengths,
the same length and verdict (blocked, horizon) for every line, on maps seen through frames and on random
layers; for the columns the way cannot pass, the same columns; for the swings of the predicted paths,
the same clearance."""

from __future__ import annotations

import numpy as np
import pytest

from companion.core.geometry import StereoGeometry
from companion.core.planner.localmap import (
    MIXED_EVIDENCE_S,
    OCCUPIED_LOG_ODDS,
    RIM_POINTS,
    LocalMap,
    _moves_closer,
)
from companion.core.pose import Pose

GEOM = StereoGeometry.ideal(336, 188, 90.0, 0.12)


def _rim_offsets(d: np.ndarray, radius_m: float) -> np.ndarray:
    """float64 ``(K, RIM_POINTS, 3)``: points a radius off each line of directions ``d`` (float
    ``(K, 3)`` unit NED), evenly round it, the first level with the line."""
    up = np.array([0.0, 0.0, -1.0])
    side = np.cross(up, d)  # level, perpendicular to the line
    n = np.linalg.norm(side, axis=1, keepdims=True)
    side = np.where(n > 1e-6, side / np.maximum(n, 1e-12), np.array([0.0, 1.0, 0.0]))  # a vertical line: any side
    over = np.cross(d, side)
    a = np.arange(RIM_POINTS) * (2.0 * np.pi / RIM_POINTS)
    return radius_m * (np.cos(a)[None, :, None] * side[:, None, :] + np.sin(a)[None, :, None] * over[:, None, :])


def _free_lengths_numpy(m: LocalMap, start: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The query as whole-array NumPy: every sample of every line and the rim round each, then the first bad."""
    h = m.range_m
    s = np.arange(m.voxel_m, h + 1e-9, m.voxel_m)
    pts = start + d[:, None, :] * s[None, :, None]
    idx, inside = m._index(pts)
    infl = m._inflated_at(idx)
    free = m._free_at(idx)
    if bool(m.within_radius(start)):
        n = int(np.count_nonzero(s <= m.radius_m + m.voxel_m))
        infl[:, :n] = m._occ.reshape(-1)[idx[:, :n]] | _moves_closer(m, start, pts[:, :n])
    ok = np.cumprod(free & ~infl & inside, axis=1, dtype=bool) & (s >= 2.0 * m.radius_m)[None, :]
    kk, ss = np.nonzero(ok)
    if len(kk):
        rim = pts[kk, ss, None, :] + _rim_offsets(d, m.radius_m)[kk]
        r_idx, r_in = m._index(rim)
        free[kk, ss] = np.all(m._free_at(r_idx) | ~r_in, axis=1)
    blocked_at = infl & inside
    bad = blocked_at | ~free | ~inside
    any_bad = bad.any(axis=1)
    first = np.where(any_bad, bad.argmax(axis=1), len(s))
    length = np.where(any_bad, np.where(first > 0, s[np.maximum(first - 1, 0)], 0.0), h)
    blocked = any_bad & blocked_at[np.arange(len(d)), np.minimum(first, len(s) - 1)]
    return length, blocked, ~any_bad


def _directions(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d[: n // 2, 2] *= 0.2  # mostly near level, as the planner asks
    d[0] = [1.0, 0.0, 0.0]  # exactly along the grid's axes too
    d[1] = [0.0, 0.0, -1.0]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _assert_same(m: LocalMap, start: np.ndarray, d: np.ndarray) -> None:
    fl = m.free_lengths(start, d)
    length, blocked, horizon = _free_lengths_numpy(m, start, d)
    np.testing.assert_array_equal(fl.length_m, length)
    np.testing.assert_array_equal(fl.blocked, blocked)
    np.testing.assert_array_equal(fl.horizon, horizon)


def test_compiled_free_lengths_equal_numpy_on_a_map_seen_through_frames() -> None:
    rng = np.random.default_rng(7)
    m = LocalMap(voxel_m=0.15, range_m=8.0, radius_m=0.25, occupied_memory_s=20.0, free_memory_s=6.0)
    # A room of walls at several depths and a post, seen from a yawing vehicle.
    blocks = np.full((47, 84), np.nan, dtype=np.float32)
    blocks[:, :30] = GEOM.focal_baseline_px_m / 3.0
    blocks[10:40, 30:50] = GEOM.focal_baseline_px_m / 5.5
    blocks[:, 60:] = GEOM.focal_baseline_px_m / 2.0
    for k in range(12):
        m.integrate(blocks, GEOM, 4, Pose.at(0.1 * k, 0.0, 1.5, yaw_rad=0.26 * k), 0.1 * k)
    m.mark_body_free(np.array([0.3, 0.0, -1.5]), 0.3)
    d = _directions(rng, 96)
    for start in ([0.0, 0.0, -1.5], [0.37, -0.21, -1.42], [1.3, 0.8, -1.9]):
        _assert_same(m, np.array(start), d)


@pytest.mark.parametrize("seed", range(4))
def test_compiled_free_lengths_equal_numpy_on_random_layers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = LocalMap(voxel_m=0.2, range_m=5.0, radius_m=0.3, occupied_memory_s=20.0, free_memory_s=6.0)
    m.centre_on(np.zeros(3))
    shape = m.shape
    m.now_s = 10.0
    # Sparse layers, with values on each side of every threshold, so that lines end in every way.
    m._fcnt[...] = (rng.random(shape) < 0.997).astype(np.int8)
    odds = np.array([0.0, OCCUPIED_LOG_ODDS, 0.71, 1.5], dtype=np.float32)
    m.log_odds[...] = rng.choice(odds, size=shape, p=[0.992, 0.004, 0.002, 0.002])
    m.prev_hit_t[...] = np.where(rng.random(shape) < 0.002, np.float32(m.now_s - MIXED_EVIDENCE_S), -np.inf)
    # Passes on each side of the mixed-evidence threshold (and none at all) after those hits.
    m.free_t[...] = rng.choice(np.array([-np.inf, m.now_s - 1.0, m.now_s - 0.5, m.now_s], dtype=np.float32), size=shape)
    m._evidence_ok[...] = m._evidence_ok_at(slice(None)).reshape(shape)  # what a frame keeps up
    m._occ[...] = rng.random(shape) < 0.0005
    m._infl[...] = (rng.random(shape) < 0.001).astype(np.int16) + m._occ
    m._body_mask[...] = rng.random(shape) < 0.01
    d = _directions(rng, 128)
    starts = rng.uniform(-1.5, 1.5, size=(6, 3))
    occ_cube = np.argwhere(m._occ)[0]
    starts[0] = (occ_cube + m.origin + 0.5) * m.voxel_m + 0.03  # within a surface's radius: the way out
    starts[1] = np.array(shape) * m.voxel_m  # far off the grid: nothing free
    assert m.within_radius(starts[0])
    for start in starts:
        _assert_same(m, start, d)


@pytest.mark.parametrize("seed", range(2))
def test_lines_from_their_own_starts_equal_each_line_from_its_start(seed: int) -> None:
    """``free_lengths_from``: each line as the whole-array NumPy query from its own start, except that
    a start within a surface's radius ends its line there, blocked."""
    rng = np.random.default_rng(100 + seed)
    m = LocalMap(voxel_m=0.2, range_m=5.0, radius_m=0.3, occupied_memory_s=20.0, free_memory_s=6.0)
    m.centre_on(np.zeros(3))
    m.now_s = 10.0
    m._fcnt[...] = (rng.random(m.shape) < 0.997).astype(np.int8)
    m._occ[...] = rng.random(m.shape) < 0.0005
    m._infl[...] = (rng.random(m.shape) < 0.002).astype(np.int16) + m._occ
    d = _directions(rng, 64)
    starts = rng.uniform(-1.5, 1.5, size=(64, 3))
    occ_cube = np.argwhere(m._occ)[0]
    starts[0] = (occ_cube + m.origin + 0.5) * m.voxel_m + 0.03
    fl = m.free_lengths_from(starts, d)
    inside = m.within_radius(starts)
    assert inside[0] and not inside.all()
    for k in range(len(d)):
        if inside[k]:
            assert fl.length_m[k] == 0.0 and fl.blocked[k] and not fl.horizon[k]
            continue
        length, blocked, horizon = _free_lengths_numpy(m, starts[k], d[k : k + 1])
        assert (fl.length_m[k], fl.blocked[k], fl.horizon[k]) == (length[0], blocked[0], horizon[0]), k


def _blocked_columns_numpy(m: LocalMap, k0: int, lo: int, hi: int) -> np.ndarray:
    at_level = m._infl[:, :, k0] > 0
    if hi <= lo:
        return at_level
    i, j = np.nonzero(at_level)
    band = (i[:, None], j[:, None], np.arange(lo, hi)[None, :])
    free = (m._fcnt[band] > 0) & (m.log_odds[band] <= np.float32(OCCUPIED_LOG_ODDS)) & (m._infl[band] == 0)
    at_level[i, j] = ~free.any(axis=1)
    return at_level


@pytest.mark.parametrize("seed", range(2))
def test_compiled_blocked_columns_equal_numpy(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    m = LocalMap(voxel_m=0.2, range_m=5.0, radius_m=0.3, occupied_memory_s=20.0, free_memory_s=6.0)
    m.centre_on(np.zeros(3))
    shape = m.shape
    m._fcnt[...] = (rng.random(shape) < 0.7).astype(np.int8)
    odds = np.array([0.0, OCCUPIED_LOG_ODDS, 0.71], dtype=np.float32)
    m.log_odds[...] = rng.choice(odds, size=shape, p=[0.8, 0.1, 0.1])
    m._infl[...] = (rng.random(shape) < 0.5).astype(np.int16)
    oz, v = int(m.origin[2]), m.voxel_m
    closed = []
    for level, top, bottom in ((-1.5, -3.0, -0.5), (0.0, -1.0, 1.0), (-1.0, -0.8, -1.2), (-1.0, -9.0, 9.0)):
        k0 = int(np.floor(level / v)) - oz
        lo = max(0, int(np.floor(top / v)) - oz)
        hi = min(shape[2], int(np.floor(bottom / v)) - oz + 1)
        expected = _blocked_columns_numpy(m, k0, lo, hi)
        np.testing.assert_array_equal(m.blocked_columns(level, top, bottom), expected)
        closed.append(int(expected.sum()))
    assert min(closed[:3]) > 0 and max(closed) < expected.size


def _clear_along_numpy(m: LocalMap, start: np.ndarray, points: np.ndarray, arc: np.ndarray) -> np.ndarray:
    """How far along each sampled path (``points`` float ``(K, S, 3)`` NED m at arc lengths ``arc``
    ``(K, S)``, NaN past its end) the centre stays out of every inflation, as whole-array NumPy."""
    valid = np.isfinite(arc)
    idx, inside = m._index(points)
    hit = m._inflated_at(idx) & inside & valid
    if bool(m.within_radius(start)):
        near = np.where(valid, arc, np.inf) <= m.radius_m + m.voxel_m
        hit = np.where(near, m.occupied().reshape(-1)[idx] & inside & valid, hit)
    first = hit.argmax(axis=1)
    before = np.where(first > 0, arc[np.arange(len(arc)), np.maximum(first - 1, 0)], 0.0)
    return np.where(hit.any(axis=1), before, np.inf)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_swings_equal_predicted_paths_judged_by_numpy(seed: int) -> None:
    """``clear_along``: for every command, the least over the velocities of the whole-array NumPy
    judgement of ``predicted_paths``, bit for bit; from a start within a surface's radius too."""
    from companion.config.planner import PlannerConfig
    from companion.core.planner.paths import predicted_paths, swing_profile

    rng = np.random.default_rng(200 + seed)
    cfg = PlannerConfig()
    m = LocalMap(voxel_m=0.15, range_m=cfg.map_range_m, radius_m=0.25, occupied_memory_s=20.0, free_memory_s=6.0)
    m.centre_on(np.zeros(3))
    m._occ[...] = rng.random(m.shape) < 0.002
    m._infl[...] = (rng.random(m.shape) < 0.003).astype(np.int16) + m._occ
    d = _directions(rng, 24)
    speeds = rng.uniform(0.0, cfg.cruise_speed_m_s, size=len(d))
    velocities = rng.uniform(-3.0, 3.0, size=(2, 3))
    t, lag, tail = swing_profile(cfg, m.voxel_m)
    occ_cube = np.argwhere(m._occ)[0]
    starts = [rng.uniform(-1.0, 1.0, size=3), (occ_cube + m.origin + 0.5) * m.voxel_m + 0.03]
    assert m.within_radius(starts[1])
    for start in starts:
        got = m.clear_along(start, velocities, d, speeds, t, lag, tail, cfg.map_range_m)
        n = len(velocities)
        offs, arc = predicted_paths(np.repeat(velocities, len(d), axis=0), np.tile(d, (n, 1)), np.tile(speeds, n), cfg, m.voxel_m)
        expected = _clear_along_numpy(m, start, start + offs, arc).reshape(n, len(d)).min(axis=0)
        np.testing.assert_array_equal(got, expected)
        assert np.isfinite(expected).any() and np.isinf(expected).any()
