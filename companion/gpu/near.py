"""The near-range check's coarse pair on the GPU (rule 11 of :mod:`companion.core.disparity.sgm`).

The rectified pair, shrunk :data:`~companion.core.disparity.sgm.NEAR_SCALE` times, is matched whole by a
second module of the SGM kernels built for that size and half the disparities; the full size's
``sgm_post`` then reads its disparity to find surfaces nearer than the full size's range.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from companion.config import CompanionConfig
from companion.core.disparity.sgm import near_range_shape
from companion.core.types import N_REGIONS
from companion.gpu.nvrtc import sgm_module
from companion.gpu.plan import SgmPlan, plan_sgm, sgm_pitch_bytes


@dataclass(frozen=True)
class NearPair:
    """The near-range check's coarse pair on the device: its plan and module (the SGM kernels built
    for ``width_px`` × ``height_px``), the shrunk eyes (uint8, ``pitch_bytes`` a row) and the SGM
    buffers; ``disp`` (int16 × 16, -1 invalid) is what the full size's ``sgm_post`` reads; ``peak_labels``
    and ``peak_counts`` (uint32, a pixel each) are rule 10's segments."""

    plan: SgmPlan
    width_px: int
    height_px: int
    pitch_bytes: int
    module: Any
    kernels: dict[str, Any]
    left: Any
    right: Any
    census: Any
    volumes: Any
    winner: Any
    right_keys: Any
    disp: Any
    peak_labels: Any
    peak_counts: Any
    hist: Any
    counter: Any
    result: Any


def build_near_pair(cp: Any, cfg: CompanionConfig, width_px: int, height_px: int, sm_count: int) -> NearPair | None:
    """The near-range check's coarse pair for frames of one eye size ``width_px`` × ``height_px`` (the
    reference's rule 11): a second module of the SGM kernels built for the pair shrunk
    :data:`~companion.core.disparity.sgm.NEAR_SCALE` times with half the disparities, and its buffers
    (1/32 of the full size's); None where the rule skips the check.

    Args:
        cp: the ``cupy`` module.
        cfg: the whole configuration (the stereo and gpu sections are read).
        sm_count: the device's multiprocessors (the SGM plan's prefetch depends on it).
    """
    st = cfg.stereo
    shape = near_range_shape(height_px, width_px, st.num_disparities)
    if shape is None:
        return None
    hc, wc, dc = shape
    rows_e, cols_e = [0, hc // 3, 2 * hc // 3, hc], [0, wc // 3, 2 * wc // 3, wc]
    plan = plan_sgm(wc, hc, dc, st.sgm_paths, rows_e, 0, cfg.gpu.sgm_prefetch_steps, sm_count)
    pitch = sgm_pitch_bytes(wc)
    module = sgm_module(cp, plan, pitch, rows_e, cols_e)
    get = module.get_function
    return NearPair(
        plan=plan,
        width_px=wc,
        height_px=hc,
        pitch_bytes=pitch,
        module=module,
        kernels={name: get(name) for name in ("sgm_census", "sgm_paths", "sgm_wta", "sgm_post", "sgm_peaks_init",
                                              "sgm_peaks_link", "sgm_peaks_count")},
        left=cp.zeros((hc, pitch), dtype=cp.uint8),
        right=cp.zeros((hc, pitch), dtype=cp.uint8),
        census=cp.zeros((3, hc, plan.census_stride_px), dtype=cp.uint64),
        volumes=cp.zeros((plan.paths, hc, wc, plan.dpad), dtype=cp.uint8),
        winner=cp.zeros((hc, wc), dtype=cp.int32),
        right_keys=cp.zeros((hc, wc), dtype=cp.uint32),
        disp=cp.full((hc, wc), -1, dtype=cp.int16),
        peak_labels=cp.zeros(hc * wc, dtype=cp.uint32),
        peak_counts=cp.zeros(hc * wc, dtype=cp.uint32),
        hist=cp.zeros(N_REGIONS * plan.nbins, dtype=cp.uint32),
        counter=cp.zeros(1, dtype=cp.uint32),
        result=cp.zeros(2 * N_REGIONS, dtype=cp.float64),
    )
