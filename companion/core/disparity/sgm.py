r"""Exact semi-global matching (census cost, SGM paths) in NumPy: the oracle of the ``cupy`` SGM kernels.

Every rule is integer arithmetic, so the CUDA kernels (``companion/gpu/kernels/sgm.cu``) equal this
module bit for bit or one of them has a bug. Notation: ``L`` and ``R`` are the rectified grey uint8
left and right images ``(H, W)``; ``D`` is the number of disparities (``d`` in ``[0, D)``,
``2 <= D <= 256``); ``P1 < P2`` are the path penalties; ``u`` is the uniqueness ratio in percent.

1. **Census** (9 wide × 7 tall, Zabih & Woodfill). For pixel ``(y, x)`` and the 62 offsets ``(i, j)``,
   ``i`` in ``[-3, 3]`` (rows), ``j`` in ``[-4, 4]`` (columns), ``(0, 0)`` excluded, taken row by row
   (``i`` outer, ``j`` inner), bit ``k`` of the 64-bit census is 1 iff the ``k``-th neighbour lies in
   the image and ``I(y+i, x+j) < I(y, x)``. A neighbour outside the image gives 0.

2. **Cost.** ``C(y, x, d) = popcount(cL(y, x) XOR cR(y, x - d))`` for ``0 <= d <= min(x, D - 1)``
   (the *included* disparities of column ``x``); in ``[0, 62]``. Larger ``d`` would match outside the
   right image: excluded, at every stage below. Every pixel of the image is matched (no border band),
   with the disparities its column allows.

3. **Paths** (Hirschmüller 2008). For each direction ``r = (dx, dy)`` (4 paths: (1, 0), (-1, 0),
   (0, 1), (0, -1); 8 paths: also (1, 1), (-1, 1), (1, -1), (-1, -1)) and each pixel ``p``: if
   ``p - r`` is outside the image, ``Lr(p, d) = C(p, d)`` (the path starts); else, with
   ``m = min_d' Lr(p - r, d')`` over the included ``d'`` of ``p - r``::

       Lr(p, d) = C(p, d) + min(Lr(p-r, d), Lr(p-r, d-1) + P1, Lr(p-r, d+1) + P1, m + P2) - m

   where a term whose disparity is excluded at ``p - r`` (or outside ``[0, D)``) is absent. Every
   ``Lr`` lies in ``[0, 62 + P2]``: with ``P2 <= 193`` it fits one byte (the kernels store it so,
   with 255 for an excluded disparity, which provably never changes a minimum; see
   ``docs/gpu_notes.md``).

4. **Sum.** ``S(p, d) = sum_r Lr(p, d)`` (at most ``8 · 255``).

5. **Winner.** ``d* = argmin_d S(p, d)`` over the included ``d``; among equal sums the **largest**
   ``d`` wins (the nearer depth, the conservative choice, as in the SAD reference).

6. **Uniqueness.** Reject ``p`` if some included ``d`` with ``|d - d*| >= 2`` has
   ``100 · S(d) <= (100 + u) · S(d*)``.

7. **Sub-pixel** (parabola through three sums, fixed point with 4 fractional bits). If ``d* >= 1``
   and ``d* + 1`` is included: ``c0 = S(d* - 1)``, ``c1 = S(d*)``, ``c2 = S(d* + 1)``,
   ``den = c0 + c2 - 2·c1`` (``>= 1``: ``c2 > c1`` by the tie-break, ``c0 >= c1``) and::

       off = floor((16·(c0 - c2) + den) / (2·den))        # in [-8, 8]
       v   = 16·d* + off

   else ``v = 16·d*``. ``v / 16`` is the disparity in pixels (exact in float32).

8. **Right disparity** (from the same sums). For each right-image column ``xr``:
   ``dR(xr) = argmin_d S(y, xr + d, d)`` over ``0 <= d <= min(D - 1, W - 1 - xr)``, ties to the
   largest ``d``.

9. **Left-right check** (when on). Reject ``p = (y, x)`` unless ``|d* - dR(x - d*)| <= lr_max_diff``.

10. **Median** (when on), after rules 6–9: a valid pixel takes the lower median of the valid ``v`` in
    its 3×3 neighbourhood (inside the image), i.e. the element ``(n - 1) // 2`` of their ``n`` sorted
    values; an invalid pixel stays invalid. Then **peak removal** (Hirschmüller 2008, when
    ``N = speckle_window_px > 0``): two valid 4-neighbours are linked when ``|v_p - v_q| <= 16 · R``
    (``R = speckle_range_px``); a pixel whose linked segment (connected component) holds at most ``N``
    pixels becomes invalid, unless it lies at the range's end (``v >= 16 · (D - 1)``). A surface is a
    segment of many pixels; a false match is not. On a plain wall the sensor's noise alone makes the
    census, and the paths turn it into short streaks that pass rules 6–9 at any disparity, about a
    third of the pixels (phantoms), each streak its own small segment; a surface the paths carry across
    a plain area from its edges is one large segment and stays. A match at the range's end says "this
    near or nearer": a surface just beyond the range has its true match outside the search, so its
    matches break up into small segments there, and they are what keeps it near. The segments are
    OpenCV's ``filterSpeckles(v, -1, N, 16 · R)`` exactly.

11. **Near-range check** (always, where the coarse pair below exists). A surface nearer than the rig's
    range (true disparity above ``D - 1``) cannot be matched: rules 1–10 leave much of it invalid and
    match the rest at a wrong, farther disparity inside the range. So the pair is also matched coarsely: both images are shrunk
    :data:`NEAR_SCALE` (``s`` = 4) times, each coarse pixel the rounded mean of its ``s × s`` block,
    ``(sum + s²/2) // s²``, over ``floor(H/s) × floor(W/s)`` pixels, and matched by rules 1–10 (the same
    ``P1``, ``P2``, paths, ``u``, left-right tolerance and median, and the same peak removal, ``N`` and
    ``R``: a false match's streak is the matcher's, as long in coarse pixels as in full-size ones) with
    ``Dc = D // 2`` disparities,
    which reaches ``s · Dc`` (about ``2·D``) full-size pixels, twice the full-size range, at
    ``1 / (s² · 2)`` of its cost. Each full-size pixel ``(y, x)`` reads its coarse pixel
    ``(min(y // s, Hc - 1), min(x // s, Wc - 1))``; where rules 1–10 left the pixel invalid and that
    coarse ``vc`` is valid with ``s · vc >= 16 · D`` (a surface beyond the full-size range), the output
    is ``16 · (D - 1)``: the rig's nearest measurable depth. A valid full-size match (unique and
    left-right consistent) is never overridden: a shrunk regular pattern (bars, a grid) can match a
    wrong repeat beyond the range, and over a surface inside the range the full-size matcher finds it.
    The check is skipped when the coarse pair is smaller than the census window (``Wc < 9`` or
    ``Hc < 7``) or ``Dc < 2``.

Output: int16 ``v`` (disparity × 16), ``-1`` where invalid. :class:`SgmReferenceMatcher` converts to
float32 pixels with NaN for invalid.

The implementation keeps the cost volume ``(H, W, D)`` uint8 and the sums ``(H, W, D)`` uint16 in
memory (about 3 bytes per (pixel, disparity): 0.35 GB at 1280×720×128) and walks each path with one
vectorised step per image column, row or diagonal: a few seconds per HD frame. It is an oracle, not a
matcher for the vehicle.
"""

from __future__ import annotations

import numpy as np

from companion.core.disparity.base import check_grey_pair, check_out

INVALID = -1
"""Value of an invalid pixel in :func:`sgm_match`'s int16 output."""

#: Sub-pixel scale: the int16 output is the disparity times this.
SUBPIXEL_SCALE = 16

#: Census window: 9 columns × 7 rows, 62 comparisons (the centre excluded).
CENSUS_HALF_W = 4
CENSUS_HALF_H = 3
CENSUS_BITS = (2 * CENSUS_HALF_W + 1) * (2 * CENSUS_HALF_H + 1) - 1
#: The largest census cost (Hamming distance of two censuses).
MAX_COST = CENSUS_BITS
#: The largest P2 with every path cost in one byte: 62 + P2 <= 255.
MAX_P2 = 255 - MAX_COST

#: Path directions (dx, dy): the first four make the 4-path set, all eight the 8-path set.
PATH_DIRECTIONS: tuple[tuple[int, int], ...] = (
    (1, 0),
    (-1, 0),
    (0, 1),
    (0, -1),
    (1, 1),
    (-1, 1),
    (1, -1),
    (-1, -1),
)

#: Near-range check (rule 11): the coarse pair is the full-size one shrunk this many times per axis.
NEAR_SCALE = 4
#: Near-range check: the smallest coarse pair it runs on (the census window), width and height.
NEAR_MIN_WIDTH_PX = 2 * CENSUS_HALF_W + 1
NEAR_MIN_HEIGHT_PX = 2 * CENSUS_HALF_H + 1

# "Absent" in path costs (an excluded disparity); larger than any real path cost + P1 + P2.
_INF = 1 << 12
_BAND_ROWS = 64


def check_sgm_params(num_disparities: int, p1: int, p2: int, paths: int, uniqueness_ratio_pct: int,
                     lr_max_diff_px: int) -> None:
    """Raise ValueError naming the first parameter outside what the rules (and the kernels) allow."""
    if int(num_disparities) != num_disparities or not 2 <= num_disparities <= 256:
        raise ValueError(f"num_disparities must be an integer in [2, 256], got {num_disparities}")
    if int(p1) != p1 or int(p2) != p2 or not 0 <= p1 < p2 <= MAX_P2:
        raise ValueError(f"need integers 0 <= P1 < P2 <= {MAX_P2}, got P1={p1}, P2={p2}")
    if paths not in (4, 8):
        raise ValueError(f"paths must be 4 or 8, got {paths}")
    if int(uniqueness_ratio_pct) != uniqueness_ratio_pct or uniqueness_ratio_pct < 0:
        raise ValueError(f"uniqueness_ratio_pct must be an integer >= 0, got {uniqueness_ratio_pct}")
    if int(lr_max_diff_px) != lr_max_diff_px or lr_max_diff_px < -1:
        raise ValueError(f"lr_max_diff_px must be an integer >= -1 (-1 = no check), got {lr_max_diff_px}")


def _popcount64(a: np.ndarray) -> np.ndarray:
    """Bit count of each uint64 as uint8 (NumPy >= 2's bitwise_count, else a byte table)."""
    if hasattr(np, "bitwise_count"):
        return np.bitwise_count(a).astype(np.uint8, copy=False)
    table = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)
    b = np.ascontiguousarray(a).view(np.uint8).reshape(a.shape + (8,))
    return table[b].sum(axis=-1, dtype=np.uint8)


def census_9x7(image: np.ndarray) -> np.ndarray:
    """The 9×7 census transform (rule 1): uint8 ``(H, W)`` -> uint64 ``(H, W)``."""
    h, w = image.shape
    hw, hh = CENSUS_HALF_W, CENSUS_HALF_H
    # 256 never compares below a uint8 centre: the "outside the image gives 0" rule for free.
    padded = np.full((h + 2 * hh, w + 2 * hw), 256, dtype=np.int16)
    padded[hh : hh + h, hw : hw + w] = image
    centre = image.astype(np.int16)
    out = np.zeros((h, w), dtype=np.uint64)
    k = 0
    for i in range(-hh, hh + 1):
        for j in range(-hw, hw + 1):
            if i == 0 and j == 0:
                continue
            nb = padded[hh + i : hh + i + h, hw + j : hw + j + w]
            out |= (nb < centre).astype(np.uint64) << np.uint64(k)
            k += 1
    return out


def census_costs(left: np.ndarray, right: np.ndarray, num_disparities: int) -> np.ndarray:
    """Cost volume (rule 2): uint8 ``(H, W, D)``; 255 marks an excluded disparity (``d > x``)."""
    h, w = left.shape
    D = int(num_disparities)
    cl, cr = census_9x7(left), census_9x7(right)
    cost = np.full((h, w, D), 255, dtype=np.uint8)
    for d in range(min(D, w)):
        cost[:, d:, d] = _popcount64(cl[:, d:] ^ cr[:, : w - d])
    return cost


def _step(prev: np.ndarray, c: np.ndarray, p1: int, p2: int) -> np.ndarray:
    """One path step (rule 3) for a batch of pixels: int16 ``(N, D)`` previous costs (``_INF`` = absent)
    and costs of this pixel (``_INF`` = excluded) -> this pixel's path costs."""
    m = prev.min(axis=1, keepdims=True)
    t = np.minimum(prev, m + p2)
    np.minimum(t[:, 1:], prev[:, :-1] + p1, out=t[:, 1:])
    np.minimum(t[:, :-1], prev[:, 1:] + p1, out=t[:, :-1])
    t -= m
    t += c
    np.minimum(t, _INF, out=t)  # excluded stays _INF; real values are <= 62 + P2
    return t


def _as_step_costs(cost: np.ndarray) -> np.ndarray:
    c = cost.astype(np.int16)
    c[cost == 255] = _INF
    return c


def aggregate_path(cost: np.ndarray, dx: int, dy: int, p1: int, p2: int, out: np.ndarray | None = None) -> np.ndarray:
    """The path costs ``Lr`` of one direction (rule 3): uint8 ``(H, W, D)``, 255 where excluded.

    Args:
        cost: uint8 ``(H, W, D)`` from :func:`census_costs`.
        dx, dy: the direction, each in {-1, 0, 1}, not both 0.
        p1, p2: penalties, ``0 <= P1 < P2 <= 193``.
        out: optional uint8 ``(H, W, D)`` array to write into.
    """
    h, w, D = cost.shape
    if out is None:
        out = np.empty_like(cost)
    if dy == 0:  # horizontal: one step per column, every row at once
        xs = range(w) if dx > 0 else range(w - 1, -1, -1)
        prev = None
        for x in xs:
            c = _as_step_costs(cost[:, x, :])
            cur = c.copy() if prev is None else _step(prev, c, p1, p2)
            out[:, x, :] = np.minimum(cur, 255)
            prev = cur
        return out
    ys = range(h) if dy > 0 else range(h - 1, -1, -1)
    prev = None
    for y in ys:
        c = _as_step_costs(cost[y])
        if prev is None:
            cur = c.copy()
        elif dx == 0:
            cur = _step(prev, c, p1, p2)
        else:
            # pixel x continues the path of x - dx in the previous row; the column where that is
            # outside the image starts a new path (zeros: C + min(0, ...) - 0 = C).
            shifted = np.zeros_like(prev)
            if dx > 0:
                shifted[1:] = prev[:-1]
            else:
                shifted[:-1] = prev[1:]
            cur = _step(shifted, c, p1, p2)
        out[y] = np.minimum(cur, 255)
        prev = cur
    return out


def aggregate(cost: np.ndarray, paths: int, p1: int, p2: int) -> np.ndarray:
    """``S`` (rule 4): uint16 ``(H, W, D)``, the sum of the path costs (excluded entries undefined)."""
    total = np.zeros(cost.shape, dtype=np.uint16)
    scratch = np.empty_like(cost)
    for dx, dy in PATH_DIRECTIONS[:paths]:
        total += aggregate_path(cost, dx, dy, p1, p2, out=scratch)
    return total


def select_disparity(
    sums: np.ndarray,
    uniqueness_ratio_pct: int,
    lr_max_diff_px: int,
) -> np.ndarray:
    """Rules 5–9 on the summed costs: int16 ``(H, W)`` sub-pixel disparity × 16, ``-1`` invalid."""
    h, w, D = sums.shape
    u = int(uniqueness_ratio_pct)
    out = np.empty((h, w), dtype=np.int16)
    xs = np.arange(w)
    included = np.arange(D)[None, :] <= xs[:, None]  # (W, D)
    big = np.int32(1 << 30)
    for y0 in range(0, h, _BAND_ROWS):
        y1 = min(h, y0 + _BAND_ROWS)
        s = sums[y0:y1].astype(np.int32)
        s[:, ~included] = big
        # winner: the first minimum along reversed d is the largest d
        d_star = D - 1 - np.argmin(s[:, :, ::-1], axis=2)
        c1 = np.take_along_axis(s, d_star[..., None], axis=2)[..., 0].astype(np.int64)
        # sub-pixel (before the uniqueness mask overwrites the neighbours)
        dm = np.maximum(d_star - 1, 0)
        dp = np.minimum(d_star + 1, D - 1)
        c0 = np.take_along_axis(s, dm[..., None], axis=2)[..., 0].astype(np.int64)
        c2 = np.take_along_axis(s, dp[..., None], axis=2)[..., 0].astype(np.int64)
        interior = (d_star >= 1) & (d_star + 1 <= np.minimum(xs, D - 1)[None, :])
        den = np.where(interior, c0 + c2 - 2 * c1, 1)
        off = np.where(interior, np.floor_divide(16 * (c0 - c2) + den, 2 * den), 0)
        v = (SUBPIXEL_SCALE * d_star + off).astype(np.int16)
        # uniqueness: the smallest sum at |d - d*| >= 2
        masked = s.copy()
        for k in (-1, 0, 1):
            np.put_along_axis(masked, np.clip(d_star + k, 0, D - 1)[..., None], big, axis=2)
        m2 = masked.min(axis=2).astype(np.int64)
        reject = (m2 < big) & (100 * m2 <= (100 + u) * c1)
        if lr_max_diff_px >= 0:
            # right disparity: dR(xr) = argmin_d S(y, xr + d, d), ties to the largest d
            t = np.full(s.shape, big, dtype=np.int32)
            for d in range(min(D, w)):
                t[:, : w - d, d] = s[:, d:, d]
            d_right = D - 1 - np.argmin(t[:, :, ::-1], axis=2)
            xr = xs[None, :] - d_star
            d_back = np.take_along_axis(d_right, xr, axis=1)
            reject |= np.abs(d_star - d_back) > lr_max_diff_px
        v[reject] = INVALID
        out[y0:y1] = v
    return out


def median3x3_valid(disp: np.ndarray) -> np.ndarray:
    """Rule 10: the lower median of the valid values of each valid pixel's 3×3 neighbourhood."""
    h, w = disp.shape
    big = np.iinfo(np.int16).max
    pad = np.full((h + 2, w + 2), big, dtype=np.int16)
    pad[1:-1, 1:-1] = np.where(disp >= 0, disp, big)
    stack = np.stack([pad[i : i + h, j : j + w] for i in range(3) for j in range(3)], axis=-1)
    n = (stack != big).sum(axis=-1)
    stack.sort(axis=-1)
    med = np.take_along_axis(stack, np.maximum(n - 1, 0)[..., None] // 2, axis=-1)[..., 0]
    return np.where(disp >= 0, med, INVALID).astype(np.int16)


def check_peak_params(speckle_window_px: int, speckle_range_px: int) -> None:
    """Raise ValueError naming the peak-removal parameter outside what rule 10 allows."""
    if int(speckle_window_px) != speckle_window_px or speckle_window_px < 0:
        raise ValueError(f"speckle_window_px must be an integer >= 0 (0 = off), got {speckle_window_px}")
    if int(speckle_range_px) != speckle_range_px or not 0 <= speckle_range_px <= 255:
        raise ValueError(f"speckle_range_px must be an integer in [0, 255], got {speckle_range_px}")


def remove_peaks(disp: np.ndarray, num_disparities: int, speckle_window_px: int, speckle_range_px: int) -> np.ndarray:
    """Rule 10's peak removal: int16 ``(H, W)`` disparity × 16 (``-1`` invalid) -> a new int16 array
    with every pixel of a linked segment of at most ``speckle_window_px`` pixels invalid (0 = a copy),
    but those at the range's end (``v >= 16 · (num_disparities - 1)``).

    The segments are found by propagating the smallest pixel index over the links until nothing
    changes, with pointer jumping (each label is a pixel of the same segment, so reading the label's
    own label skips ahead): a few dozen vectorised passes, an oracle, not an engine.
    """
    out = disp.copy()
    n_max = int(speckle_window_px)
    if n_max <= 0 or out.size == 0:
        return out
    h, w = out.shape
    v = out.astype(np.int32)
    valid = v >= 0
    tol = SUBPIXEL_SCALE * int(speckle_range_px)
    link_x = valid[:, 1:] & valid[:, :-1] & (np.abs(v[:, 1:] - v[:, :-1]) <= tol)  # (y, x) - (y, x + 1)
    link_y = valid[1:] & valid[:-1] & (np.abs(v[1:] - v[:-1]) <= tol)  # (y, x) - (y + 1, x)
    label = np.arange(h * w, dtype=np.int64).reshape(h, w)
    while True:
        new = label.copy()
        np.minimum(new[:, :-1], np.where(link_x, label[:, 1:], new[:, :-1]), out=new[:, :-1])
        np.minimum(new[:, 1:], np.where(link_x, label[:, :-1], new[:, 1:]), out=new[:, 1:])
        np.minimum(new[:-1], np.where(link_y, label[1:], new[:-1]), out=new[:-1])
        np.minimum(new[1:], np.where(link_y, label[:-1], new[1:]), out=new[1:])
        flat = new.reshape(-1)
        flat[:] = flat[flat]
        if np.array_equal(new, label):
            break
        label = new
    size = np.bincount(label[valid], minlength=h * w)
    end = v >= SUBPIXEL_SCALE * (int(num_disparities) - 1)
    out[valid & ~end & (size[label] <= n_max)] = INVALID
    return out


def near_range_shape(height_px: int, width_px: int, num_disparities: int) -> tuple[int, int, int] | None:
    """Rule 11's coarse pair: ``(Hc, Wc, Dc)``, or None where the check is skipped."""
    hc, wc, dc = int(height_px) // NEAR_SCALE, int(width_px) // NEAR_SCALE, int(num_disparities) // 2
    if wc < NEAR_MIN_WIDTH_PX or hc < NEAR_MIN_HEIGHT_PX or dc < 2:
        return None
    return hc, wc, dc


def shrink(image: np.ndarray, scale: int = NEAR_SCALE) -> np.ndarray:
    """Rule 11's coarse image: uint8 ``(H, W)`` -> uint8 ``(H // s, W // s)``, each pixel the rounded
    mean of its ``s × s`` block (``(sum + s²/2) // s²``)."""
    s = int(scale)
    h, w = image.shape[0] // s, image.shape[1] // s
    block = image[: h * s, : w * s].astype(np.int32).reshape(h, s, w, s).sum(axis=(1, 3))
    return ((block + s * s // 2) // (s * s)).astype(np.uint8)


def near_range_mask(coarse: np.ndarray, height_px: int, width_px: int, num_disparities: int) -> np.ndarray:
    """Rule 11's test: bool ``(H, W)``, True where the coarse match (int16 ``(Hc, Wc)`` disparity × 16,
    ``-1`` invalid) finds a surface beyond the full-size range ``[0, D)``."""
    hc, wc = coarse.shape
    ys = np.minimum(np.arange(int(height_px)) // NEAR_SCALE, hc - 1)
    xs = np.minimum(np.arange(int(width_px)) // NEAR_SCALE, wc - 1)
    beyond = NEAR_SCALE * coarse.astype(np.int32) >= SUBPIXEL_SCALE * int(num_disparities)
    return beyond[ys][:, xs]


def near_range_check(
    left: np.ndarray,
    right: np.ndarray,
    disp: np.ndarray,
    num_disparities: int,
    *,
    p1: int,
    p2: int,
    paths: int = 4,
    uniqueness_ratio_pct: int = 10,
    lr_max_diff_px: int = 1,
    median: bool = True,
    speckle_window_px: int = 0,
    speckle_range_px: int = 2,
) -> np.ndarray:
    """Rule 11 on rules 1–10's output ``disp`` (int16 ``(H, W)`` disparity × 16, ``-1`` invalid): a new
    int16 array, ``16 · (D - 1)`` where ``disp`` is invalid and the coarse match finds a surface nearer
    than the range."""
    h, w = disp.shape
    shape = near_range_shape(h, w, num_disparities)
    if shape is None:
        return disp.copy()
    coarse = sgm_match(
        shrink(left), shrink(right), shape[2], p1=p1, p2=p2, paths=paths, uniqueness_ratio_pct=uniqueness_ratio_pct,
        lr_max_diff_px=lr_max_diff_px, median=median, speckle_window_px=speckle_window_px,
        speckle_range_px=speckle_range_px, near_range=False,
    )
    out = disp.copy()
    out[near_range_mask(coarse, h, w, num_disparities) & (disp < 0)] = SUBPIXEL_SCALE * (int(num_disparities) - 1)
    return out


def sgm_match(
    left: np.ndarray,
    right: np.ndarray,
    num_disparities: int,
    *,
    p1: int,
    p2: int,
    paths: int = 4,
    uniqueness_ratio_pct: int = 10,
    lr_max_diff_px: int = 1,
    median: bool = True,
    speckle_window_px: int = 0,
    speckle_range_px: int = 2,
    near_range: bool = True,
) -> np.ndarray:
    """Exact census + SGM matching (the rules in this module's docstring).

    Args:
        left, right: uint8 ``(H, W)`` rectified grey images.
        num_disparities: ``D`` in ``[2, 256]``; disparities searched are ``[0, D)`` px.
        p1, p2: path penalties in census-cost units (bits), ``0 <= P1 < P2 <= 193``.
        paths: 4 or 8.
        uniqueness_ratio_pct: ``u >= 0``, percent (rule 6).
        lr_max_diff_px: largest accepted ``|d* - dR|``, px; ``-1`` = no left-right check.
        median: apply the 3×3 median of rule 10.
        speckle_window_px, speckle_range_px: rule 10's peak removal, ``N`` (0 = off) and ``R`` (px).
        near_range: apply the near-range check of rule 11 (the product always does; off gives rules
            1–10 alone, the kernels' stages).

    Returns:
        int16 ``(H, W)`` disparity × 16 (:data:`SUBPIXEL_SCALE`), ``-1`` where invalid.

    Raises:
        FrameError: bad images. ValueError: bad parameters.
    """
    check_grey_pair(left, right)
    check_sgm_params(num_disparities, p1, p2, paths, uniqueness_ratio_pct, lr_max_diff_px)
    check_peak_params(speckle_window_px, speckle_range_px)
    cost = census_costs(left, right, num_disparities)
    sums = aggregate(cost, paths, p1, p2)
    del cost
    disp = select_disparity(sums, uniqueness_ratio_pct, lr_max_diff_px)
    disp = median3x3_valid(disp) if median else disp
    disp = remove_peaks(disp, num_disparities, speckle_window_px, speckle_range_px)
    if not near_range:
        return disp
    return near_range_check(
        left, right, disp, num_disparities, p1=p1, p2=p2, paths=paths, uniqueness_ratio_pct=uniqueness_ratio_pct,
        lr_max_diff_px=lr_max_diff_px, median=median, speckle_window_px=speckle_window_px,
        speckle_range_px=speckle_range_px,
    )


def fixed_to_float(disp: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """int16 disparity × 16 (``-1`` invalid) -> float32 pixels with NaN for invalid."""
    out = check_out(out, disp.shape)
    np.multiply(disp, np.float32(1.0 / SUBPIXEL_SCALE), out=out, casting="unsafe")
    np.copyto(out, np.float32(np.nan), where=disp < 0)
    return out


class SgmReferenceMatcher:
    """The exact census + SGM matcher behind the common matcher contract (slow; the GPU's oracle).

    Args:
        num_disparities: ``D`` in ``[2, 256]``.
        p1, p2, paths, uniqueness_ratio_pct, lr_max_diff_px, median, speckle_window_px, speckle_range_px:
            see :func:`sgm_match`.
    """

    name = "reference"

    def __init__(
        self,
        num_disparities: int,
        *,
        p1: int,
        p2: int,
        paths: int = 4,
        uniqueness_ratio_pct: int = 10,
        lr_max_diff_px: int = 1,
        median: bool = True,
        speckle_window_px: int = 0,
        speckle_range_px: int = 2,
    ) -> None:
        check_sgm_params(num_disparities, p1, p2, paths, uniqueness_ratio_pct, lr_max_diff_px)
        check_peak_params(speckle_window_px, speckle_range_px)
        self.num_disparities = int(num_disparities)
        self.params = dict(
            p1=int(p1), p2=int(p2), paths=int(paths), uniqueness_ratio_pct=int(uniqueness_ratio_pct),
            lr_max_diff_px=int(lr_max_diff_px), median=bool(median), speckle_window_px=int(speckle_window_px),
            speckle_range_px=int(speckle_range_px),
        )

    def compute_fixed(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """int16 ``(H, W)`` disparity × 16, ``-1`` invalid (the exact output the GPU must equal)."""
        return sgm_match(left, right, self.num_disparities, **self.params)

    def compute(self, left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 ``(H, W)`` disparity, px, NaN where invalid (see the module rules)."""
        return fixed_to_float(self.compute_fixed(left, right), out=out)
