"""Compiled kernels of the local map's queries (:class:`companion.core.planner.localmap.LocalMap`): the
free lengths, each line walked cube by cube to its first bad sample, so that the body's rim is read
only where the line itself is still free; and the columns the way to the goal cannot pass. Imported
when the map is first asked (it loads Numba); each compiles at its first call in a process, or loads
from the cache folder a service or simulator points Numba at (:mod:`companion.jitcache`).

Every sample is computed with the same float64 operations, in the same order, as NumPy's broadcast of
``start + d * s`` and ``floor(p / voxel) - origin`` would: a line ends at the same cube as it would in
NumPy (a test compares them on random maps).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = dict(cache=bool(nb.config.CACHE_DIR), nogil=True, boundscheck=False)


@nb.njit(**_JIT)
def _cube_at(px: float, py: float, pz: float, voxel: float, origin: np.ndarray, nx: int, ny: int, nz: int) -> int:
    """The flat index of the grid cube that holds the point, or -1 off the grid (or not a number)."""
    # Floored as floats, compared, then made integers: a float-to-integer conversion per axis, not
    # one per axis and back, and a NaN fails every comparison.
    i = np.floor(px / voxel) - origin[0]
    j = np.floor(py / voxel) - origin[1]
    k = np.floor(pz / voxel) - origin[2]
    if not (i >= 0.0 and i < nx and j >= 0.0 and j < ny and k >= 0.0 and k < nz):
        return -1
    return (int(i) * ny + int(j)) * nz + int(k)


@nb.njit(**_JIT)
def _seen_free(c: int, fcnt, evidence_ok, body) -> bool:
    return body[c] or (fcnt[c] > 0 and evidence_ok[c])


@nb.njit(**_JIT)
def _rim_of(d0: float, d1: float, d2: float, radius_m: float, cos_a: np.ndarray, sin_a: np.ndarray, out: np.ndarray) -> None:
    """``out`` float64 ``(R, 3)``: the rim's points round the line of unit NED direction ``d``, as
    offsets from it (m): the first level with it on its side, then round over it. The products and
    sums are NumPy's ``cross`` and ``norm``, in their order."""
    up0, up1, up2 = 0.0, 0.0, -1.0
    s0 = up1 * d2 - up2 * d1
    s1 = up2 * d0 - up0 * d2
    s2 = up0 * d1 - up1 * d0
    n = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    if n > 1e-6:
        s0, s1, s2 = s0 / n, s1 / n, s2 / n
    else:  # a vertical line: any side
        s0, s1, s2 = 0.0, 1.0, 0.0
    o0 = d1 * s2 - d2 * s1
    o1 = d2 * s0 - d0 * s2
    o2 = d0 * s1 - d1 * s0
    for r in range(cos_a.shape[0]):
        out[r, 0] = radius_m * (cos_a[r] * s0 + sin_a[r] * o0)
        out[r, 1] = radius_m * (cos_a[r] * s1 + sin_a[r] * o1)
        out[r, 2] = radius_m * (cos_a[r] * s2 + sin_a[r] * o2)


@nb.njit(**_JIT)
def free_lengths(
    starts: np.ndarray,
    d: np.ndarray,
    s: np.ndarray,
    radius_m: float,
    rim_cos: np.ndarray,
    rim_sin: np.ndarray,
    rim_from_m: float,
    near: np.ndarray,
    voxel: float,
    origin: np.ndarray,
    shape: np.ndarray,
    infl: np.ndarray,
    fcnt: np.ndarray,
    evidence_ok: np.ndarray,
    body: np.ndarray,
    first: np.ndarray,
    blocked: np.ndarray,
) -> None:
    """For each line k of ``d`` (float64 ``(K, 3)`` unit NED) from ``starts[k]`` (float64 ``(K, 3)`` NED m),
    sampled at ``s`` (float64 ``(S,)`` m): ``first[k]`` (int64) the index of its first bad sample (S:
    none) and ``blocked[k]`` (bool) whether that sample is within a surface's radius.

    A sample is bad off the grid, within a surface's radius (``infl`` > 0, or for the first
    ``near.shape[1]`` samples ``near`` bool ``(K, n)`` instead), or not seen free; from ``rim_from_m``
    out, also where a point of the body's rim on the grid is not seen free: R points ``radius_m`` off
    the line, at angles of cosine ``rim_cos`` and sine ``rim_sin`` (float64 ``(R,)``) round it from
    its level side (:func:`_rim_of`). The layers are the map's flat arrays (``infl`` int16, ``fcnt``
    int8, ``evidence_ok`` and ``body`` bool); a cube is seen free where the body is, or where its
    count is positive and its own evidence allows it (``evidence_ok``)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    n_near = near.shape[1]
    rim = np.empty((rim_cos.shape[0], 3))
    for k in range(d.shape[0]):
        _rim_of(d[k, 0], d[k, 1], d[k, 2], radius_m, rim_cos, rim_sin, rim)
        first[k] = s.shape[0]
        blocked[k] = False
        for j in range(s.shape[0]):
            px = starts[k, 0] + d[k, 0] * s[j]
            py = starts[k, 1] + d[k, 1] * s[j]
            pz = starts[k, 2] + d[k, 2] * s[j]
            c = _cube_at(px, py, pz, voxel, origin, nx, ny, nz)
            if c < 0:
                first[k] = j
                break
            inflated = near[k, j] if j < n_near else infl[c] > 0
            if inflated:
                first[k] = j
                blocked[k] = True
                break
            if not _seen_free(c, fcnt, evidence_ok, body):
                first[k] = j
                break
            if s[j] >= rim_from_m:
                rim_ok = True
                for r in range(rim.shape[0]):
                    cr = _cube_at(px + rim[r, 0], py + rim[r, 1], pz + rim[r, 2], voxel, origin, nx, ny, nz)
                    # Off the grid: the line ends there anyway.
                    if cr >= 0 and not _seen_free(cr, fcnt, evidence_ok, body):
                        rim_ok = False
                        break
                if not rim_ok:
                    first[k] = j
                    break


@nb.njit(**_JIT)
def blocked_columns(
    k0: int, lo: int, hi: int, infl: np.ndarray, fcnt: np.ndarray, log_odds: np.ndarray, occupied_log_odds: np.float32, out: np.ndarray
) -> None:
    """``out`` bool ``(nx, ny)``: the columns whose cube at level ``k0`` is inflated (``infl`` int16
    ``(nx, ny, nz)``) and none of whose cubes ``lo`` to ``hi - 1`` is seen free and out of every
    surface's radius (``fcnt`` int8 > 0, ``log_odds`` float32 at most ``occupied_log_odds``, ``infl``
    0)."""
    for i in range(infl.shape[0]):
        for j in range(infl.shape[1]):
            closed = infl[i, j, k0] > 0
            if closed:
                for k in range(lo, hi):
                    if fcnt[i, j, k] > 0 and log_odds[i, j, k] <= occupied_log_odds and infl[i, j, k] == 0:
                        closed = False
                        break
            out[i, j] = closed


@nb.njit(**_JIT)
def swing_clear(
    start: np.ndarray, v0s: np.ndarray, dirs: np.ndarray, speeds: np.ndarray, t: np.ndarray, lag: np.ndarray,
    step_m: float, n_tail: int, arc_limit_m: float, near_m: float, voxel: float, origin: np.ndarray,
    shape: np.ndarray, infl: np.ndarray, occ: np.ndarray, out: np.ndarray,
) -> None:
    """The predicted paths of :func:`~companion.core.planner.paths.predicted_paths` from each velocity of
    ``v0s`` (float64 ``(P, 3)`` NED m/s) toward each command ``dirs · speeds`` (float64 ``(K, 3)``,
    ``(K,)``), judged as :meth:`~companion.core.planner.localmap.LocalMap.clear_along` states, from
    ``start``: ``out`` float64 ``(K,)``, the least over the velocities of the arc length (m) before the
    first sample in a surface's inflation (``infl`` flat > 0; within ``near_m`` of arc, where
    ``near_m >= 0``, on the surfaces alone, ``occ`` flat), inf where none is. ``t``, ``lag`` (float64
    ``(M,)``): the swing's times (s) and its lag factor ``τ(1 - exp(-t/τ))`` (s); then ``n_tail``
    samples ``step_m`` apart on along the command; samples past ``arc_limit_m`` of arc are not
    judged. Each sample is the same float64 operations, in NumPy's order, as ``predicted_paths`` and
    the grid's ``floor(p / voxel) - origin`` (a test compares them with whole-array NumPy)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    m_swing = t.shape[0]
    for k in range(dirs.shape[0]):
        d0, d1, d2 = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        sp = speeds[k]
        vc0, vc1, vc2 = d0 * sp, d1 * sp, d2 * sp
        best = math.inf
        for p in range(v0s.shape[0]):
            dv0, dv1, dv2 = v0s[p, 0] - vc0, v0s[p, 1] - vc1, v0s[p, 2] - vc2
            prev0, prev1, prev2 = 0.0, 0.0, 0.0
            last0, last1, last2 = 0.0, 0.0, 0.0
            arc = 0.0
            before = 0.0
            res = math.inf
            for m in range(m_swing + n_tail):
                if m < m_swing:
                    x0 = vc0 * t[m] + dv0 * lag[m]
                    x1 = vc1 * t[m] + dv1 * lag[m]
                    x2 = vc2 * t[m] + dv2 * lag[m]
                    last0, last1, last2 = x0, x1, x2
                else:
                    s = step_m * float(m - m_swing + 1)
                    x0 = last0 + d0 * s
                    x1 = last1 + d1 * s
                    x2 = last2 + d2 * s
                g0, g1, g2 = x0 - prev0, x1 - prev1, x2 - prev2
                arc = arc + math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
                if not arc <= arc_limit_m:  # past the map's range: the arc only grows
                    break
                c = _cube_at(start[0] + x0, start[1] + x1, start[2] + x2, voxel, origin, nx, ny, nz)
                if c >= 0:
                    hit = occ[c] if (near_m >= 0.0 and arc <= near_m) else infl[c] > 0
                    if hit:
                        res = before
                        break
                before = arc
                prev0, prev1, prev2 = x0, x1, x2
            best = min(best, res)
        out[k] = best
