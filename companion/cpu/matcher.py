""":class:`CpuSgmMatcher`: the census + SGM matcher behind the common matcher contract, on the CPU."""

from __future__ import annotations

import logging

import cv2
import numpy as np

from companion.core.disparity.base import check_grey_pair, check_out
from companion.core.disparity.sgm import (
    NEAR_SCALE, SUBPIXEL_SCALE, check_peak_params, check_sgm_params, near_range_shape,
)
from companion.errors import FrameError
from companion.interrupts import interrupt_after

log = logging.getLogger(__name__)


class CpuSgmMatcher:
    """Census + SGM + left-right check on the CPU, equal to
    :class:`~companion.core.disparity.sgm.SgmReferenceMatcher` bit for bit (how it runs:
    :func:`companion.cpu.kernels.match`; docs/gpu.md).

    Built once per eye size: the kernels compile (or load from the cache) here, and every buffer is
    allocated here (about 3 bytes per pixel and disparity: 49 MB at 672×376×64, and 1/32 of that for
    the near-range check's coarse pair), so :meth:`compute`
    allocates nothing.

    Args:
        width_px, height_px: the rectified image size the matcher is built for.
        num_disparities: ``D`` in ``[2, 256]``.
        p1, p2, paths, uniqueness_ratio_pct, lr_max_diff_px, median, speckle_window_px, speckle_range_px:
            see :func:`~companion.core.disparity.sgm.sgm_match` (the peak removal is OpenCV's
            ``filterSpeckles``, which the reference's rule states).
        threads: worker threads, 0 = all Numba threads (``NUMBA_NUM_THREADS``, by default every
            core); more than Numba has are clamped.
        near_range: the near-range check (the reference's rule 11; the product always has it): a
            second engine of this class matches the pair shrunk 4 times with half the disparities.

    Raises:
        ValueError: a parameter outside the rules.
    """

    name = "cpu-sgm"

    def __init__(
        self,
        width_px: int,
        height_px: int,
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
        threads: int = 0,
        near_range: bool = True,
    ) -> None:
        check_sgm_params(num_disparities, p1, p2, paths, uniqueness_ratio_pct, lr_max_diff_px)
        check_peak_params(speckle_window_px, speckle_range_px)
        if width_px < 1 or height_px < 1:
            raise ValueError(f"image size must be at least 1x1 px, got {width_px}x{height_px}")
        from companion.cpu import load_kernels  # Numba only when the engine is built

        import numba

        self._k = load_kernels()
        self._numba = numba
        available = int(numba.config.NUMBA_NUM_THREADS)
        self.threads = available if threads <= 0 else min(int(threads), available)
        if 0 < threads and threads > available:
            log.info("cpu-sgm: %d threads asked for, Numba has %d (NUMBA_NUM_THREADS)", threads, available)
        self.shape = (int(height_px), int(width_px))
        self.num_disparities = D = int(num_disparities)
        self.p1, self.p2, self.paths = int(p1), int(p2), int(paths)
        self.uniqueness_ratio_pct = int(uniqueness_ratio_pct)
        self.lr_max_diff_px = int(lr_max_diff_px)
        self.median = bool(median)
        self.speckle_window_px = int(speckle_window_px)
        self.speckle_range_px = int(speckle_range_px)
        h, w = self.shape
        # Chunks of rows for the median's parallel loop: a few per thread, so that a slow one is caught up.
        chunks = max(1, min(h, 4 * self.threads))
        self._census = np.empty((2, 3, w), np.uint64)
        self._planes = np.empty((2, 8, w), np.uint8)
        self._sums = np.empty((h, w + 1, D), np.uint16)
        self._cost = np.empty((h, w + 1, D), np.uint8)
        self._scratch = (
            np.empty((2, self._k.ROW_GROUP, 2, D + 2), np.int16),
            np.empty((2, self._k.ROW_GROUP), np.int16),
            np.empty((2, 3 if self.paths == 8 else 1, 2, w, D + 2), np.int16),
            np.empty((2, 3 if self.paths == 8 else 1, 2, w), np.int16),
            np.empty((2, 2, w), np.uint32),
            (255 - np.arange(D)).astype(np.uint32),
        )
        self._med = np.empty((chunks, 3, w + 2), np.int16)
        self._raw = np.empty((h, w), np.int16)
        self._fixed = np.empty((h, w), np.int16)
        self._out = np.empty((h, w), np.float32)
        self._invalid = np.empty((h, w), np.bool_)
        self._pre_peaks = np.empty((h, w), np.int16)
        # filterSpeckles' work buffer, the size it asks for (13 bytes a pixel and 64), so that it is reused
        self._speckle_buf = np.empty((1, h * w * 13 + 64), np.uint8)
        # Rule 11: the coarse pair and the engine that matches it (without a check of its own).
        self._coarse: CpuSgmMatcher | None = None
        coarse = near_range_shape(h, w, D) if near_range else None
        if coarse is not None:
            hc, wc, dc = coarse
            self._shrunk = np.empty((2, hc, wc), np.uint8)
            self._shrink_cols = np.empty((2 * hc, wc * NEAR_SCALE), np.uint16)
            self._coarse = CpuSgmMatcher(
                wc, hc, dc, p1=p1, p2=p2, paths=paths, uniqueness_ratio_pct=uniqueness_ratio_pct,
                lr_max_diff_px=lr_max_diff_px, median=median,
                speckle_window_px=speckle_window_px, speckle_range_px=speckle_range_px,
                threads=self.threads, near_range=False,
            )
        # Compile (or load the cached machine code) now, not on the first frame; a Ctrl-C meanwhile
        # is delivered after (the compiler's callbacks would drop it).
        zeros = np.zeros((h, w), np.uint8)
        with interrupt_after():
            self._run(zeros, zeros, self._out)

    def _run(self, left: np.ndarray, right: np.ndarray, out: np.ndarray) -> None:
        k = self._k
        # Numba's thread count is per calling thread: set it on the thread that matches.
        self._numba.set_num_threads(self.threads)
        for phase in (0, 1):
            k.match(
                left, right, self._cost, self._sums, self.p1, self.p2, self.paths, self.uniqueness_ratio_pct,
                self.lr_max_diff_px, self._raw, phase, self._census, self._planes, *self._scratch,
            )
        k.median_to_float(self._raw, self.median, self._fixed, out, self._med)
        if self.speckle_window_px > 0:  # rule 10's peak removal; a match at the range's end stays
            np.copyto(self._pre_peaks, self._fixed)
            cv2.filterSpeckles(
                self._fixed, -1, self.speckle_window_px, SUBPIXEL_SCALE * self.speckle_range_px, self._speckle_buf
            )
            np.greater_equal(self._pre_peaks, SUBPIXEL_SCALE * (self.num_disparities - 1), out=self._invalid)
            np.copyto(self._fixed, self._pre_peaks, where=self._invalid)
            np.less(self._fixed, 0, out=self._invalid)
            np.copyto(out, np.float32(np.nan), where=self._invalid)
        c = self._coarse
        if c is not None:
            k.shrink_pair(left, right, self._shrunk, NEAR_SCALE, self._shrink_cols)
            c._run(self._shrunk[0], self._shrunk[1], c._out)
            k.near_fill(c._fixed, NEAR_SCALE, self.num_disparities, self._fixed, out)

    def _check(self, left: np.ndarray, right: np.ndarray) -> None:
        shape = check_grey_pair(left, right)
        if shape != self.shape:
            raise FrameError(f"cpu-sgm matcher built for {self.shape[1]}x{self.shape[0]} px, got {shape[1]}x{shape[0]}")

    def compute_fixed(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """int16 ``(H, W)`` disparity × 16, ``-1`` invalid: a new array (the reference's output)."""
        self._check(left, right)
        self._run(np.ascontiguousarray(left), np.ascontiguousarray(right), self._out)
        return self._fixed.copy()

    def compute(self, left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 ``(H, W)`` disparity, px, NaN where invalid (``out`` when given, else a buffer of the
        matcher's, overwritten by the next call)."""
        self._check(left, right)
        if out is not None:
            out = check_out(out, self.shape)
        else:
            out = self._out
        self._run(left if left.flags.c_contiguous else np.ascontiguousarray(left),
                  right if right.flags.c_contiguous else np.ascontiguousarray(right), out)
        return out
