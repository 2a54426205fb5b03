"""Region estimators: one side-by-side frame -> 9 raw region depths (the pipeline's expensive half).

:class:`RegionEstimator` is the contract every backend meets; :class:`CpuRegionEstimator` is the CPU
implementation (OpenCV StereoBM/SGBM or the exact NumPy reference). Other backends (the CuPy one in
:mod:`companion.gpu`) live outside the core and are plugged in by :mod:`companion.backends`, which maps a
backend name to a factory; the core never imports a backend.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from companion.config import CompanionConfig
from companion.core.depth import disparity_to_depth
from companion.core.disparity import DisparityMatcher, make_cpu_matcher
from companion.core.geometry import StereoGeometry
from companion.core.blocks import BlockMax
from companion.core.obstacle import ObstacleDistance, obstacle_layout, reduce_obstacle_distance
from companion.core.rectifier import make_rectifier
from companion.core.regions import RegionLayout, reduce_regions, region_layout
from companion.core.stereo import split_frame, to_grey
from companion.core.types import RegionDepths

Clock = Callable[[], float]


@dataclass(frozen=True)
class RegionEstimate:
    """What an estimator returns for one frame.

    Attributes:
        regions: raw region depths (before the LUT), metres, NaN = unknown.
        timings_ms: stage name -> milliseconds, in pipeline order.
        disparity: float32 (H, W) disparity in pixels (NaN invalid) when asked for, else None. A GPU
            estimator may return a downsampled image.
        near_blocks: when asked for with ``near_block_px``: float32 ``(ceil(H/b), ceil(W/b))`` the
            largest valid disparity of each ``b``-pixel block, pixels, NaN none
            (:class:`~companion.core.blocks.BlockMax`, eroded by ``near_erode_px``); a buffer valid
            until the next estimate.
        obstacle: the frame's OBSTACLE_DISTANCE bins (:mod:`companion.core.obstacle`), or None when
            ``obstacle_distance.send`` is off (or the backend does not compute them).
    """

    regions: RegionDepths
    timings_ms: dict[str, float]
    disparity: np.ndarray | None = None
    near_blocks: np.ndarray | None = None
    obstacle: ObstacleDistance | None = None


class RegionEstimator(Protocol):
    """Turns one side-by-side frame into 9 raw region depths."""

    name: str
    geometry: StereoGeometry
    layout: RegionLayout

    def estimate(
        self, frame: np.ndarray, want_disparity: bool = False, near_block_px: int = 0, near_erode_px: int = 0
    ) -> RegionEstimate:
        """``frame``: uint8 (H, 2W, 3) BGR or (H, 2W) grey side-by-side image; ``near_block_px`` > 0
        also returns the block-maximum disparity (the local planner's map input), of the disparity
        eroded along rows by ``near_erode_px`` (:class:`~companion.core.blocks.BlockMax`)."""
        ...


class CpuRegionEstimator:
    """The CPU path: OpenCV StereoBM/SGBM, the exact NumPy reference, or a matcher given to it (the
    compiled census + SGM engine of ``companion.cpu``, plugged in by :mod:`companion.backends`).

    Built once per (config, resolution): the rectification maps, the matcher and every per-frame
    buffer are allocated here, so :meth:`estimate` allocates nothing large.

    Args:
        matcher: the disparity matcher to use, built for ``width_px`` × ``height_px``; None = the
            one :func:`~companion.core.disparity.make_cpu_matcher` builds for ``cfg.stereo``.
    """

    def __init__(
        self,
        cfg: CompanionConfig,
        width_px: int,
        height_px: int,
        clock: Clock = time.perf_counter,
        matcher: DisparityMatcher | None = None,
    ):
        self.width_px = width_px
        self.height_px = height_px
        self._clock = clock
        self._regions_cfg = cfg.regions
        self._rectifier = make_rectifier(cfg.calibration, width_px, height_px)
        self.geometry: StereoGeometry = self._rectifier.geometry
        self._matcher = make_cpu_matcher(cfg.stereo) if matcher is None else matcher
        self.name = self._matcher.name
        self.layout: RegionLayout = region_layout(self.geometry, cfg.regions)
        shape = (height_px, width_px)
        self._grey_l = np.empty(shape, np.uint8)
        self._grey_r = np.empty(shape, np.uint8)
        self._rect_l = np.empty(shape, np.uint8)
        self._rect_r = np.empty(shape, np.uint8)
        self._disparity = np.empty(shape, np.float32)
        self._depth = np.empty(shape, np.float32)
        self._block_max: BlockMax | None = None
        self._obstacle = (
            obstacle_layout(self.geometry, cfg.stereo.num_disparities, cfg.obstacle_distance)
            if cfg.obstacle_distance.send != "off"
            else None
        )

    def estimate(
        self, frame: np.ndarray, want_disparity: bool = False, near_block_px: int = 0, near_erode_px: int = 0
    ) -> RegionEstimate:
        clock = self._clock
        timings: dict[str, float] = {}
        t0 = clock()
        left, right = split_frame(frame, self.width_px, self.height_px)
        gl = to_grey(left, out=self._grey_l)
        gr = to_grey(right, out=self._grey_r)
        t1 = clock()
        timings["grey_ms"] = (t1 - t0) * 1e3
        rl, rr = self._rectifier.rectify(gl, gr, out_left=self._rect_l, out_right=self._rect_r)
        t2 = clock()
        timings["rectify_ms"] = (t2 - t1) * 1e3
        disp = self._matcher.compute(rl, rr, out=self._disparity)
        t3 = clock()
        timings["disparity_ms"] = (t3 - t2) * 1e3
        depth = disparity_to_depth(disp, self.geometry.focal_baseline_px_m, out=self._depth)
        regions = reduce_regions(depth, self.layout, self._regions_cfg)
        near = None
        if near_block_px > 0:
            bm = self._block_max
            if bm is None or bm.block_px != near_block_px or bm.erode_px != near_erode_px:
                self._block_max = BlockMax(disp.shape, near_block_px, near_erode_px)
            near = self._block_max(disp)
        t4 = clock()
        timings["regions_ms"] = (t4 - t3) * 1e3
        obstacle = None
        if self._obstacle is not None:
            obstacle = reduce_obstacle_distance(disp, self._obstacle)
            timings["obstacle_ms"] = (clock() - t4) * 1e3
        return RegionEstimate(
            regions=regions,
            timings_ms=timings,
            disparity=disp.copy() if want_disparity else None,
            near_blocks=near,
            obstacle=obstacle,
        )


#: Builds the estimator ``cfg`` asks for at one eye size: ``factory(cfg, width_px, height_px, clock)``.
#: :func:`companion.backends.make_estimator` is the one the product uses.
EstimatorFactory = Callable[[CompanionConfig, int, int, Clock], RegionEstimator]
