"""The contract every disparity matcher follows, and the input checks they share.

A matcher is built once from :class:`~companion.config.core.StereoConfig` and reused for every frame:

* ``name``: the backend name (``"opencv-bm"``, ``"opencv-sgbm"``, ``"reference"``, ``"cupy"``).
* ``compute(left, right, out=None)``: rectified grey uint8 ``(H, W)`` left and right images ->
  float32 ``(H, W)`` disparity of the *left* image in pixels, ``u_left - u_right`` >= 0, NaN where no
  match was accepted (never 0 for "invalid": 0 is a valid match at infinity). ``out``, when given, is
  a float32 C-contiguous ``(H, W)`` array that receives the result and is returned.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from companion.errors import FrameError


@runtime_checkable
class DisparityMatcher(Protocol):
    """A stereo matcher: rectified grey pair -> float32 disparity (px), NaN = invalid."""

    name: str

    def compute(self, left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Disparity of ``left`` against ``right``.

        Args:
            left, right: uint8 ``(H, W)`` rectified grey images, same shape.
            out: optional float32 ``(H, W)`` C-contiguous array to write into.

        Returns:
            float32 ``(H, W)`` disparity in pixels, NaN where invalid (``out`` when given).
        """
        ...


def half_size_disparities(num_disparities: int) -> int:
    """The search range of StereoBM's half-size check (``stereo.bm_scale_check``): half of
    ``num_disparities``, rounded up to OpenCV's multiple of 16, px at half size."""
    return max(16, -(-int(num_disparities) // 32) * 16)


def check_grey_pair(left: np.ndarray, right: np.ndarray) -> tuple[int, int]:
    """Validate a rectified grey pair and return its ``(H, W)``.

    Raises:
        FrameError: not 2-D uint8, or the two images differ in shape.
    """
    for label, img in (("left", left), ("right", right)):
        if not isinstance(img, np.ndarray) or img.ndim != 2 or img.dtype != np.uint8:
            raise FrameError(
                f"{label} image must be a grey uint8 (H, W) array, got "
                f"{getattr(img, 'dtype', type(img).__name__)} {getattr(img, 'shape', '')}"
            )
    if left.shape != right.shape:
        raise FrameError(f"left {left.shape} and right {right.shape} images differ in shape")
    h, w = left.shape
    return int(h), int(w)


def check_out(out: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Return ``out`` if it is a usable float32 ``shape`` C-contiguous buffer, else a new one.

    Raises:
        ValueError: ``out`` is given but has the wrong shape, dtype or layout.
    """
    if out is None:
        return np.empty(shape, dtype=np.float32)
    if out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(
            f"out must be a C-contiguous float32 {shape} array, got {out.dtype} {out.shape}"
        )
    return out
