r"""Exact SAD block matching in NumPy: the oracle the CUDA kernel must equal bit for bit.

Every rule below is integer arithmetic, so two correct implementations agree exactly. Notation: ``L``
and ``R`` are the rectified grey uint8 left and right images, ``(H, W)``; ``b`` is the (odd) block
size and ``r = b // 2``; ``D`` is the number of disparities (the search is ``d`` in ``[0, D)``, ``D >=
2``); ``u`` is ``uniqueness_ratio_pct``; ``t`` is ``texture_threshold_grey``.

1. **Cost.** For every pixel ``(y, x)`` and disparity ``d``::

       C(y, x, d) = sum_{i=-r..r} sum_{j=-r..r} |L(y+i, x+j) - R(y+i, x+j-d)|

   an integer in ``[0, 255 * b * b]``.

2. **Valid area.** ``C`` is evaluated only where the whole window lies inside both images for
   *every* ``d``: rows ``y`` in ``[r, H - r)`` and columns ``x`` in ``[r + D - 1, W - r)``. Every
   other pixel is invalid; there is no border extrapolation. An image too small to hold one such
   pixel (``H < b`` or ``W < b + D - 1``) is entirely invalid.

3. **Winner.** ``d* = argmin_d C(y, x, d)``. Tie-break: among disparities with the same minimum
   cost the **largest** ``d`` wins (the nearer depth: the conservative choice for obstacle
   avoidance).

4. **Uniqueness.** Reject the pixel if some ``d`` with ``|d - d*| > 1`` has
   ``100 * C(d) <= (100 + u) * C(d*)`` (integers, no division). Consequences worth stating:

   * ``u = 0`` still rejects an *exact* tie with a non-adjacent disparity (``C(d) == C(d*)``): two
     equally good, separated matches are ambiguous, and the rule as written says so.
   * A tie with an adjacent disparity (``|d - d*| == 1``) is never rejected (the winner is then the
     larger of the two by rule 3).
   * When ``D <= 3`` there may be no ``d`` with ``|d - d*| > 1``; the test then passes.
   * ``C(d*) == 0`` with another non-adjacent ``C(d) == 0`` is rejected (``0 <= 0``).

5. **Texture.** With ``T(y, x) = sum_{i=-r..r} sum_{j=-r..r} |L(y+i, x+j) - L(y+i, x+j-1)|``
   (left image only), reject the pixel if ``T < t * b * b`` (integer compare; ``t = 0`` never
   rejects). Inside the valid area ``x + j - 1 >= x - r - 1 >= D - 2 >= 0`` because
   ``x >= r + D - 1`` and ``D >= 2``, so ``T`` never reads outside the image.

6. **Output.** ``d*`` as an integer; ``-1`` for invalid (outside the valid area, or rejected by rule
   4 or 5). The rules are independent: a pixel is valid iff it is in the valid area and passes both
   tests. The :class:`ReferenceMatcher` wrapper converts to float32 with NaN for ``-1``.

Implementation: for a band of rows, the absolute differences for all ``D`` shifts are one
``(D, rows, cols)`` uint8 array (shift ``s = D - 1 - d``, so the first minimum along ``s`` is the
largest ``d``, which is the tie-break for free); window sums come from an int32 integral image per
shift. Bands bound memory (about :data:`_BAND_BYTES`) and keep the integral sums far below 2**31.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from companion.core.disparity.base import check_out, check_grey_pair

#: Target size of one band's int32 integral image, bytes (bounds memory; ~20 MB keeps it in L3-ish).
_BAND_BYTES = 24 * 1024 * 1024

INVALID = -1
"""Integer disparity that marks an invalid pixel in :func:`sad_block_match`'s output."""


def valid_area(
    height: int, width: int, num_disparities: int, block_size: int
) -> tuple[slice, slice]:
    """Rows and columns of the pixels that the reference evaluates (rule 2).

    Returns:
        ``(rows, cols)`` slices; empty when the image is too small.
    """
    r = block_size // 2
    y0, y1 = r, max(r, height - r)
    x0, x1 = r + num_disparities - 1, max(r + num_disparities - 1, width - r)
    return slice(y0, y1), slice(x0, x1)


def _check_params(
    num_disparities: int, block_size: int, uniqueness_ratio_pct: int, texture_threshold_grey: int
) -> None:
    if int(num_disparities) != num_disparities or num_disparities < 2:
        raise ValueError(f"num_disparities must be an integer >= 2, got {num_disparities}")
    if int(block_size) != block_size or block_size < 1 or block_size % 2 == 0:
        raise ValueError(f"block_size must be a positive odd integer, got {block_size}")
    if int(uniqueness_ratio_pct) != uniqueness_ratio_pct or uniqueness_ratio_pct < 0:
        raise ValueError(f"uniqueness_ratio_pct must be an integer >= 0, got {uniqueness_ratio_pct}")
    if int(texture_threshold_grey) != texture_threshold_grey or texture_threshold_grey < 0:
        raise ValueError(f"texture_threshold_grey must be an integer >= 0, got {texture_threshold_grey}")


def sad_block_match(
    left: np.ndarray,
    right: np.ndarray,
    num_disparities: int,
    block_size: int,
    uniqueness_ratio_pct: int,
    texture_threshold_grey: int,
    out: np.ndarray | None = None,
    *,
    band_rows: int | None = None,
) -> np.ndarray:
    """Exact SAD block matching (the rules in this module's docstring).

    Args:
        left, right: uint8 ``(H, W)`` rectified grey images.
        num_disparities: ``D >= 2``; disparities searched are ``[0, D)`` px (any integer, not only
            multiples of 16).
        block_size: odd window side ``b >= 1``, px.
        uniqueness_ratio_pct: ``u >= 0``, percent.
        texture_threshold_grey: ``t >= 0``, mean absolute horizontal grey difference.
        out: optional int16 ``(H, W)`` array to write into.
        band_rows: rows of valid output per band (tests use small values to exercise the band
            seams); default: sized from :data:`_BAND_BYTES`.

    Returns:
        int16 ``(H, W)`` integer disparity in px, ``-1`` where invalid.

    Raises:
        FrameError: bad images. ValueError: bad parameters or ``out``.
    """
    h, w = check_grey_pair(left, right)
    _check_params(num_disparities, block_size, uniqueness_ratio_pct, texture_threshold_grey)
    D, b = int(num_disparities), int(block_size)
    r = b // 2
    if out is None:
        out = np.empty((h, w), dtype=np.int16)
    elif out.shape != (h, w) or out.dtype != np.int16:
        raise ValueError(f"out must be an int16 {(h, w)} array, got {out.dtype} {out.shape}")
    out.fill(INVALID)

    hv = h - 2 * r  # valid rows
    wc = w - D + 1  # left columns [D-1, W) that some valid window touches
    wv = wc - 2 * r  # valid columns
    if hv <= 0 or wv <= 0:
        return out

    if band_rows is None:
        band_rows = max(1, _BAND_BYTES // (4 * D * (wc + 1)) - 2 * r - 1)
    band_rows = max(1, min(int(band_rows), hv))

    u = int(uniqueness_ratio_pct)
    tex_min = int(texture_threshold_grey) * b * b
    # Shift s = D-1-d: window s of R starts at column s, so R[:, s:s+wc] pairs with L[:, D-1:W].
    right_shifts = sliding_window_view(right, wc, axis=1)  # (H, D, wc), view
    left_c = left[:, D - 1 :]
    left_g = left[:, D - 2 :]  # one extra column on the left for the texture gradient

    # Band buffers, allocated once for the largest band and sliced for the last one.
    rows_in = band_rows + 2 * r
    diff = np.empty((D, rows_in, wc), dtype=np.uint8)
    tmp = np.empty((D, rows_in, wc), dtype=np.uint8)
    integ = np.zeros((D, rows_in + 1, wc + 1), dtype=np.int32)
    cost = np.empty((D, band_rows, wv), dtype=np.int32)
    g_integ = np.zeros((rows_in + 1, wc + 1), dtype=np.int32)
    grad = np.empty((rows_in, wc), dtype=np.uint8)
    grad_tmp = np.empty((rows_in, wc), dtype=np.uint8)

    for v0 in range(0, hv, band_rows):
        v1 = min(v0 + band_rows, hv)
        nb = v1 - v0
        ni = nb + 2 * r
        lc = left_c[v0 : v0 + ni][None, :, :]
        rs = right_shifts[v0 : v0 + ni].transpose(1, 0, 2)  # (D, ni, wc)
        dv, tv = diff[:, :ni], tmp[:, :ni]
        # |L - R| in uint8 without widening: max - min.
        np.maximum(lc, rs, out=dv)
        np.minimum(lc, rs, out=tv)
        np.subtract(dv, tv, out=dv)
        cost_b = _box_sums(dv, integ[:, : ni + 1], b, cost[:, :nb])

        # Winner: first minimum along s is the largest d (rule 3).
        s_best = np.argmin(cost_b, axis=0)  # (nb, wv) intp
        s_idx = s_best[None]
        c_best = np.take_along_axis(cost_b, s_idx, axis=0)[0].astype(np.int64)

        # Uniqueness (rule 4): the smallest cost over |d - d*| > 1 (s and d differ only in sign).
        sentinel = np.iinfo(np.int32).max
        for off in (-1, 0, 1):
            np.put_along_axis(cost_b, np.clip(s_idx + off, 0, D - 1), sentinel, axis=0)
        c_other = cost_b.min(axis=0).astype(np.int64)
        reject = 100 * c_other <= (100 + u) * c_best

        # Texture (rule 5).
        if tex_min > 0:
            rows = left_g[v0 : v0 + ni]
            g, gt = grad[:ni], grad_tmp[:ni]
            cur, prev = rows[:, 1:], rows[:, :-1]  # |L(y, x) - L(y, x - 1)|, x from D - 1
            np.maximum(cur, prev, out=g)
            np.minimum(cur, prev, out=gt)
            np.subtract(g, gt, out=g)
            tex = _box_sums(g[None], g_integ[None, : ni + 1], b, None)[0]
            reject |= tex < tex_min

        disp = (D - 1 - s_best).astype(np.int16)
        disp[reject] = INVALID
        out[r + v0 : r + v1, r + D - 1 : w - r] = disp
    return out


def _box_sums(a: np.ndarray, integ: np.ndarray, b: int, out: np.ndarray | None) -> np.ndarray:
    """Sums of every b×b window of ``a`` (uint8 ``(n, rows, cols)``) -> int32 ``(n, rows-b+1, cols-b+1)``.

    ``integ`` is an int32 ``(n, rows+1, cols+1)`` scratch whose first row and column are zero. Bands
    keep the integral below 2**31; even if it wrapped, NumPy's int32 arithmetic is modular and every
    box sum (at most 255·b²) fits, so the differences would still be exact.
    """
    inner = integ[:, 1:, 1:]
    np.cumsum(a, axis=1, dtype=np.int32, out=inner)
    np.cumsum(inner, axis=2, dtype=np.int32, out=inner)
    res = np.subtract(integ[:, b:, b:], integ[:, :-b, b:], out=out)
    res -= integ[:, b:, :-b]
    res += integ[:, :-b, :-b]
    return res


class ReferenceMatcher:
    """The exact SAD matcher behind the common matcher contract (slow; the GPU's oracle).

    Args:
        num_disparities: ``D >= 2``.
        block_size: odd window side, px.
        uniqueness_ratio_pct: ``u``, percent.
        texture_threshold_grey: ``t``, grey levels.
    """

    name = "reference"

    def __init__(
        self, num_disparities: int, block_size: int, uniqueness_ratio_pct: int, texture_threshold_grey: int
    ) -> None:
        _check_params(num_disparities, block_size, uniqueness_ratio_pct, texture_threshold_grey)
        self.num_disparities = int(num_disparities)
        self.block_size = int(block_size)
        self.uniqueness_ratio_pct = int(uniqueness_ratio_pct)
        self.texture_threshold_grey = int(texture_threshold_grey)
        self._int_buf: np.ndarray | None = None

    def compute(self, left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 ``(H, W)`` disparity, px, NaN where invalid (see the module rules)."""
        shape = check_grey_pair(left, right)
        out = check_out(out, shape)
        if self._int_buf is None or self._int_buf.shape != shape:
            self._int_buf = np.empty(shape, dtype=np.int16)
        disp = sad_block_match(
            left,
            right,
            self.num_disparities,
            self.block_size,
            self.uniqueness_ratio_pct,
            self.texture_threshold_grey,
            out=self._int_buf,
        )
        np.copyto(out, disp, casting="unsafe")
        np.copyto(out, np.float32(np.nan), where=disp < 0)
        return out
