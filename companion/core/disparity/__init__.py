"""CPU disparity matchers: ``opencv-bm``, ``opencv-sgbm`` and ``reference`` (the GPU's exact oracles:
census + SGM in :mod:`~companion.core.disparity.sgm`, SAD block matching in
:mod:`~companion.core.disparity.reference`; ``stereo.matcher`` picks one).

All follow :class:`~companion.core.disparity.base.DisparityMatcher`: rectified grey uint8 ``(H, W)``
pair in, float32 ``(H, W)`` disparity in pixels out, NaN where invalid (never 0). Build one with
:func:`make_cpu_matcher` once and call ``compute`` per frame.
"""

from __future__ import annotations

from companion.config.core import StereoConfig
from companion.core.disparity.base import DisparityMatcher, check_grey_pair
from companion.core.disparity.opencv import OpenCVBMMatcher, OpenCVSGBMMatcher, set_cv_threads
from companion.core.disparity.reference import INVALID, ReferenceMatcher, sad_block_match, valid_area
from companion.core.disparity.sgm import SgmReferenceMatcher, sgm_match
from companion.errors import BackendError

__all__ = [
    "INVALID",
    "DisparityMatcher",
    "OpenCVBMMatcher",
    "OpenCVSGBMMatcher",
    "ReferenceMatcher",
    "SgmReferenceMatcher",
    "check_grey_pair",
    "make_cpu_matcher",
    "sad_block_match",
    "set_cv_threads",
    "sgm_match",
    "valid_area",
]

CPU_BACKENDS: tuple[str, ...] = ("opencv-bm", "opencv-sgbm", "reference")


def make_cpu_matcher(cfg: StereoConfig) -> DisparityMatcher:
    """Build the CPU matcher that ``cfg.backend`` names (``auto`` -> ``opencv-bm``); for ``reference``,
    the exact matcher that ``cfg.matcher`` names (``sgm`` or ``sad``).

    Sets OpenCV's process-wide thread count from ``cfg.cpu_threads`` (0 = all cores).

    Raises:
        BackendError: ``cupy`` (the GPU backend lives in ``companion.gpu``) or an unknown name.
    """
    backend = cfg.backend
    if backend == "auto":
        backend = "opencv-bm"
    if backend == "cupy":
        raise BackendError(
            "stereo.backend 'cupy' is the GPU backend (companion.gpu), not a CPU matcher; "
            "build it with the GPU backend, or choose opencv-bm, opencv-sgbm or reference",
            backend=backend,
        )
    if backend == "cpu-sgm":
        raise BackendError(
            "stereo.backend 'cpu-sgm' is the compiled engine (companion.cpu, built by companion.backends), "
            "not a matcher of the core; choose opencv-bm, opencv-sgbm or reference here",
            backend=backend,
        )
    if backend == "reference" and cfg.matcher == "sgm":
        return SgmReferenceMatcher(
            cfg.num_disparities,
            p1=cfg.sgm_p1,
            p2=cfg.sgm_p2,
            paths=cfg.sgm_paths,
            uniqueness_ratio_pct=cfg.sgm_uniqueness_ratio_pct,
            lr_max_diff_px=cfg.sgm_lr_max_diff_px,
            median=cfg.sgm_median,
            speckle_window_px=cfg.speckle_window_px,
            speckle_range_px=cfg.speckle_range_px,
        )
    if backend == "reference":
        return ReferenceMatcher(
            cfg.num_disparities, cfg.block_size_px, cfg.uniqueness_ratio_pct, cfg.texture_threshold_grey
        )
    if backend in ("opencv-bm", "opencv-sgbm"):
        set_cv_threads(cfg.cpu_threads)
        return OpenCVBMMatcher(cfg) if backend == "opencv-bm" else OpenCVSGBMMatcher(cfg)
    raise BackendError(
        f"stereo.backend {backend!r} is not a CPU matcher; choose one of {', '.join(CPU_BACKENDS)}",
        backend=backend,
    )
