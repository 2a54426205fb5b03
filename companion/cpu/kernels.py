r"""The census + SGM rules of :mod:`companion.core.disparity.sgm` as Numba kernels: :func:`match` (the
census, the costs, the paths in two halves side by side, the selection) and :func:`median_to_float`
(rows in parallel).

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

#: Rows whose horizontal paths one thread walks side by side (:func:`_horizontal4`).
ROW_GROUP = 4

_JIT = dict(cache=True, nogil=True, error_model="numpy", boundscheck=False)


@nb.njit(**_JIT)
def _census_row(image, y, out, planes):  # pragma: no cover - compiled
    """Rule 1 for row ``y`` of uint8 ``image`` ``(H, W)``: uint64 ``out`` ``(W,)``; a neighbour
    outside the image gives 0.

    One neighbour offset at a time along the whole row into eight byte planes (bit ``k`` of the
    census is bit ``k % 8`` of plane ``k // 8``), so that the compiler compares 32 columns at once;
    the planes are then joined into the 64-bit censuses. ``planes``: uint8 ``(8, W)`` scratch.
    """
    h, w = image.shape
    centre = image[y]
    planes[:, :] = 0
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
                plane = planes[k >> 3, lo:hi]
                nbr = image[yy, lo + j : hi + j]
                c = centre[lo:hi]
                bit = np.uint8(1 << (k & 7))
                for x in range(hi - lo):
                    plane[x] |= bit if nbr[x] < c[x] else np.uint8(0)
            k += 1
    for x in range(w):
        v = np.uint64(0)
        for b in range(8):
            v |= np.uint64(planes[b, x]) << np.uint64(8 * b)
        out[x] = v


@nb.njit(**_JIT)
def _popcount(v):  # pragma: no cover - compiled
    # the compiler recognises this pattern as a population count and vectorises it
    v = v - ((v >> np.uint64(1)) & np.uint64(0x5555555555555555))
    v = (v & np.uint64(0x3333333333333333)) + ((v >> np.uint64(2)) & np.uint64(0x3333333333333333))
    v = (v + (v >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (v * np.uint64(0x0101010101010101)) >> np.uint64(56)


@nb.njit(**_JIT, inline="always")
def _path(p, c, cx, out, mode, m, nc, first, p1, p2):  # pragma: no cover - compiled
    """One pixel of a path (rule 3) and its share of the sums; returns the new path costs' minimum.

    ``p``: the path costs of the pixel before (int16 ``(D + 2,)``, padded), whose minimum is ``m``
    (unused when ``first``: the path starts here, ``Lr = C``); ``c`` receives this pixel's; ``cx``:
    its uint8 costs; ``nc``: its included disparities. ``mode`` 0: ``out = Lr``; 1: ``out += Lr``
    (uint16 ``(D,)``). One loop with the minimum kept as it goes, inlined:
    the form the compiler vectorises best.
    """
    D = cx.shape[0]
    mn = np.int16(INF)
    if first:
        for d in range(nc):
            v = np.int16(cx[d])
            c[d + 1] = v
            mn = min(mn, v)
            if mode == 0:
                out[d] = np.uint16(v)
            else:
                out[d] += np.uint16(v)
    else:
        mp2 = np.int16(m + p2)
        if mode == 0:
            for d in range(nc):
                v = min(min(p[d + 1], mp2), min(np.int16(p[d] + p1), np.int16(p[d + 2] + p1)))
                v = np.int16(np.int16(cx[d]) + v - m)
                c[d + 1] = v
                mn = min(mn, v)
                out[d] = np.uint16(v)
        else:
            for d in range(nc):
                v = min(min(p[d + 1], mp2), min(np.int16(p[d] + p1), np.int16(p[d + 2] + p1)))
                v = np.int16(np.int16(cx[d]) + v - m)
                c[d + 1] = v
                mn = min(mn, v)
                out[d] += np.uint16(v)
    for d in range(nc, D):
        c[d + 1] = INF
    return mn


@nb.njit(**_JIT, inline="always")
def _horizontal4(cost, sums, w, hbufs, hmins, y0, dy, forward, mode, p1, p2):  # pragma: no cover - compiled
    """The horizontal path of four rows ``y0 + g·dy`` side by side, from the left (``forward``) or the
    right, into their sums (``mode`` as :func:`_path`'s): the rows' steps are independent, so each
    overlaps the others' latency (one row's step waits on its previous pixel's). ``hbufs``: int16
    ``(4, 2, D + 2)``; ``hmins``: int16 ``(4,)`` scratch."""
    D = sums.shape[2]
    for j in range(w):
        x = j if forward else w - 1 - j
        nc = min(x, D - 1) + 1
        for g in range(4):
            y = y0 + g * dy
            hb = hbufs[g]
            hmins[g] = _path(hb[(j + 1) & 1], hb[j & 1], cost[y, x], sums[y, x], mode, hmins[g], nc, j == 0, p1, p2)


@nb.njit(**_JIT)
def _horizontal1(cost, sums, w, hb, y, forward, mode, p1, p2):  # pragma: no cover - compiled
    """:func:`_horizontal4` for one row ``y``; ``hb``: int16 ``(2, D + 2)`` scratch."""
    D = sums.shape[2]
    m = np.int16(0)
    for j in range(w):
        x = j if forward else w - 1 - j
        m = _path(hb[(j + 1) & 1], hb[j & 1], cost[y, x], sums[y, x], mode, m, min(x, D - 1) + 1, j == 0, p1, p2)


@nb.njit(**_JIT)
def _select_row(srow, best, d_bits, u, lr_max_diff, out):  # pragma: no cover - compiled
    """Rules 5-9 for one row: ``srow`` uint16 ``(W, D)`` the sums ``S``, into int16 ``out`` ``(W,)``.

    Each argmin with ties to the largest ``d`` is a plain minimum of the key ``256·S + 255 - d``
    (``S`` < 2^16, ``d`` < 256), which the compiler vectorises; ``key >> 8`` is ``S``. One pass over
    the sums makes every column's left winner and offers each key to its right-image column (rule
    8); a second reads the sub-pixel neighbours and the uniqueness minimum from the sums themselves.
    ``best``: uint32 ``(2, W)`` scratch (each column's left and right winner); ``d_bits``: uint32
    ``255 - d``.
    """
    w = out.shape[0]
    D = srow.shape[1]
    none = np.uint32(0xFFFFFFFF)
    best_left = best[0]
    best_right = best[1]
    check = lr_max_diff >= 0
    if check:
        best_right[:] = none
    for x in range(w):
        sx = srow[x]
        nc = min(x, D - 1) + 1
        b = none
        if check:
            # dR(xr) = argmin_d S(y, xr + d, d): every included (x, d) offers itself to xr = x - d
            br = best_right[x + 1 - nc : x + 1]
            for d in range(nc):
                key = (np.uint32(sx[d]) << np.uint32(8)) | d_bits[d]
                b = min(b, key)
                # an unsigned index: no negative-index check, so the loop vectorises
                j = np.uint64(nc - 1) - np.uint64(d)
                br[j] = min(br[j], key)
        else:
            for d in range(nc):
                b = min(b, (np.uint32(sx[d]) << np.uint32(8)) | d_bits[d])
        best_left[x] = b
    for x in range(w):
        sx = srow[x]
        nc = min(x, D - 1) + 1
        b = best_left[x]
        ds = 255 - np.int64(b & np.uint32(255))
        c1 = np.int64(b >> np.uint32(8))
        if ds >= 1 and ds + 1 < nc:
            c0 = np.int64(sx[ds - 1])
            c2 = np.int64(sx[ds + 1])
            den = c0 + c2 - 2 * c1
            # floor division in float64: exact here (|numerator|, |denominator| < 2^20, so a
            # quotient that is not an integer lies at least 2^-20 from one), and cheaper than idiv
            off = np.int64(np.floor(np.float64(16 * (c0 - c2) + den) / np.float64(2 * den)))
        else:
            off = 0
        v = 16 * ds + off
        # uniqueness: the smallest sum 2 or more away. The winner and its neighbours are taken out
        # by overwriting them (the row's sums are not read again) with 65535, above every sum
        # (at most 8 · 255), which also means "none": one loop over every included disparity
        for d in range(max(ds - 1, 0), min(ds + 2, nc)):
            sx[d] = 65535
        m2 = np.uint16(65535)
        for d in range(nc):
            m2 = min(m2, sx[d])
        reject = m2 != 65535 and 100 * np.int64(m2) <= (100 + u) * c1
        if check:
            d_back = 255 - np.int64(best_right[x - ds] & np.uint32(255))
            if abs(ds - d_back) > lr_max_diff:
                reject = True
        out[x] = -1 if reject else v


@nb.njit(**_JIT)
def _walk(half, left_image, right_image, cost, sums, p1, p2, paths, u, lr_max_diff, out, phase, census, planes,
          scratch_rows, scratch_hmins, scratch_cols, scratch_mins, scratch_right,
          d_bits):  # pragma: no cover - compiled
    """One half of :func:`match` (the same arguments), a plain function that the parallel loop calls."""
    h, w = left_image.shape
    D = sums.shape[2]
    mid = h // 2
    n_col = 1 if paths == 4 else 3
    hbufs = scratch_rows[half]
    hmins = scratch_hmins[half]
    vbufs = scratch_cols[half]
    vmins = scratch_mins[half]
    if phase == 0:
        hbufs[:, :, 0] = INF
        hbufs[:, :, D + 1] = INF
        vbufs[:, :, :, 0] = INF
        vbufs[:, :, :, D + 1] = INF
    # step i of this half's walk: half 0 at row i, half 1 at row h - 1 - i
    if half == 0:
        i0, i1 = (0, mid) if phase == 0 else (mid, h)
    else:
        i0, i1 = (0, h - mid) if phase == 0 else (h - mid, h)
    dy = 1 if half == 0 else -1
    # phase 0 writes the sums of its rows, phase 1 adds the other half's paths to them
    mode = 0 if phase == 0 else 1
    left = census[half, 0]
    right = census[half, 1]
    right_rev = census[half, 2]
    for g0 in range(i0, i1, ROW_GROUP):
        g1 = min(g0 + ROW_GROUP, i1)
        y0 = g0 if half == 0 else h - 1 - g0
        # the rows' costs: computed in phase 0 by the half that reaches the row first, kept for
        # the other half in phase 1
        if phase == 0:
            for i in range(g0, g1):
                y = y0 + dy * (i - g0)
                crow = cost[y]
                _census_row(left_image, y, left, planes[half])
                _census_row(right_image, y, right, planes[half])
                # the right censuses in reverse, so that a column's costs read them forwards (the
                # compiler then vectorises without reversing each vector)
                for k in range(w):
                    right_rev[k] = right[w - 1 - k]
                for x in range(w):
                    a = left[x]
                    cx = crow[x]
                    r = right_rev[w - 1 - x :]  # r[d] is the right census at x - d
                    for d in range(min(x, D - 1) + 1):
                        cx[d] = _popcount(a ^ r[d])
        # horizontal, from the left (half 0) or from the right (half 1), four rows side by side
        if g1 - g0 == ROW_GROUP:
            if mode == 0:
                _horizontal4(cost, sums, w, hbufs, hmins, y0, dy, half == 0, 0, p1, p2)
            else:
                _horizontal4(cost, sums, w, hbufs, hmins, y0, dy, half == 0, 1, p1, p2)
        else:
            for i in range(g0, g1):
                _horizontal1(cost, sums, w, hbufs[0], y0 + dy * (i - g0), half == 0, mode, p1, p2)
        for i in range(g0, g1):
            y = y0 + dy * (i - g0)
            crow = cost[y]
            srow = sums[y]
            # vertical (and diagonal): continue the path of the row before, in walking order
            for k in range(n_col):
                prev = vbufs[k, (i + 1) & 1]
                cur = vbufs[k, i & 1]
                prev_min = vmins[k, (i + 1) & 1]
                cur_min = vmins[k, i & 1]
                dx = 0 if k == 0 else (1 if k == 1 else -1)
                for x in range(w):
                    xp = x - dx
                    first = i == 0 or xp < 0 or xp >= w
                    xq = x if first else xp
                    cur_min[x] = _path(prev[xq], cur[x], crow[x], srow[x], 1, prev_min[xq],
                                       min(x, D - 1) + 1, first, p1, p2)
            if phase == 1:
                _select_row(srow, scratch_right[half], d_bits, u, lr_max_diff, out[y])


@nb.njit(**_JIT, parallel=True)
def match(left_image, right_image, cost, sums, p1, p2, paths, u, lr_max_diff, out, phase, census, planes,
          scratch_rows, scratch_hmins, scratch_cols, scratch_mins, scratch_right,
          d_bits):  # pragma: no cover - compiled
    """Rules 1-9 in two halves that run side by side, in two phases (two calls, ``phase`` 0 then 1).

    Half 0 walks the rows downwards with the paths that come from the left and from above
    (``(1, 0)``, ``(0, 1)``, and with 8 paths ``(1, 1)``, ``(-1, 1)``), half 1 upwards with the
    others. In phase 0 half 0 covers the upper rows ``[0, H // 2)`` and half 1 the lower ``[H // 2, H)``, each
    computing its rows' censuses and costs into ``cost`` and writing its partial sums into ``sums``.
    In phase 1 each continues into the other's rows, adds its paths to the other's partial sums in
    place and, the row's ``S`` now complete, selects its disparities into ``out`` at once; no half
    waits for the other within a phase. Each half walks its horizontal path four rows at a time
    (:func:`_horizontal4`).

    Args:
        left_image, right_image: uint8 ``(H, W)`` rectified grey images.
        cost: uint8 ``(H, W + 1, D)``: rule 2's costs (phase 0 writes them, phase 1 reads them;
            excluded disparities and the last column: undefined; the spare column keeps rows
            from lying a multiple of 4 KiB apart, where the four rows walked side by side would
            share cache sets).
        sums: uint16 ``(H, W + 1, D)``: the sums (excluded disparities and the last column:
            undefined; overwritten by the selection).
        p1, p2: the penalties; paths: 4 or 8; u, lr_max_diff: rules 6 and 9.
        out: int16 ``(H, W)`` disparity × 16, -1 invalid (written in phase 1).
        census, planes: per half: uint64 ``(2, 3, W)`` a row's left and right censuses (and the
            right ones reversed) and uint8
            ``(2, 8, W)`` their byte planes (:func:`_census_row`).
        scratch_*: per half: int16 ``(2, ROW_GROUP, 2, D + 2)`` and ``(2, ROW_GROUP)`` the
            horizontal path's costs at the pixel before and this one in each row of a group, and
            their minima; int16 ``(2, P, 2, W, D + 2)`` and ``(2, P, 2, W)`` the previous and
            current row of the vertical (and, P = 3, the two diagonal) paths and their minima
            (kept from phase 0 to phase 1); uint32 ``(2, 2, W)`` the selection's winners.
            d_bits: uint32 ``(D,)``, ``255 - d``.
    """
    for half in nb.prange(2):
        _walk(half, left_image, right_image, cost, sums, p1, p2, paths, u, lr_max_diff, out, phase, census, planes, scratch_rows, scratch_hmins, scratch_cols, scratch_mins, scratch_right, d_bits)


@nb.njit(**_JIT, parallel=True)
def median_to_float(disp, median, fixed, out, med_buf):  # pragma: no cover - compiled
    """Rule 10 (when ``median``) and the conversion: int16 ``disp`` ``(H, W)`` -> int16 ``fixed``
    (disparity × 16, -1 invalid) and float32 ``out`` pixels, NaN where invalid.

    The lower median of the valid values: the nine neighbours (invalid or outside: 32767, above every
    valid value) sorted by an odd-even transposition network (nine rounds of compare-exchanges, as
    straight-line code the compiler vectorises across columns), then the element ``(n - 1) // 2`` of
    the ``n`` valid ones. ``med_buf``: int16 ``(T, 3, W + 2)`` scratch: three rows padded with 32767.
    """
    h, w = disp.shape
    n_chunks = med_buf.shape[0]
    scale = np.float32(1.0 / 16.0)
    nan = np.float32(np.nan)
    big = np.int16(32767)
    for t in nb.prange(n_chunks):
        rows = med_buf[t]
        for y in range(t * h // n_chunks, (t + 1) * h // n_chunks):
            fr = fixed[y]
            src = disp[y]
            if median:
                for k in range(3):
                    yy = y + k - 1
                    r = rows[k]
                    r[0] = big
                    r[w + 1] = big
                    if 0 <= yy < h:
                        s_row = disp[yy]
                        inner = r[1 : w + 1]
                        for x in range(w):
                            q = s_row[x]
                            inner[x] = q if q >= 0 else big
                    else:
                        r[:] = big
                r0 = rows[0]
                r1 = rows[1]
                r2 = rows[2]
                for x in range(w):
                    v0, v1, v2 = r0[x], r0[x + 1], r0[x + 2]
                    v3, v4, v5 = r1[x], r1[x + 1], r1[x + 2]
                    v6, v7, v8 = r2[x], r2[x + 1], r2[x + 2]
                    n = (
                        np.int16(v0 != big) + np.int16(v1 != big) + np.int16(v2 != big)
                        + np.int16(v3 != big) + np.int16(v4 != big) + np.int16(v5 != big)
                        + np.int16(v6 != big) + np.int16(v7 != big) + np.int16(v8 != big)
                    )
                    v0, v1 = min(v0, v1), max(v0, v1)
                    v2, v3 = min(v2, v3), max(v2, v3)
                    v4, v5 = min(v4, v5), max(v4, v5)
                    v6, v7 = min(v6, v7), max(v6, v7)
                    v1, v2 = min(v1, v2), max(v1, v2)
                    v3, v4 = min(v3, v4), max(v3, v4)
                    v5, v6 = min(v5, v6), max(v5, v6)
                    v7, v8 = min(v7, v8), max(v7, v8)
                    v0, v1 = min(v0, v1), max(v0, v1)
                    v2, v3 = min(v2, v3), max(v2, v3)
                    v4, v5 = min(v4, v5), max(v4, v5)
                    v6, v7 = min(v6, v7), max(v6, v7)
                    v1, v2 = min(v1, v2), max(v1, v2)
                    v3, v4 = min(v3, v4), max(v3, v4)
                    v5, v6 = min(v5, v6), max(v5, v6)
                    v7, v8 = min(v7, v8), max(v7, v8)
                    v0, v1 = min(v0, v1), max(v0, v1)
                    v2, v3 = min(v2, v3), max(v2, v3)
                    v4, v5 = min(v4, v5), max(v4, v5)
                    v6, v7 = min(v6, v7), max(v6, v7)
                    v1, v2 = min(v1, v2), max(v1, v2)
                    v3, v4 = min(v3, v4), max(v3, v4)
                    v5, v6 = min(v5, v6), max(v5, v6)
                    v7, v8 = min(v7, v8), max(v7, v8)
                    v0, v1 = min(v0, v1), max(v0, v1)
                    v2, v3 = min(v2, v3), max(v2, v3)
                    v4, v5 = min(v4, v5), max(v4, v5)
                    v6, v7 = min(v6, v7), max(v6, v7)
                    v1, v2 = min(v1, v2), max(v1, v2)
                    v3, v4 = min(v3, v4), max(v3, v4)
                    v5, v6 = min(v5, v6), max(v5, v6)
                    v7, v8 = min(v7, v8), max(v7, v8)
                    v0, v1 = min(v0, v1), max(v0, v1)
                    v2, v3 = min(v2, v3), max(v2, v3)
                    v4, v5 = min(v4, v5), max(v4, v5)
                    v6, v7 = min(v6, v7), max(v6, v7)
                    k = (n - 1) >> 1  # at most 4
                    m = v0 if k == 0 else (v1 if k == 1 else (v2 if k == 2 else (v3 if k == 3 else v4)))
                    fr[x] = m if src[x] >= 0 else np.int16(-1)
            else:
                for x in range(w):
                    fr[x] = src[x]
            orow = out[y]
            for x in range(w):
                v = fr[x]
                orow[x] = nan if v < 0 else np.float32(v) * scale


@nb.njit(**_JIT, parallel=True)
def shrink_pair(left, right, out, scale, cols_buf):  # pragma: no cover - compiled
    """Rule 11's coarse pair: uint8 ``left``, ``right`` ``(H, W)`` -> uint8 ``out`` ``(2, Hc, Wc)``,
    each coarse pixel the rounded mean of its ``scale × scale`` block. ``out``'s rows are the
    parallel loop's items; each sums its source rows column by column first (a loop the compiler
    vectorises) into its row of ``cols_buf`` (uint16 ``(2·Hc, Wc·scale)`` scratch), then the columns
    in groups."""
    hc, wc = out.shape[1], out.shape[2]
    n = scale * scale
    half = n // 2
    for k in nb.prange(2 * hc):
        eye = 0 if k < hc else 1
        yc = k - eye * hc
        img = left if eye == 0 else right
        dst = out[eye, yc]
        cols = cols_buf[k]
        row = img[yc * scale, : wc * scale]
        for x in range(wc * scale):
            cols[x] = np.uint16(row[x])
        for i in range(1, scale):
            row = img[yc * scale + i, : wc * scale]
            for x in range(wc * scale):
                cols[x] += np.uint16(row[x])
        for xc in range(wc):
            acc = np.int32(half)
            for j in range(scale):
                acc += np.int32(cols[xc * scale + j])
            dst[xc] = np.uint8(acc // n)


@nb.njit(**_JIT, parallel=True)
def near_fill(coarse, scale, num_disparities, fixed, out):  # pragma: no cover - compiled
    """Rule 11's test and fill: where full-size pixel ``(y, x)`` is invalid in int16 ``fixed`` and its
    coarse match (int16 ``(Hc, Wc)`` disparity × 16, -1 invalid; coarse ``(min(y // s, Hc - 1),
    min(x // s, Wc - 1))``) lies beyond ``[0, D)``, ``fixed`` becomes ``16 · (D - 1)`` and float32
    ``out`` ``D - 1`` px. One test
    per coarse pixel and full-size row (the columns it covers are filled together)."""
    h, w = fixed.shape
    hc, wc = coarse.shape
    limit = 16 * num_disparities
    near_v = np.int16(16 * (num_disparities - 1))
    near_px = np.float32(num_disparities - 1)
    for y in nb.prange(h):
        crow = coarse[min(y // scale, hc - 1)]
        frow = fixed[y]
        orow = out[y]
        for xc in range(wc):
            q = np.int32(crow[xc])
            if q >= 0 and scale * q >= limit:
                x1 = w if xc == wc - 1 else (xc + 1) * scale
                for x in range(xc * scale, x1):
                    if frow[x] < 0:
                        frow[x] = near_v
                        orow[x] = near_px
