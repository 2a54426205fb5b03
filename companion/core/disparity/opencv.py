"""OpenCV StereoBM and StereoSGBM behind the common matcher contract.

Both OpenCV matchers return int16 fixed point (disparity × 16) with ``(minDisparity - 1) * 16`` for
invalid pixels. ``minDisparity`` is always 0 here, so every negative value is invalid; the wrappers
turn the result into float32 pixels (``raw / 16``, exact) with NaN for invalid, never 0.

Images too small for one full window over the whole search range (``H <= block_size`` or ``W <
num_disparities + block_size``) give an all-NaN disparity without calling OpenCV, which refuses
(StereoBM) or mis-sizes its buffers (StereoSGBM) on them.

The OpenCV objects are created once per matcher from :class:`~companion.config.core.StereoConfig`;
the int16 result and the invalid mask are preallocated after the first frame and reused.
"""

from __future__ import annotations

from types import MappingProxyType

import cv2
import numpy as np

from companion.config.core import StereoConfig
from companion.core.disparity.base import check_grey_pair, check_out, half_size_disparities
from companion.errors import FrameError

_PREFILTER = MappingProxyType({
    "xsobel": cv2.StereoBM_PREFILTER_XSOBEL,
    "normalized_response": cv2.StereoBM_PREFILTER_NORMALIZED_RESPONSE,
})
_SGBM_MODE = MappingProxyType({
    "sgbm": cv2.StereoSGBM_MODE_SGBM,
    "hh": cv2.StereoSGBM_MODE_HH,
    "sgbm_3way": cv2.StereoSGBM_MODE_SGBM_3WAY,
    "hh4": cv2.StereoSGBM_MODE_HH4,
})
_INV_SCALE = np.float32(1.0 / cv2.StereoMatcher_DISP_SCALE)  # 1/16, exact in float32


def set_cv_threads(cpu_threads: int) -> None:
    """Set OpenCV's (process-wide) worker thread count; ``0`` = all cores.

    OpenCV reads 0 as "no threading" and a negative value as "the default (all cores)", so the
    config's 0 maps to -1.
    """
    cv2.setNumThreads(int(cpu_threads) if cpu_threads > 0 else -1)


class _OpenCVMatcher:
    """Shared conversion: int16 ×16 fixed point -> float32 px with NaN for invalid."""

    name = "opencv"

    def __init__(self, matcher: cv2.StereoMatcher, num_disparities: int, block_size: int) -> None:
        self._matcher = matcher
        self._num_disparities = num_disparities
        self._block_size = block_size
        self._raw: np.ndarray | None = None
        self._invalid: np.ndarray | None = None

    def compute(self, left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 ``(H, W)`` disparity of ``left``, px, NaN where OpenCV rejected the match.

        Args:
            left, right: uint8 ``(H, W)`` rectified grey images.
            out: optional float32 ``(H, W)`` C-contiguous array to write into.
        """
        shape = check_grey_pair(left, right)
        out = check_out(out, shape)
        if self._raw is None or self._raw.shape != shape:
            self._raw = np.empty(shape, dtype=np.int16)
            self._invalid = np.empty(shape, dtype=bool)
        assert self._invalid is not None
        h, w = shape
        if h <= self._block_size or w < self._num_disparities + self._block_size:
            # No pixel can be matched; OpenCV rejects (BM) or mis-sizes buffers (SGBM) on such images.
            out.fill(np.nan)
            return out
        try:
            raw = self._matcher.compute(left, right, self._raw)
        except cv2.error as exc:
            raise FrameError(f"{self.name} failed on a {w}x{h} pair: {str(exc).strip()}") from exc
        if raw is not self._raw:  # OpenCV reallocated (should not happen): keep its result
            self._raw = raw
        np.multiply(raw, _INV_SCALE, out=out)
        np.less(raw, 0, out=self._invalid)
        np.copyto(out, np.float32(np.nan), where=self._invalid)
        return out


def _stereo_bm(cfg: StereoConfig, num_disparities: int, speckle_window_px: int) -> cv2.StereoBM:
    """A StereoBM with ``cfg``'s settings, searching ``num_disparities`` and removing speckles up to
    ``speckle_window_px`` pixels."""
    bm = cv2.StereoBM.create(numDisparities=num_disparities, blockSize=cfg.block_size_px)
    bm.setMinDisparity(0)
    bm.setPreFilterType(_PREFILTER[cfg.bm_prefilter_type])
    bm.setPreFilterSize(cfg.bm_prefilter_size_px)
    bm.setPreFilterCap(cfg.bm_prefilter_cap)
    bm.setUniquenessRatio(cfg.uniqueness_ratio_pct)
    bm.setTextureThreshold(cfg.bm_texture_threshold)
    bm.setSpeckleWindowSize(speckle_window_px)
    bm.setSpeckleRange(cfg.speckle_range_px)
    bm.setDisp12MaxDiff(cfg.disp12_max_diff_px)
    return bm


class OpenCVBMMatcher(_OpenCVMatcher):
    """OpenCV StereoBM (block matching on pre-filtered images; fast).

    Args:
        cfg: stereo config: num_disparities, block_size_px, uniqueness_ratio_pct,
            bm_texture_threshold, bm_prefilter_type/size/cap, speckle_window_px/range_px,
            disp12_max_diff_px, bm_scale_check and its tolerance (the half-size check).
    """

    name = "opencv-bm"

    def __init__(self, cfg: StereoConfig) -> None:
        bm = _stereo_bm(cfg, cfg.num_disparities, cfg.speckle_window_px)
        super().__init__(bm, cfg.num_disparities, cfg.block_size_px)
        self._scale_check = cfg.bm_scale_check
        self._half_disparities = half_size_disparities(cfg.num_disparities)
        # the same settings at half size; a blob's area in pixels shrinks fourfold
        self._half = (
            None if self._scale_check == "off"
            else _stereo_bm(cfg, self._half_disparities, cfg.speckle_window_px // 4)
        )
        # |d - 2 d_half| in OpenCV's 1/16 px units; every buffer below is allocated on the first frame
        self._tol16 = int(round(16 * cfg.bm_scale_check_tolerance_px))
        self._bufs: tuple[np.ndarray, ...] | None = None

    def compute(self, left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 ``(H, W)`` disparity of ``left``, px, NaN where rejected: by StereoBM, and with
        ``bm_scale_check`` by the half-size check (:class:`~companion.config.stereo.StereoConfig`)."""
        out = super().compute(left, right, out)
        if self._half is None or self._raw is None:
            return out
        h, w = left.shape
        hh, wh = h // 2, w // 2
        if hh <= self._block_size or wh < self._half_disparities + self._block_size:
            return out  # too small to match at half size: no check (the full-size result stands)
        if self._bufs is None or self._bufs[0].shape != (hh, wh) or self._bufs[3].shape != (h, w):
            self._bufs = (
                np.empty((hh, wh), np.uint8), np.empty((hh, wh), np.uint8), np.empty((hh, wh), np.int16),
                np.empty((h, w), np.int16), np.empty((h, w), np.int16), np.empty((h, w), bool),
                np.empty((h, w), bool),
            )
        lh, rh, dh, up, diff, reject, half_ok = self._bufs
        cv2.resize(left, (wh, hh), dst=lh, interpolation=cv2.INTER_AREA)
        cv2.resize(right, (wh, hh), dst=rh, interpolation=cv2.INTER_AREA)
        try:
            dh = self._half.compute(lh, rh, dh)
        except cv2.error as exc:
            raise FrameError(f"{self.name} failed on the {wh}x{hh} half-size pair: {str(exc).strip()}") from exc
        cv2.resize(dh, (w, h), dst=up, interpolation=cv2.INTER_NEAREST)
        # |raw - 2 up| fits int16: both are below 16 * 2 * num_disparities
        np.multiply(up, 2, out=diff)
        np.subtract(self._raw, diff, out=diff)
        np.abs(diff, out=diff)
        np.greater(diff, self._tol16, out=reject)
        np.greater_equal(up, 0, out=half_ok)
        if self._scale_check == "agree":  # a missing half-size match rejects too
            np.logical_or(reject, np.logical_not(half_ok, out=half_ok), out=reject)
        else:  # no_conflict: only a half-size match that exists can reject
            np.logical_and(reject, half_ok, out=reject)
        # The half-size matcher's own unmatched left band (wider than the full size's) says nothing:
        # there the full-size result stands, so the check never widens the band the rig check knows.
        reject[:, : min(w, 2 * (self._half_disparities - 1 + self._block_size // 2))] = False
        np.copyto(out, np.float32(np.nan), where=reject)
        return out


class OpenCVSGBMMatcher(_OpenCVMatcher):
    """OpenCV StereoSGBM (semi-global matching; better, slower).

    P1/P2 default to ``8·b²`` and ``32·b²`` (OpenCV's advice for one grey channel). OpenCV needs
    ``P2 > P1``; a configured P1 at or above the default P2 raises P2 to ``P1 + 1`` (the same
    adjustment OpenCV itself makes).

    With ``sgbm_lr_check`` a second matcher runs on the mirrored pair (the right image, flipped, as the
    left): its result, flipped back, is the right view's disparity ``dR``, and a pixel ``x`` with
    disparity ``d`` is rejected unless ``dR`` at ``round(x - d)`` is valid and within
    ``disp12_max_diff_px`` (1 when that is -1) of ``d``, both in OpenCV's 1/16 px units.

    Args:
        cfg: stereo config: num_disparities, block_size_px, uniqueness_ratio_pct, bm_prefilter_cap,
            speckle_window_px/range_px, sgbm_mode, sgbm_p1, sgbm_p2, sgbm_lr_check, disp12_max_diff_px.
    """

    name = "opencv-sgbm"

    def __init__(self, cfg: StereoConfig) -> None:
        b = cfg.block_size_px
        p1 = cfg.sgbm_p1 or 8 * b * b
        p2 = max(cfg.sgbm_p2 or 32 * b * b, p1 + 1)
        sgbm = cv2.StereoSGBM.create(
            minDisparity=0,
            numDisparities=cfg.num_disparities,
            blockSize=b,
            P1=p1,
            P2=p2,
            preFilterCap=cfg.bm_prefilter_cap,
            uniquenessRatio=cfg.uniqueness_ratio_pct,
            speckleWindowSize=cfg.speckle_window_px,
            speckleRange=cfg.speckle_range_px,
            mode=_SGBM_MODE[cfg.sgbm_mode],
        )
        self.p1, self.p2 = p1, p2
        super().__init__(sgbm, cfg.num_disparities, b)
        self._lr_check = bool(cfg.sgbm_lr_check)
        self._lr_max16 = 16 * (cfg.disp12_max_diff_px if cfg.disp12_max_diff_px >= 0 else 1)
        self._raw_r: np.ndarray | None = None

    def compute(self, left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """float32 ``(H, W)`` disparity of ``left``, px, NaN where rejected (see the class doc)."""
        out = super().compute(left, right, out)
        if not self._lr_check or self._raw is None:
            return out
        h, w = left.shape
        if h <= self._block_size or w < self._num_disparities + self._block_size:
            return out
        if self._raw_r is None or self._raw_r.shape != (h, w):
            self._raw_r = np.empty((h, w), dtype=np.int16)
        try:
            raw_r = self._matcher.compute(
                np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), self._raw_r
            )
        except cv2.error as exc:
            raise FrameError(f"{self.name} failed on a {w}x{h} mirrored pair: {str(exc).strip()}") from exc
        d_right = raw_r[:, ::-1].astype(np.int32)  # right view's disparity, 1/16 px, < 0 invalid
        d_left = self._raw.astype(np.int32)
        xs = np.arange(w, dtype=np.int32)[None, :]
        # x - d rounded to the nearest pixel (d in 1/16 px), clipped into the image
        xr = np.clip(xs - ((d_left + 8) >> 4), 0, w - 1)
        back = np.take_along_axis(d_right, xr, axis=1)
        reject = (d_left >= 0) & ((back < 0) | (np.abs(d_left - back) > self._lr_max16))
        np.copyto(out, np.float32(np.nan), where=reject)
        return out
