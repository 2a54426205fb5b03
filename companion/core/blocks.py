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

    With ``erode_px`` = k > 0, each pixel first takes the smallest disparity of its row's pixels
    ``x - k .. x + k`` inside the image (an invalid one, NaN, is the smallest): a pixel counts only
    where its neighbours see something as near. A lone too-near pixel and a foreground edge smeared
    ``k`` px onto what is behind it (a semi-global matcher's, across a door's jamb) then give no block
    its depth; a true surface loses ``k`` px at each side.

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
        self._eroded = np.empty((h, w), dtype=np.float32) if k else None
        self.out_shape = (-(-h // b), -(-w // b))
        oh, ow = self.out_shape
        # Partial edge blocks: the image is copied into a NaN-filled buffer of whole blocks; an image
        # of whole blocks (ZED VGA and HD at 4 px) is reduced in place.
        self._pad = None if (h % b == 0 and w % b == 0) else np.full((oh * b, ow * b), np.nan, dtype=np.float32)
        self._cols = np.empty((oh * b, ow), dtype=np.float32)
        self._out = np.empty((oh, ow), dtype=np.float32)

    def __call__(self, disparity: np.ndarray) -> np.ndarray:
        """``disparity``: float32 ``(H, W)`` pixels, NaN invalid → float32 ``out_shape``, NaN where a
        block has no valid pixel. The result is a buffer reused by the next call."""
        if disparity.shape != self.shape:
            raise ValueError(f"disparity must be {self.shape}, got {disparity.shape}")
        h, w = self.shape
        b = self.block_px
        src = disparity
        if self._eroded is not None:
            src = erode_rows(disparity, self.erode_px, out=self._eroded)
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


def erode_rows(disparity: np.ndarray, erode_px: int, out: np.ndarray | None = None) -> np.ndarray:
    """Each pixel the smallest of its row's ``x - k .. x + k`` inside the image, NaN (invalid) the
    smallest of all: float32 ``(H, W)`` px, into ``out`` (a new array if None; not ``disparity``)."""
    d = disparity
    if out is None:
        out = np.empty(d.shape, dtype=np.float32)
    np.copyto(out, d, casting="same_kind")
    for j in range(1, int(erode_px) + 1):
        np.minimum(out[:, j:], d[:, :-j], out=out[:, j:])  # np.minimum propagates NaN
        np.minimum(out[:, :-j], d[:, j:], out=out[:, :-j])
    return out
