"""Compiled kernels of the way to the goal (:mod:`companion.core.planner.way`): a Dijkstra over a 2D grid
and the walk down its distances. Imported only when a way is first asked for (it loads Numba); each
kernel compiles at its first call in a process, or loads from the cache folder a service or simulator
points Numba at (:mod:`companion.jitcache`).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = dict(cache=bool(nb.config.CACHE_DIR), nogil=True, boundscheck=False)
#: The 8 neighbours of a cell, row and column offsets.
_DI = (-1, -1, -1, 0, 0, 1, 1, 1)
_DJ = (-1, 0, 1, -1, 1, -1, 0, 1)


@nb.njit(**_JIT)
def _push(keys: np.ndarray, cells: np.ndarray, n: int, key: float, cell: int) -> int:
    """Add ``key``, ``cell`` to the binary min-heap of ``n`` entries; returns its new size. The parents
    larger than the key move down into the hole it leaves, and the key is written once, at the end."""
    i = n
    while i > 0:
        p = (i - 1) >> 1
        if keys[p] <= key:
            break
        keys[i] = keys[p]
        cells[i] = cells[p]
        i = p
    keys[i] = key
    cells[i] = cell
    return n + 1


@nb.njit(**_JIT)
def _pop(keys: np.ndarray, cells: np.ndarray, n: int) -> int:
    """Remove the heap's least entry (read ``keys[0]``, ``cells[0]`` before); returns its new size. The
    last entry sinks from the root through the hole, the smaller child moving up each level."""
    n -= 1
    key = keys[n]
    cell = cells[n]
    i = 0
    while True:
        a = 2 * i + 1
        if a >= n:
            break
        b = a + 1
        c = a if (b >= n or keys[a] <= keys[b]) else b
        if key <= keys[c]:
            break
        keys[i] = keys[c]
        cells[i] = cells[c]
        i = c
    keys[i] = key
    cells[i] = cell
    return n


@nb.njit(**_JIT)
def dijkstra(
    blocked: np.ndarray,
    start: np.ndarray,
    cell_m: float,
    penalty: np.ndarray,
    out: np.ndarray,
    keys: np.ndarray,
    cells: np.ndarray,
) -> None:
    """Shortest 8-connected distances (metres) over the cells not ``blocked`` (bool ``(nx, ny)``) from
    sources whose own distance is ``start`` (float64 ``(nx, ny)``, inf: not a source), into ``out``
    (float64 ``(nx, ny)``; inf where unreachable or blocked). A step into a cell counts its length times
    ``1 + penalty`` there (float64 ``(nx, ny)``, >= 0). ``keys`` (float64) and ``cells`` (int64), each
    ``(8·nx·ny + 1,)``, are the heap's scratch: every cell is pushed at most once per neighbour."""
    nx, ny = blocked.shape
    n = 0
    for i in range(nx):
        for j in range(ny):
            out[i, j] = math.inf
            if not blocked[i, j] and start[i, j] < math.inf:
                out[i, j] = start[i, j]
                n = _push(keys, cells, n, start[i, j], i * ny + j)
    diag = cell_m * math.sqrt(2.0)
    while n > 0:
        d = keys[0]
        c = cells[0]
        n = _pop(keys, cells, n)
        i = c // ny
        j = c - i * ny
        if d > out[i, j]:
            continue
        for di in range(-1, 2):
            p = i + di
            if p < 0 or p >= nx:
                continue
            for dj in range(-1, 2):
                q = j + dj
                if (di == 0 and dj == 0) or q < 0 or q >= ny or blocked[p, q]:
                    continue
                nd = d + (diag if (di != 0 and dj != 0) else cell_m) * (1.0 + penalty[p, q])
                if nd < out[p, q] and n < keys.shape[0]:
                    out[p, q] = nd
                    n = _push(keys, cells, n, nd, p * ny + q)


@nb.njit(**_JIT)
def clearance(blocked: np.ndarray, cell_m: float, cap_m: float, out: np.ndarray) -> None:
    """Distance from each cell's centre to the nearest ``blocked`` cell's centre (bool ``(nx, ny)``),
    metres, at most ``cap_m``, into ``out`` (float64 ``(nx, ny)``; 0 on blocked cells): the two-pass
    chamfer transform with steps of ``cell_m`` and ``cell_m·√2`` (within 8 % of the Euclidean)."""
    nx, ny = blocked.shape
    diag = cell_m * math.sqrt(2.0)
    for i in range(nx):
        for j in range(ny):
            out[i, j] = 0.0 if blocked[i, j] else cap_m
    for i in range(nx):
        for j in range(ny):
            d = out[i, j]
            if i > 0:
                d = min(d, out[i - 1, j] + cell_m)
                if j > 0:
                    d = min(d, out[i - 1, j - 1] + diag)
                if j < ny - 1:
                    d = min(d, out[i - 1, j + 1] + diag)
            if j > 0:
                d = min(d, out[i, j - 1] + cell_m)
            out[i, j] = d
    for i in range(nx - 1, -1, -1):
        for j in range(ny - 1, -1, -1):
            d = out[i, j]
            if i < nx - 1:
                d = min(d, out[i + 1, j] + cell_m)
                if j > 0:
                    d = min(d, out[i + 1, j - 1] + diag)
                if j < ny - 1:
                    d = min(d, out[i + 1, j + 1] + diag)
            if j < ny - 1:
                d = min(d, out[i, j + 1] + cell_m)
            out[i, j] = d


@nb.njit(**_JIT)
def pool_all(fine: np.ndarray, pool: int, out: np.ndarray) -> None:
    """Each ``pool × pool`` block of ``fine`` (bool ``(nx·pool, ny·pool)``) into ``out`` (bool
    ``(nx, ny)``): True where all of the block is."""
    nx, ny = out.shape
    for i in range(nx):
        for j in range(ny):
            v = True
            for a in range(pool):
                for b in range(pool):
                    v = v and fine[i * pool + a, j * pool + b]
            out[i, j] = v


@nb.njit(**_JIT)
def pool_penalty(clear: np.ndarray, cell_m: float, clearance_m: float, pool: int, scale: float, out: np.ndarray) -> None:
    """The way's penalty per cell into ``out`` (float64 ``(nx, ny)``): ``scale`` times the mean over its
    ``pool × pool`` columns of ``clip(1 - (clear - cell_m) / clearance_m, 0, 1)``, where ``clear``
    (float64 ``(nx·pool, ny·pool)``, metres) is each column's :func:`clearance` (from its centre: less a
    column, from its edge), so 1 beside a closed column and 0 from ``clearance_m`` out."""
    nx, ny = out.shape
    inv = -1.0 / clearance_m
    for i in range(nx):
        for j in range(ny):
            acc = 0.0
            for a in range(pool):
                row = 0.0  # summed by rows, then the rows: NumPy's order, so the same bits
                for b in range(pool):
                    v = (clear[i * pool + a, j * pool + b] - cell_m) * inv + 1.0
                    row += min(max(v, 0.0), 1.0)
                acc += row
            out[i, j] = scale * (acc / (pool * pool))


@nb.njit(**_JIT)
def farthest_in_view(blocked: np.ndarray, hi: float, hj: float, path: np.ndarray) -> int:
    """Of the cells of a walk (int64 ``(n, 2)``, n >= 1), the last whose centre the straight line from
    ``(hi, hj)`` (cells, continuous) reaches over open cells only (not ``blocked``, bool ``(nx, ny)``):
    the line sampled at ``m`` evenly spaced points, ``m`` one more than twice the longest such line in
    cells (so at most half a cell apart), rounded up; the first sample (the vehicle's own cell) counts
    as open. 0 where none does."""
    nx, ny = blocked.shape
    n = path.shape[0]
    span = 0.0
    for c in range(n):
        di = (path[c, 0] + 0.5) - hi
        dj = (path[c, 1] + 0.5) - hj
        span = max(span, math.sqrt(di * di + dj * dj))
    m = int(math.ceil(span * 2.0)) + 1
    step = 1.0 / (m - 1) if m > 1 else 0.0
    far = 0
    for c in range(n):
        di = (path[c, 0] + 0.5) - hi
        dj = (path[c, 1] + 0.5) - hj
        clear = True
        for s in range(1, m):
            t = 1.0 if s == m - 1 else s * step
            i = min(max(int(math.floor(hi + di * t)), 0), nx - 1)
            j = min(max(int(math.floor(hj + dj * t)), 0), ny - 1)
            if blocked[i, j]:
                clear = False
                break
        if clear:
            far = c
    return far


@nb.njit(**_JIT)
def descend(dist: np.ndarray, i0: int, j0: int, steps: int, path: np.ndarray) -> int:
    """Walk down ``dist`` (float64 ``(nx, ny)``) from cell ``(i0, j0)`` to the least of the 8 neighbours,
    at most ``steps`` times, while it falls; the cells visited into ``path`` (int64 ``(steps, 2)``).
    Returns how many."""
    nx, ny = dist.shape
    i, j = i0, j0
    k = 0
    while k < steps:
        best = dist[i, j]
        bi, bj = -1, -1
        for m in range(8):
            p = i + _DI[m]
            q = j + _DJ[m]
            if 0 <= p < nx and 0 <= q < ny and dist[p, q] < best:
                best = dist[p, q]
                bi, bj = p, q
        if bi < 0:
            break
        i, j = bi, bj
        path[k, 0] = i
        path[k, 1] = j
        k += 1
    return k


@nb.njit(**_JIT)
def bearings(
    dist: np.ndarray,
    blocked: np.ndarray,
    points: np.ndarray,
    cell_m: float,
    origin: np.ndarray,
    path: np.ndarray,
    out: np.ndarray,
) -> None:
    """The way's bearing from each of ``points`` (float64 ``(K, 2)``, north and east m) into ``out``
    (float64 ``(K,)``, radians clockwise from north; NaN where there is none): from the point's cell
    (``cell_m`` m cells, cell (0, 0) at ``origin``, float64 ``(2,)`` cells from the NED origin) or,
    where that one has no way (within a surface's radius), the nearest open one of the 5 × 5 round
    it, :func:`descend` ``dist`` (float64 ``(nx, ny)``) up to ``path``'s length (int64 ``(steps, 2)``
    scratch), and toward the :func:`farthest_in_view` of that walk over ``blocked``."""
    nx, ny = dist.shape
    for k in range(points.shape[0]):
        out[k] = math.nan
        hi = points[k, 0] / cell_m - origin[0]
        hj = points[k, 1] / cell_m - origin[1]
        qi = math.floor(hi)
        qj = math.floor(hj)
        if not (qi >= 0 and qi < nx and qj >= 0 and qj < ny):
            continue
        i0, j0 = int(qi), int(qj)
        if not dist[i0, j0] < math.inf:
            # The first least of the window, in rows then columns (NumPy's argmin order).
            best = math.inf
            bi, bj = -1, -1
            for i in range(max(0, i0 - 2), min(nx, i0 + 3)):
                for j in range(max(0, j0 - 2), min(ny, j0 + 3)):
                    if dist[i, j] < best:
                        best = dist[i, j]
                        bi, bj = i, j
            if bi < 0:
                continue
            i0, j0 = bi, bj
        n = descend(dist, i0, j0, path.shape[0], path)
        if n == 0:
            continue
        far = farthest_in_view(blocked, hi, hj, path[:n])
        out[k] = math.atan2((path[far, 1] + 0.5) - hj, (path[far, 0] + 0.5) - hi)
