"""The disparity image reduced to blocks: the nearest surface in each ``block_px``-square block.

This is the local planner's map input (``planner.block_px``, :mod:`companion.core.planner.localmap`):
each block's largest valid disparity, the nearest surface on its ray. The GPU estimator computes the
same reduction on the device; :func:`block_max` is the CPU reference it must match. Pure NumPy.
"""

from __future__ import annotations

import numpy as np


class BlockMax:
    """The largest valid disparity of each ``block_px × block_px`` block (the nearest surface in it),
    into buffers allocated once for one image shape.

    With ``erode_px`` = k > 0, each pixel is first eroded along its row (:func:`erode_rows`): a
    foreground edge smeared ``k`` px onto what is behind it (a semi-global matcher's, across a door's
    jamb) and a lone too-near pixel then give no block its depth, while a thin upright thing (a bar
    of a see-through fence, a pole) keeps it.

    Args:
        shape: ``(H, W)`` of the disparity images, pixels.
        block_px: block side, pixels (>= 1).
        erode_px: k, pixels (>= 0).
    """

    def __init__(self, shape: tuple[int, int], block_px: int, erode_px: int = 0) -> None:
        b = int(block_px)
        if b < 1:
            raise ValueError(f"block_px must be >= 1, got {block_px}")
        k = int(erode_px)
        if k < 0:
            raise ValueError(f"erode_px must be >= 0, got {erode_px}")
        h, w = int(shape[0]), int(shape[1])
        self.shape = (h, w)
        self.block_px = b
        self.erode_px = k
        self._erode = RowErosion((h, w), k) if k else None
        self.out_shape = (-(-h // b), -(-w // b))
        oh, ow = self.out_shape
        # Eroded, the kernel reduces straight into the blocks. Plain, partial edge blocks: the image is
        # copied into a NaN-filled buffer of whole blocks; an image of whole blocks (ZED VGA and HD at
        # 4 px) is reduced in place.
        whole = k or (h % b == 0 and w % b == 0)
        self._pad = None if whole else np.full((oh * b, ow * b), np.nan, dtype=np.float32)
        self._cols = np.empty((0 if k else oh * b, ow), dtype=np.float32)
        self._out = np.empty((oh, ow), dtype=np.float32)

    def __call__(self, disparity: np.ndarray) -> np.ndarray:
        """``disparity``: float32 ``(H, W)`` pixels, NaN invalid → float32 ``out_shape``, NaN where a
        block has no valid pixel. The result is a buffer reused by the next call."""
        if disparity.shape != self.shape:
            raise ValueError(f"disparity must be {self.shape}, got {disparity.shape}")
        h, w = self.shape
        b = self.block_px
        src = disparity
        if self._erode is not None:
            return self._erode.block_max(disparity, b, self._out)
        if self._pad is not None:
            np.copyto(self._pad[:h, :w], src, casting="same_kind")
            src = self._pad
        # b strided column slices, then b strided row slices: a few whole-array ufunc calls, far
        # faster than a reduction over a length-b axis.
        cols, out = self._cols, self._out
        np.copyto(cols, src[:, 0::b], casting="same_kind")
        for k in range(1, b):
            np.fmax(cols, src[:, k::b], out=cols)
        np.copyto(out, cols[0::b, :])
        for k in range(1, b):
            np.fmax(out, cols[k::b, :], out=out)
        return out


def block_max(disparity: np.ndarray, block_px: int, erode_px: int = 0) -> np.ndarray:
    """:class:`BlockMax` of one image, as a new float32 ``(ceil(H/b), ceil(W/b))`` array: the CPU
    reference of the GPU estimator's device-side reduction."""
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"disparity must be 2-D, got shape {d.shape}")
    return BlockMax((d.shape[0], d.shape[1]), block_px, erode_px)(d).copy()


def erode_rows(disparity: np.ndarray, erode_px: int) -> np.ndarray:
    """:class:`RowErosion` of one image, as a new float32 ``(H, W)`` array, pixels, NaN invalid (a
    copy of it with ``erode_px`` = 0)."""
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"disparity must be 2-D, got shape {d.shape}")
    if int(erode_px) == 0:
        return d.copy()
    return RowErosion((d.shape[0], d.shape[1]), erode_px)(d).copy()


class RowErosion:
    """A disparity image with its smeared edges taken off and its thin upright things kept, into a
    buffer allocated once for one image shape: the CPU reference of the GPU's ``memory_max``.

    A semi-global matcher smears a near surface's disparity a pixel or two onto what lies behind
    its edge. Each pixel therefore takes the smallest disparity of its row's pixels ``x - k .. x + k``
    inside the image (an invalid one, NaN, the smallest): a wide surface loses ``k`` px at each side,
    and with them the smear. A thing narrower than ``2k + 1`` px would vanish whole, so a pixel
    that stands in front of what is on *both* sides of it keeps its own disparity: some pixel within
    ``2k`` to its left and some within ``2k`` to its right are more than an eighth farther
    (``8·d(neighbour) < 7·d(x)``; an invalid one counts as farther; the image's edge does not). A
    smeared pixel has its surface on one side, so it is still taken off; a slanted wall changes its
    disparity by far less than an eighth over ``2k`` px. Such a thin pixel counts only as far as the
    rows above and below it see something as near within one pixel of its column (the nearest of
    those three pixels in each row; a row outside the image does not count): a bar is tall, a lone
    false match is not. In disparities, for a pixel ``x`` of row ``y``::

        e    = min d[y, x-k .. x+k]
        thin = any(8 d[y, x-2k .. x-1] < 7 d[y, x]) and any(8 d[y, x+1 .. x+2k] < 7 d[y, x])
        s    = min(d[y, x], max d[y-1, x-1 .. x+1], max d[y+1, x-1 .. x+1])
        out  = max(e, s) if thin else e

    Every step is a comparison, a min or a max of the input's values (times 7 or 8 in float32, exact
    for the matchers' fixed-point disparities), so the GPU's integer kernel equals it bit for bit.
    A compiled kernel computes it (``companion.core._blockkernels``); the statement above in NumPy
    is in the tests, which compare the two.

    Args:
        shape: ``(H, W)`` of the disparity images, pixels.
        erode_px: k, pixels (>= 1).
    """

    def __init__(self, shape: tuple[int, int], erode_px: int) -> None:
        k = int(erode_px)
        if k < 1:
            raise ValueError(f"erode_px must be >= 1, got {erode_px}")
        from companion.core import _blockkernels

        self._kernels = _blockkernels
        self.shape, self.erode_px = (int(shape[0]), int(shape[1])), k
        self._scratch = np.empty(self.shape, dtype=np.float32)
        self._rows = np.empty((7, self.shape[1]), dtype=np.float32)
        self._out: np.ndarray | None = None

    def __call__(self, disparity: np.ndarray) -> np.ndarray:
        """``disparity``: float32 ``(H, W)`` pixels, NaN invalid → float32 ``(H, W)`` pixels, NaN
        invalid: a buffer reused by the next call."""
        if disparity.shape != self.shape:
            raise ValueError(f"disparity must be {self.shape}, got {disparity.shape}")
        if self._out is None:
            self._out = np.empty(self.shape, dtype=np.float32)
        self._kernels.erode(np.ascontiguousarray(disparity, dtype=np.float32), self.erode_px, self._scratch,
                            self._rows, self._out)
        return self._out

    def block_max(self, disparity: np.ndarray, block_px: int, out: np.ndarray) -> np.ndarray:
        """:class:`BlockMax` of the eroded ``disparity`` (float32 ``(H, W)`` px, NaN invalid) into
        ``out``, float32 ``(ceil(H/b), ceil(W/b))`` px, NaN where a block has none; no image between."""
        if disparity.shape != self.shape:
            raise ValueError(f"disparity must be {self.shape}, got {disparity.shape}")
        self._kernels.eroded_block_max(np.ascontiguousarray(disparity, dtype=np.float32), self.erode_px,
                                       int(block_px), self._scratch, self._rows, out)
        return out


def compile_kernels() -> None:
    """Compile the erosion's kernels now (about a second, once per process)."""
    erosion = RowErosion((3, 5), 1)
    d = np.arange(15, dtype=np.float32).reshape(3, 5)
    erosion(d)
    erosion.block_max(d, 2, np.empty((2, 3), dtype=np.float32))
