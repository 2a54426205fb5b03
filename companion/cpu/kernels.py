r"""The census + SGM rules of :mod:`companion.core.disparity.sgm` as Numba kernels (threaded over rows).

Import through :func:`companion.cpu.load_kernels`, which points Numba's on-disk cache at a writable
directory first: the decorators below bind their cache location when this module is imported.
Nothing here compiles at import; each kernel compiles (or loads from the cache) at its first call,
which :class:`companion.cpu.CpuSgmMatcher` makes when it is built.

Every kernel writes into buffers its caller preallocated and allocates nothing. Path costs live in
int16 rows of ``D + 2`` entries: entry ``d + 1`` is disparity ``d``, and entries ``0`` and ``D + 1``
are sentinels at :data:`INF`, so that a path step reads its ``d - 1`` and ``d + 1`` neighbours without
a branch; an excluded disparity (``d > x``) is also :data:`INF`, which is the reference's "absent".
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: "Absent": larger than any path cost + P1 + P2 (as the reference's), small enough for int16 sums.
INF = 1 << 12

_JIT = dict(cache=True, nogil=True, error_model="numpy", boundscheck=False)


@nb.njit(**_JIT, parallel=True)
def census_9x7(image, out, planes):  # pragma: no cover - compiled
    """Rule 1: uint8 ``(H, W)`` -> uint64 ``(H, W)`` into ``out``; a neighbour outside gives 0.

    One neighbour offset at a time along a whole row into eight byte planes (bit ``k`` of the census
    is bit ``k % 8`` of plane ``k // 8``), so that the compiler compares 32 columns at once; the
    planes are then joined into the 64-bit censuses. ``planes``: uint8 ``(T, 8, W)`` scratch, one set
    per chunk of rows.
    """
    h, w = image.shape
    n_chunks = planes.shape[0]
    for t in nb.prange(n_chunks):
        pl = planes[t]
        for y in range(t * h // n_chunks, (t + 1) * h // n_chunks):
            centre = image[y]
            pl[:, :] = 0
            k = 0
            for i in range(-3, 4):
                yy = y + i
                for j in range(-4, 5):
                    if i == 0 and j == 0:
                        continue
                    if 0 <= yy < h:
                        # 0-based loops over views: the compiler vectorises them (no index checks)
                        lo = max(0, -j)
                        hi = min(w, w - j)
                        plane = pl[k >> 3, lo:hi]
                        nbr = image[yy, lo + j : hi + j]
                        c = centre[lo:hi]
                        bit = np.uint8(1 << (k & 7))
                        for x in range(hi - lo):
                            plane[x] |= bit if nbr[x] < c[x] else np.uint8(0)
                    k += 1
            row = out[y]
            for x in range(w):
                v = np.uint64(0)
                for b in range(8):
                    v |= np.uint64(pl[b, x]) << np.uint64(8 * b)
                row[x] = v


@nb.njit(**_JIT)
def _popcount(v):  # pragma: no cover - compiled
    # the compiler recognises this pattern as a population count and vectorises it
    v = v - ((v >> np.uint64(1)) & np.uint64(0x5555555555555555))
    v = (v & np.uint64(0x3333333333333333)) + ((v >> np.uint64(2)) & np.uint64(0x3333333333333333))
    v = (v + (v >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (v * np.uint64(0x0101010101010101)) >> np.uint64(56)


@nb.njit(**_JIT)
def _path(prev, pi, cur, ci, crow, x, srow, add, first, p1, p2):  # pragma: no cover - compiled
    """One pixel of a path (rule 3), added into (``add``) or written to the sums.

    ``prev[pi]`` holds the path costs of the pixel before (padded int16 row of ``D + 2``; unused when
    ``first``: the path starts here, ``Lr = C``); ``cur[ci]`` receives this pixel's; ``crow[x]`` and
    ``srow[x]`` are this pixel's uint8 costs and uint16 sums.
    """
    D = crow.shape[1]
    nc = min(x, D - 1) + 1
    if first:
        for d in range(nc):
            v = np.int16(crow[x, d])
            cur[ci, d + 1] = v
            if add:
                srow[x, d] += np.uint16(v)
            else:
                srow[x, d] = np.uint16(v)
    else:
        m = prev[pi, 1]
        for d in range(2, D + 1):
            m = min(m, prev[pi, d])
        mp2 = np.int16(m + p2)
        for d in range(nc):
            v = min(min(prev[pi, d + 1], mp2), min(np.int16(prev[pi, d] + p1), np.int16(prev[pi, d + 2] + p1)))
            v = np.int16(np.int16(crow[x, d]) + v - m)
            cur[ci, d + 1] = v
            if add:
                srow[x, d] += np.uint16(v)
            else:
                srow[x, d] = np.uint16(v)
    for d in range(nc, D):
        cur[ci, d + 1] = INF


@nb.njit(**_JIT, parallel=True)
def aggregate(cl, cr, sums, p1, p2, paths, cost_buf, row_buf, col_buf):  # pragma: no cover - compiled
    """Rules 2-4 in two halves that run side by side: half 0 walks the rows downwards with the paths
    that come from the left and from above (``(1, 0)``, ``(0, 1)``, and with 8 paths ``(1, 1)``,
    ``(-1, 1)``), half 1 upwards with the others; each writes its own partial sums, so the two never
    wait for each other and the cost volume is never stored (each half computes a row's costs when
    it reaches it).

    Args:
        cl, cr: uint64 ``(H, W)`` censuses of the left and right images.
        sums: uint16 ``(2, H, W, D)``: each half's partial sums ``S``; the entries of excluded
            disparities are undefined.
        p1, p2: the penalties; paths: 4 or 8.
        cost_buf: uint8 ``(2, W, D)`` scratch: each half's cost row.
        row_buf: int16 ``(2, W, D + 2)`` scratch: each half's horizontal path costs along a row.
        col_buf: int16 ``(2, 3, 2, W, D + 2)`` scratch: each half's previous and current row of its
            vertical and two diagonal paths.
    """
    _, h, w, D = sums.shape
    for half in nb.prange(2):
        crow = cost_buf[half]
        hbuf = row_buf[half]
        hbuf[:, 0] = INF
        hbuf[:, D + 1] = INF
        vbufs = col_buf[half]
        vbufs[:, :, :, 0] = INF
        vbufs[:, :, :, D + 1] = INF
        for i in range(h):
            y = i if half == 0 else h - 1 - i
            srow = sums[half, y]
            left = cl[y]
            right = cr[y]
            for x in range(w):
                a = left[x]
                nc = min(x, D - 1) + 1
                cx = crow[x]
                for d in range(nc):
                    cx[d] = _popcount(a ^ right[np.uint64(x) - np.uint64(d)])
            # horizontal: from the left (half 0) or from the right (half 1); sets the sums
            if half == 0:
                for x in range(w):
                    _path(hbuf, x - 1, hbuf, x, crow, x, srow, False, x == 0, p1, p2)
            else:
                for x in range(w - 1, -1, -1):
                    _path(hbuf, x + 1, hbuf, x, crow, x, srow, False, x == w - 1, p1, p2)
            # vertical (and diagonal): continue the path of the row before, in walking order
            n_col = 1 if paths == 4 else 3
            for k in range(n_col):
                prev = vbufs[k, (i + 1) & 1]
                cur = vbufs[k, i & 1]
                dx = 0 if k == 0 else (1 if k == 1 else -1)
                for x in range(w):
                    xp = x - dx
                    first = i == 0 or xp < 0 or xp >= w
                    _path(prev, xp, cur, x, crow, x, srow, True, first, p1, p2)


@nb.njit(**_JIT, parallel=True)
def select_rows(sums, u, lr_max_diff, out, right_buf):  # pragma: no cover - compiled
    """Rules 5-9 on the summed costs (``sums``: uint16 ``(2, H, W, D)``, the two halves of
    :func:`aggregate`, whose sum is ``S``), into int16 ``out`` ``(H, W)`` (disparity × 16, -1
    invalid).

    Each argmin with ties to the largest ``d`` is a plain minimum of the key ``256·S + 255 - d``
    (``S`` < 2^16, ``d`` < 256), which the compiler vectorises. ``right_buf``: int32 ``(T, W)``
    scratch (the right disparities' keys of one row per chunk of rows).
    """
    _, h, w, D = sums.shape
    n_chunks = right_buf.shape[0]
    big = np.int32(1 << 30)
    for t in nb.prange(n_chunks):
        best_right = right_buf[t]
        for y in range(t * h // n_chunks, (t + 1) * h // n_chunks):
            s0 = sums[0, y]
            s1 = sums[1, y]
            if lr_max_diff >= 0:
                # dR(xr) = argmin_d S(y, xr + d, d): every included (x, d) offers itself to xr = x - d
                for xr in range(w):
                    best_right[xr] = big
                for x in range(w):
                    a0 = s0[x]
                    a1 = s1[x]
                    for d in range(min(x, D - 1) + 1):
                        key = ((np.int32(a0[d]) + np.int32(a1[d])) << 8) | np.int32(255 - d)
                        # an unsigned index: no negative-index check, so the loop vectorises
                        j = np.uint64(x) - np.uint64(d)
                        best_right[j] = min(best_right[j], key)
            for x in range(w):
                nc = min(x, D - 1) + 1
                best = big
                for d in range(nc):
                    best = min(best, ((np.int32(s0[x, d]) + np.int32(s1[x, d])) << 8) | np.int32(255 - d))
                ds = 255 - (best & 255)
                c1 = np.int64(best >> 8)
                if ds >= 1 and ds + 1 < nc:
                    c0 = np.int64(s0[x, ds - 1]) + np.int64(s1[x, ds - 1])
                    c2 = np.int64(s0[x, ds + 1]) + np.int64(s1[x, ds + 1])
                    den = c0 + c2 - 2 * c1
                    off = (16 * (c0 - c2) + den) // (2 * den)
                else:
                    off = 0
                v = 16 * ds + off
                m2 = big
                for d in range(0, ds - 1):
                    m2 = min(m2, (np.int32(s0[x, d]) + np.int32(s1[x, d])))
                for d in range(ds + 2, nc):
                    m2 = min(m2, (np.int32(s0[x, d]) + np.int32(s1[x, d])))
                reject = m2 < big and 100 * np.int64(m2) <= (100 + u) * c1
                if lr_max_diff >= 0:
                    d_back = 255 - (best_right[x - ds] & 255)
                    if abs(ds - d_back) > lr_max_diff:
                        reject = True
                out[y, x] = -1 if reject else v


@nb.njit(**_JIT, parallel=True)
def median_to_float(disp, median, fixed, out, med_buf):  # pragma: no cover - compiled
    """Rule 10 (when ``median``) and the conversion: int16 ``disp`` ``(H, W)`` -> int16 ``fixed``
    (disparity × 16, -1 invalid) and float32 ``out`` pixels, NaN where invalid.

    The lower median of the valid values: the nine neighbours (invalid or outside: 32767, above every
    valid value) sorted by a network of compare-exchanges along whole rows, then the element
    ``(n - 1) // 2`` of the ``n`` valid ones. ``med_buf``: int16 ``(T, 9, W)`` scratch.
    """
    h, w = disp.shape
    n_chunks = med_buf.shape[0]
    scale = np.float32(1.0 / 16.0)
    nan = np.float32(np.nan)
    big = np.int16(32767)
    for t in nb.prange(n_chunks):
        v9 = med_buf[t]
        for y in range(t * h // n_chunks, (t + 1) * h // n_chunks):
            if median:
                k = 0
                for i in range(-1, 2):
                    yy = y + i
                    for j in range(-1, 2):
                        r = v9[k]
                        if 0 <= yy < h:
                            src = disp[yy]
                            for x in range(max(0, -j), min(w, w - j)):
                                q = src[x + j]
                                r[x] = q if q >= 0 else big
                            if j < 0:
                                r[0] = big
                            elif j > 0:
                                r[w - 1] = big
                        else:
                            r[:] = big
                        k += 1
                # odd-even transposition sort: 9 rounds of neighbour compare-exchanges
                for rnd in range(9):
                    for a in range(rnd & 1, 8, 2):
                        ra = v9[a]
                        rb = v9[a + 1]
                        for x in range(w):
                            lo = min(ra[x], rb[x])
                            rb[x] = max(ra[x], rb[x])
                            ra[x] = lo
            for x in range(w):
                v = disp[y, x]
                if v < 0:
                    fixed[y, x] = -1
                    out[y, x] = nan
                    continue
                if median:
                    n = 0
                    for k in range(9):
                        n += v9[k, x] != big
                    v = v9[(n - 1) // 2, x]
                fixed[y, x] = v
                out[y, x] = np.float32(v) * scale
