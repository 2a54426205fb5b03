"""The row bands of the GPU estimator's per-frame pipeline.

A frame goes to the device in bands of rows so that the host copy and the DMA of band k+1 overlap the
GPU work of band k. Each band carries the work that needs only the rows uploaded by its end: the grey
conversion of its rows, the rectified rows whose bilinear taps are uploaded, and the disparity rows
(SAD) or census rows (SGM) whose windows are rectified. Pure Python and NumPy: a plan can be computed
and checked without a GPU.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.config.gpu import GpuConfig
from companion.gpu.plan import SGM_CENSUS_HALF_HEIGHT, DisparityPlan


@dataclass(frozen=True)
class Band:
    """One row band of the per-frame pipeline (half-open row ranges, px).

    Attributes:
        src: source rows uploaded (and converted to grey) with this band.
        rect: rectified rows computed with this band (equal to ``src`` for an ideal rig).
        out: disparity output rows matched with this band.
        census: SGM: the census rows computed with this band (their rows ±3 are rectified by then).
        rows_per_block, grid: the disparity launch of this band.
    """

    src: tuple[int, int]
    rect: tuple[int, int]
    out: tuple[int, int]
    census: tuple[int, int]
    rows_per_block: int
    grid: tuple[int, int, int]


def plan_bands(
    plan: DisparityPlan,
    sgm: bool,
    height_px: int,
    rectifier: Any,
    gpu: GpuConfig,
    sm_count: int,
    blocks_per_sm: int,
) -> list[Band]:
    """Split the frame into row bands whose GPU work needs only the rows uploaded so far.

    Disparity band k covers output rows ``[o_k, o_k+1)``; its windows read rectified rows up to
    ``o_k+1 + r``; those read source rows up to the largest ``floor(map_y) + 2`` among them (the
    two bilinear taps), or the same rows for an ideal rig. The upload of band k is the source rows
    from the previous band's end to that row.

    Args:
        plan: the SAD kernel's shape (with the SGM matcher it still fixes the disparity launch).
        sgm: the SGM matcher (its kernels need the whole pair: the bands only overlap the upload with
            grey, rectification and census).
        height_px: one eye's height, px.
        rectifier: the rig's rectifier (its ``is_identity`` and, unless identity, its float32 maps).
        gpu: the ``[gpu]`` options (``pipeline_bands``, ``stage_timing``, ``rows_per_block``).
        sm_count, blocks_per_sm: the device's multiprocessors and the disparity kernel's blocks on each.
    """
    p, h = plan, height_px
    k_bands = gpu.pipeline_bands
    if sgm:
        # The SGM kernels need the whole pair: bands only overlap the upload with grey + remap.
        if gpu.stage_timing or h < 2 * k_bands:
            k_bands = 1
        r = 0
        outs = [(h * k) // k_bands for k in range(k_bands + 1)]
    else:
        if not p.fast or gpu.stage_timing or p.valid_rows < 2 * k_bands:
            k_bands = 1
        r = p.radius
        outs = [p.y_start + (p.valid_rows * k) // k_bands for k in range(k_bands + 1)]
        if p.valid_rows == 0:
            outs = [p.y_start, p.y_end]
    rect_end = [h if k == k_bands - 1 else min(h, outs[k + 1] + r) for k in range(k_bands)]
    if rectifier.is_identity:
        src_end = list(rect_end)
    else:
        row_max = np.maximum(rectifier.map_left_y.max(axis=1), rectifier.map_right_y.max(axis=1))
        reach = np.maximum.accumulate(np.clip(np.floor(row_max) + 2, 0, h)).astype(int)
        src_end = [h if k == k_bands - 1 else int(reach[rect_end[k] - 1]) for k in range(k_bands)]
        src_end = [max(src_end[: k + 1]) for k in range(k_bands)]
    # SGM: the census rows each band can run, those whose rows +-3 are rectified by then
    census_end = [h if k == k_bands - 1 else max(0, rect_end[k] - SGM_CENSUS_HALF_HEIGHT) for k in range(k_bands)]
    census_end = [max(census_end[: k + 1]) for k in range(k_bands)] if sgm else [0] * k_bands
    bands = []
    for k in range(k_bands):
        rows = outs[k + 1] - outs[k]
        rpb = p.choose_rows_per_block(sm_count, blocks_per_sm, gpu.rows_per_block, rows=rows)
        bands.append(
            Band(
                src=(src_end[k - 1] if k else 0, src_end[k]),
                rect=(rect_end[k - 1] if k else 0, rect_end[k]),
                out=(outs[k], outs[k + 1]),
                census=(census_end[k - 1] if k else 0, census_end[k]),
                rows_per_block=rpb,
                grid=(p.tiles_x, max(1, -(-rows // rpb)), 1),
            )
        )
    return bands
