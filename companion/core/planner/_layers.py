"""Array helpers of the local map's layers (:mod:`companion.core.planner.localmap`): counts over a box
round cubes, kept up cube by cube or rebuilt whole; time-ordered logs of what ages out; the grid's roll.
Pure NumPy."""

from __future__ import annotations

from collections import deque

import numpy as np


def count_box(counts: np.ndarray, cubes: np.ndarray, box: np.ndarray, shape: np.ndarray, delta: int) -> None:
    """Add ``delta`` to ``counts`` (integer 3-D) at every cube of ``box`` (int ``(B, 3)`` offsets)
    round each of ``cubes`` (int64 flat indices, unique) inside the grid of ``shape``."""
    if len(cubes) == 0:
        return
    ny, nz = counts.shape[1], counts.shape[2]
    r = int(np.abs(box).max())
    ijk = np.stack(np.unravel_index(cubes, counts.shape), axis=-1)
    inner = np.all((ijk >= r) & (ijk < shape - r), axis=1)
    # Inside the grid by the box's reach: flat offsets alone; at the edge, each cube of the box checked.
    flat = (cubes[inner][:, None] + ((box[:, 0] * ny + box[:, 1]) * nz + box[:, 2])[None, :]).reshape(-1)
    if not np.all(inner):
        q = (ijk[~inner][:, None, :] + box[None, :, :]).reshape(-1, 3)
        q = q[np.all((q >= 0) & (q < shape), axis=1)]
        flat = np.concatenate([flat, (q[:, 0] * ny + q[:, 1]) * nz + q[:, 2]])
    np.add.at(counts.reshape(-1), flat, counts.dtype.type(delta))


def log_of(flag: np.ndarray, times: np.ndarray) -> deque:
    """The flagged cubes of a rebuilt layer as a log: (time, int64 flat indices) per distinct time
    (``times``, float32 per cube), in time order."""
    idx = np.flatnonzero(flag)
    if len(idx) == 0:
        return deque()
    t = times[idx]
    order = np.argsort(t, kind="stable")
    idx, t = idx[order], t[order]
    cuts = np.flatnonzero(np.diff(t)) + 1
    return deque(zip(t[np.concatenate([[0], cuts])], np.split(idx.astype(np.int32), cuts)))


def box_count(mask: np.ndarray, n: int) -> np.ndarray:
    """int16 grid: the number of True cubes of ``mask`` (bool 3-D) within ``n`` cubes along each axis
    (a cube of side 2n+1; separable sums)."""
    out = mask.astype(np.int16)
    for axis in range(3):
        src = out.copy()
        for k in range(1, n + 1):
            sl_a = [slice(None)] * 3
            sl_b = [slice(None)] * 3
            sl_a[axis], sl_b[axis] = slice(k, None), slice(None, -k)
            out[tuple(sl_a)] += src[tuple(sl_b)]
            out[tuple(sl_b)] += src[tuple(sl_a)]
    return out


def shift_fill(arr: np.ndarray, shift: np.ndarray, fill: float) -> None:
    """Shift ``arr`` in place by integer ``shift`` (3,) cubes, filling what enters with ``fill``."""
    src = arr.copy()
    arr[...] = fill
    dst_sl, src_sl = [], []
    for ax, k in enumerate(int(v) for v in shift):
        n = arr.shape[ax]
        if abs(k) >= n:
            return
        if k >= 0:
            dst_sl.append(slice(k, n))
            src_sl.append(slice(0, n - k))
        else:
            dst_sl.append(slice(0, n + k))
            src_sl.append(slice(-k, n))
    arr[tuple(dst_sl)] = src[tuple(src_sl)]
