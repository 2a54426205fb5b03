"""Compiled kernels of the map's row erosion (:class:`companion.core.blocks.RowErosion`): row by row,
in whole-row passes of selects that the compiler vectorises (the GPU's ``eroded_px`` computes each
pixel alone; a loop per pixel over its neighbours ran about four times slower here), straight into the
map's blocks. Imported when an erosion is first built (it loads Numba); each compiles at its first
call in a process, or loads from the cache folder a service or simulator points Numba at
(:mod:`companion.jitcache`).

The arithmetic is float32 as in NumPy's statement of the rule (``8·d`` and ``7·d`` rounded to float32),
so the kernels equal it bit for bit on any input (a test compares them on random images)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = dict(cache=bool(nb.config.CACHE_DIR), nogil=True, boundscheck=False)

_SEVEN = np.float32(7.0)
_EIGHT = np.float32(8.0)
_NEG_INF = np.float32(-np.inf)


@nb.njit(**_JIT)
def _sentinel(d, out) -> None:  # pragma: no cover - compiled
    """``out`` = ``d`` with invalid (NaN) as -inf: the smallest in every comparison, as -1 on the device."""
    h, w = d.shape
    for y in range(h):
        for x in range(w):
            v = d[y, x]
            out[y, x] = _NEG_INF if math.isnan(v) else v


@nb.njit(inline="always", **_JIT)
def _row_max3(d, y: int, out) -> None:  # pragma: no cover - compiled
    """``out`` = each pixel's nearest within one column of it in row ``y`` of ``d``."""
    w = d.shape[1]
    row = d[y]
    for x in range(w):
        out[x] = row[x]
    for x in range(1, w):
        v = row[x - 1]
        out[x] = v if v > out[x] else out[x]
    for x in range(w - 1):
        v = row[x + 1]
        out[x] = v if v > out[x] else out[x]


@nb.njit(inline="always", **_JIT)
def _min_of_left(row, j: int, dst) -> None:  # pragma: no cover - compiled
    """``dst[x]`` = the smaller of itself and ``row[x - j]``, where that is in the row."""
    for x in range(j, row.shape[0]):
        v = row[x - j]
        dst[x] = v if v < dst[x] else dst[x]


@nb.njit(inline="always", **_JIT)
def _min_of_right(row, j: int, dst) -> None:  # pragma: no cover - compiled
    """``dst[x]`` = the smaller of itself and ``row[x + j]``, where that is in the row."""
    for x in range(row.shape[0] - j):
        v = row[x + j]
        dst[x] = v if v < dst[x] else dst[x]


@nb.njit(**_JIT)
def _invalid_to_nan(a) -> None:  # pragma: no cover - compiled
    """-inf (invalid) back to NaN in the 2-D ``a``."""
    h, w = a.shape
    for y in range(h):
        for x in range(w):
            if a[y, x] == _NEG_INF:
                a[y, x] = np.float32(np.nan)


@nb.njit(inline="always", **_JIT)
def _eroded_row(d, y: int, k: int, up, down, lo, left, right, out) -> None:  # pragma: no cover - compiled
    """Row ``y`` of the eroded image of ``d`` (-inf invalid) into ``out`` (-inf invalid): the rule of
    RowErosion's docstring, as whole-row passes of selects that the compiler vectorises (a loop per
    pixel over its neighbours ran about four times slower). ``up``, ``down``: the nearest within one column
    (:func:`_row_max3`) of rows ``y - 1`` and ``y + 1`` (not read where outside the image);
    ``lo``, ``left``, ``right``: float32 ``(W,)`` scratch."""
    h, w = d.shape
    row = d[y]
    # lo: the smallest of x - k .. x + k; left, right: of x - 2k .. x - 1 and x + 1 .. x + 2k (+inf where none)
    for x in range(w):
        lo[x] = row[x]
        left[x] = np.float32(np.inf)
        right[x] = np.float32(np.inf)
    for j in range(1, min(2 * k, w - 1) + 1):
        _min_of_left(row, j, left)
        _min_of_right(row, j, right)
        if j <= k:
            _min_of_left(row, j, lo)
            _min_of_right(row, j, lo)
    # 8·min < 7·d0 is "some pixel more than an eighth farther" (8·v is exact, and monotone).
    has_up, has_down = y > 0, y < h - 1
    for x in range(w):
        d0 = row[x]
        near7 = _SEVEN * d0
        thin = (_EIGHT * left[x] < near7) & (_EIGHT * right[x] < near7)
        s = d0
        if has_up:
            s = up[x] if up[x] < s else s
        if has_down:
            s = down[x] if down[x] < s else s
        e = lo[x]
        kept = s if s > e else e
        out[x] = kept if thin else e


@nb.njit(**_JIT)
def erode(d, k: int, scratch, rows, out) -> None:  # pragma: no cover - compiled
    """``d`` float32 ``(H, W)`` px, NaN invalid → ``out`` float32 ``(H, W)`` px, NaN invalid;
    ``scratch``: float32 ``(H, W)``; ``rows``: float32 ``(7, W)``."""
    _sentinel(d, scratch)
    _eroded_rows(scratch, k, rows, out, 0)
    _invalid_to_nan(out)


@nb.njit(**_JIT)
def _eroded_rows(d, k: int, rows, out, b: int) -> None:  # pragma: no cover - compiled
    """Every row of the eroded ``d`` (-inf invalid): into ``out`` (H, W) when ``b`` = 0, else each
    ``b``-square block's largest into ``out`` (ceil(H/b), ceil(W/b)), both -inf invalid."""
    h, w = d.shape
    near = rows[0:3]  # row y's nearest within a column (_row_max3) in near[y % 3], rows y - 1 .. y + 1
    lo, left, right, line = rows[3], rows[4], rows[5], rows[6]
    _row_max3(d, 0, near[0])
    for y in range(h):
        if y + 1 < h:
            _row_max3(d, y + 1, near[(y + 1) % 3])
        dst = out[y] if b == 0 else line
        _eroded_row(d, y, k, near[(y + 2) % 3], near[(y + 1) % 3], lo, left, right, dst)
        if b:
            orow = out[y // b]
            for x in range(w):
                v = line[x]
                ox = x // b
                orow[ox] = v if v > orow[ox] else orow[ox]


@nb.njit(**_JIT)
def eroded_block_max(d, k: int, b: int, scratch, rows, out) -> None:  # pragma: no cover - compiled
    """The largest eroded disparity of each ``b``-square block: ``d`` float32 ``(H, W)`` px, NaN
    invalid → ``out`` float32 ``(ceil(H/b), ceil(W/b))`` px, NaN where none is valid; ``scratch``:
    float32 ``(H, W)``; ``rows``: float32 ``(7, W)``."""
    _sentinel(d, scratch)
    out[:] = _NEG_INF
    _eroded_rows(scratch, k, rows, out, b)
    _invalid_to_nan(out)
