"""The disparity backends, in one place: a backend name -> the factory of its region estimator.

The core (:mod:`companion.core`) defines the estimator contract and the CPU implementation and never
imports a backend; the GPU backend (:mod:`companion.gpu`) depends on the core, not the other way round.
This module plugs them together: :data:`BACKENDS` maps each ``stereo.backend`` name to a
:class:`Backend`, :func:`make_estimator` builds the one a config asks for, and :func:`make_pipeline`
builds a :class:`~companion.core.pipeline.Pipeline` that rebuilds its estimator through the same
registry when the config changes, and matches with :func:`cpu_fallback` once a GPU fault has lost the
device. A new backend is one entry here.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

from companion.config import CompanionConfig, concrete_backend
from companion.core.estimator import Clock, CpuRegionEstimator, RegionEstimator
from companion.core.pipeline import Pipeline
from companion.devices import cuda_available, numba_available
from companion.errors import BackendError

__all__ = [
    "BACKENDS", "Backend", "cpu_fallback", "cuda_available", "make_estimator", "make_pipeline", "resolve_backend",
]

log = logging.getLogger(__name__)


def _cpu(cfg: CompanionConfig, width_px: int, height_px: int, clock: Clock) -> RegionEstimator:
    return CpuRegionEstimator(cfg, width_px, height_px, clock=clock)


def _cpu_sgm(cfg: CompanionConfig, width_px: int, height_px: int, clock: Clock) -> RegionEstimator:
    if not numba_available():
        raise BackendError("stereo.backend = 'cpu-sgm' needs Numba (pip install numba); or use 'auto'")
    from companion.cpu import CpuSgmMatcher  # imported only when asked for: it loads Numba

    st = cfg.stereo
    matcher = CpuSgmMatcher(
        width_px, height_px, st.num_disparities, p1=st.sgm_p1, p2=st.sgm_p2, paths=st.sgm_paths,
        uniqueness_ratio_pct=st.sgm_uniqueness_ratio_pct, lr_max_diff_px=st.sgm_lr_max_diff_px,
        median=st.sgm_median, speckle_window_px=st.speckle_window_px, speckle_range_px=st.speckle_range_px,
        threads=st.cpu_threads,
    )
    return CpuRegionEstimator(cfg, width_px, height_px, clock=clock, matcher=matcher)


def _cupy(cfg: CompanionConfig, width_px: int, height_px: int, clock: Clock) -> RegionEstimator:
    if not cuda_available():
        raise BackendError("stereo.backend = 'cupy' but no CUDA device with CuPy is available; use 'auto'")
    from companion.gpu import CupyRegionEstimator  # imported only when asked for: CuPy is optional

    return CupyRegionEstimator(cfg, width_px, height_px, clock=clock)


@dataclass(frozen=True)
class Backend:
    """One ``stereo.backend``.

    Attributes:
        name: the config value.
        factory: builds its estimator: ``factory(cfg, width_px, height_px, clock)``.
        needs_gpu: True when it needs CuPy and a CUDA device.
    """

    name: str
    factory: Callable[[CompanionConfig, int, int, Clock], RegionEstimator]
    needs_gpu: bool = False


#: Every concrete backend by name (``auto`` is resolved by :func:`resolve_backend`, not listed).
BACKENDS: Mapping[str, Backend] = MappingProxyType(
    {
        "opencv-bm": Backend("opencv-bm", _cpu),
        "opencv-sgbm": Backend("opencv-sgbm", _cpu),
        "reference": Backend("reference", _cpu),
        "cupy": Backend("cupy", _cupy, needs_gpu=True),
        "cpu-sgm": Backend("cpu-sgm", _cpu_sgm),
    }
)


def resolve_backend(cfg: CompanionConfig) -> str:
    """The backend ``cfg.stereo.backend`` means on this machine (:func:`~companion.config.concrete_backend`)."""
    return concrete_backend(cfg)


def make_estimator(
    cfg: CompanionConfig, width_px: int, height_px: int, clock: Clock = time.perf_counter
) -> RegionEstimator:
    """Build the estimator the config asks for (``auto``: CuPy when a CUDA device is present).

    Raises:
        BackendError: ``cupy`` requested on a machine without a usable CUDA device.
    """
    name = resolve_backend(cfg)
    if name != cfg.stereo.backend:
        cfg = cfg.model_copy(update={"stereo": cfg.stereo.model_copy(update={"backend": name})})
    return BACKENDS[name].factory(cfg, width_px, height_px, clock)


def cpu_fallback(
    cfg: CompanionConfig, width_px: int, height_px: int, clock: Clock = time.perf_counter
) -> RegionEstimator:
    """The estimator that matches once the GPU is lost to the process: the CPU engine of the same census
    + SGM (``cpu-sgm``), whose disparities are the GPU's bit for bit, so the map and every setting
    resolved for the GPU's dense map still hold; StereoBM where Numba cannot load.

    Raises:
        BackendError: it cannot be built (e.g. the calibration no longer loads).
    """
    name = "cpu-sgm" if numba_available() else "opencv-bm"
    cfg = cfg.model_copy(update={"stereo": cfg.stereo.model_copy(update={"backend": name})})
    return BACKENDS[name].factory(cfg, width_px, height_px, clock)


def make_pipeline(
    cfg: CompanionConfig,
    width_px: int,
    height_px: int,
    estimator: RegionEstimator | None = None,
    clock: Clock = time.perf_counter,
) -> Pipeline:
    """A :class:`~companion.core.pipeline.Pipeline` whose estimator (built now, and again when a config
    change needs a new one) comes from :func:`make_estimator`; ``estimator`` replaces the first one;
    once a GPU fault loses the device, :func:`cpu_fallback` builds them. The config's
    backend-dependent settings were resolved when it was loaded."""
    return Pipeline(
        cfg, width_px, height_px, make_estimator=make_estimator, estimator=estimator, fallback=cpu_fallback,
        clock=clock,
    )
