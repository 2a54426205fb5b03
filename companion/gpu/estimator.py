"""The CuPy region estimator: one side-by-side frame -> 9 raw region depths, on the GPU.

Per frame, with nothing allocated, in ``gpu.pipeline_bands`` row bands so that the host copy, the
DMA and the GPU work of successive bands overlap (a copy stream and a compute stream, joined by one
event per band):

1. band k of the caller's frame is copied into a pinned staging buffer (``np.copyto``, or OpenCV's
   parallel BGR->RGB shuffle with ``gpu.host_copy_engine = "opencv"``) and its DMA is queued on the
   copy stream; with ``gpu.zero_copy`` the staging buffer is mapped and read in place (Jetsons); a
   frame written straight into :meth:`CupyRegionEstimator.frame_buffer`, or decoded by the camera
   into one of :meth:`CupyRegionEstimator.frame_pool`'s buffers, skips the host copy;
2. the compute stream waits for band k's DMA, then ``grey_*`` converts its rows (OpenCV's
   fixed-point formula, bit-exact; a YUYV frame's luma as it is), ``remap_linear`` rectifies the rows that depend only on rows
   uploaded so far (bit-exact with ``cv2.remap``; skipped for an ideal rig), and
   ``sad_fast_regions`` matches the disparity rows whose windows are complete, with the region
   histograms fused in; the last block of the last band turns the histograms into the 9 robust
   depths (``sad_naive`` + ``regions_from_disp`` for configurations the fast kernel does not cover);
3. the 9 depths and 9 valid fractions (144 bytes) come back to a pinned host buffer; with
   ``obstacle_distance.send`` on, ``obstacle_bins`` (``kernels/obstacle.cu``, a column of blocks per 5° bin)
   first reduces the device disparity to OBSTACLE_DISTANCE's 72 bins (144 more bytes, in the same copy), exactly
   :func:`companion.core.obstacle.reduce_obstacle_distance`; when the local planner's map or an overlay
   asks, ``preview_max`` reduces the disparity to blocks of ``gpu.disparity_preview_downsample`` px
   (and, with ``planner.block_erode_px``, ``memory_max`` to the map's eroded blocks) and they come
   back too.

With ``stereo.matcher = "sgm"`` (the default) the bands carry the upload, grey, rectification and
``sgm_census`` of the rows whose rows ±3 are rectified by then (so that it overlaps the later bands'
upload); after the last band the rest of the semi-global matcher of ``kernels/sgm.cu`` runs on the whole
rectified pair: ``sgm_paths`` (every path in one launch, one byte per (pixel, disparity) and path),
``sgm_wta`` (the winner, uniqueness, sub-pixel and the right view's disparity, per run of pixels) and
``sgm_post`` (left-right check, median, the disparity image and the 9 region depths), exactly
:mod:`companion.core.disparity.sgm`'s rules. Before ``sgm_post``, the near-range check (rule 11):
``sgm_shrink`` shrinks the rectified pair 4 times and a second module of the same kernels, built for
that size and half the disparities, matches it; ``sgm_post`` then reads its disparity.

Each band's GPU work is captured once as a CUDA graph and replayed. The results equal
:class:`~companion.core.estimator.CpuRegionEstimator` with the ``reference`` backend and the same matcher.
"""

from __future__ import annotations

import importlib.resources
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.config import CompanionConfig
from companion.core.calibration import make_rectifier
from companion.core.disparity.sgm import near_range_shape
from companion.core.geometry import StereoGeometry
from companion.core.blocks import block_max
from companion.core.estimator import RegionEstimate
from companion.core.obstacle import N_BINS, ObstacleDistance, ObstacleLayout, obstacle_layout
from companion.core.regions import RegionLayout, region_layout
from companion.core.stereo import split_frame
from companion.core.types import N_REGIONS, RegionDepths
from companion.errors import BackendError, ConfigError
from companion.framepool import FramePool
from companion.gpu.plan import (
    OBSTACLE_HIST_BINS,
    OBSTACLE_THREADS,
    SGM_CENSUS_HALF_HEIGHT,
    SGM_CENSUS_TILE,
    SGM_PATH_THREADS,
    SGM_POST_THREADS,
    DisparityPlan,
    SgmPlan,
    kernel_defines,
    obstacle_defines,
    obstacle_slices,
    plan_disparity,
    plan_sgm,
    sgm_defines,
)

log = logging.getLogger(__name__)

Clock = Callable[[], float]

#: Threads per block of the element-wise kernels (grey, remap, preview).
_EW_THREADS = 128
#: Threads per block of the fallback kernels.
_NAIVE_THREADS = 64
_REGIONS_THREADS = 256
_MAX_CHANNELS = 4


def kernel_source(name: str = "stereo.cu") -> str:
    """The CUDA source of a kernel file (``companion/gpu/kernels/stereo.cu`` or ``sgm.cu``), without the #defines."""
    return (importlib.resources.files("companion.gpu") / "kernels" / name).read_text(encoding="utf-8")


def _import_cupy() -> Any:
    try:
        import cupy
    except ImportError as err:  # the caller asked for the GPU explicitly
        raise BackendError(f"the cupy backend needs CuPy ({err}); install companion[gpu]") from None
    return cupy


class CupyRegionEstimator:
    """GPU implementation of the :class:`~companion.core.pipeline.RegionEstimator` contract.

    Built once per (config, resolution): compiles the kernels for this size and matcher setting
    (NVRTC; CuPy caches the binaries on disk), uploads the rectification maps, allocates every device
    and pinned host buffer, and runs one blank frame so that module loading and graph capture happen
    here and not on the first real frame. Not thread-safe: one estimator per camera thread.

    Args:
        cfg: the whole configuration (calibration, stereo, regions and gpu sections are read).
        width_px, height_px: size of one eye, px.
        clock: host clock for the ``timings_ms`` figures (seconds).

    Attributes:
        name: ``"cupy"``.
        geometry: the rectified rig.
        layout: the nine regions.
        matcher: ``"sgm"`` or ``"sad"`` (``stereo.matcher``).
        plan: the SAD kernel's shape (:class:`~companion.gpu.plan.DisparityPlan`; with the SGM matcher it
            still fixes the row pitch of the rectified images).
        sgm_plan: the SGM kernels' shape (:class:`~companion.gpu.plan.SgmPlan`), None with ``sad``.
        disparity_scale: the device disparity is pixels times this (16 with ``sgm``: 4 fractional bits).
        rows_per_block: output rows per block of the disparity kernel.
        device_name: the CUDA device's name.

    Raises:
        BackendError: CuPy missing, no such device, or the kernels fail to compile or run.
        CalibrationError: the calibration cannot be loaded for this size.
    """

    name = "cupy"

    def __init__(self, cfg: CompanionConfig, width_px: int, height_px: int, clock: Clock = time.perf_counter):
        cp = _import_cupy()
        self._cp = cp
        self.width_px = int(width_px)
        self.height_px = int(height_px)
        self._clock = clock
        self._gpu_cfg = cfg.gpu
        self._regions_cfg = cfg.regions
        _check_block_px(cfg.planner.block_px, cfg.gpu.disparity_preview_downsample)
        rectifier = make_rectifier(cfg.calibration, self.width_px, self.height_px)
        self.geometry: StereoGeometry = rectifier.geometry
        self.layout: RegionLayout = region_layout(self.geometry, cfg.regions)
        st = cfg.stereo
        self.matcher: str = st.matcher
        try:
            n_dev = cp.cuda.runtime.getDeviceCount()
        except cp.cuda.runtime.CUDARuntimeError as err:
            raise BackendError(f"no usable CUDA device: {err}") from None
        if not 0 <= cfg.gpu.device_id < n_dev:
            raise BackendError(f"gpu.device_id = {cfg.gpu.device_id} but {n_dev} CUDA device(s) are present")
        self._device = cp.cuda.Device(cfg.gpu.device_id)
        try:
            self.sm_count = int(self._device.attributes["MultiProcessorCount"])
        except cp.cuda.runtime.CUDARuntimeError as err:
            raise BackendError(f"cannot read the CUDA device's attributes: {err}") from None
        self.plan: DisparityPlan = plan_disparity(self.width_px, self.height_px, st.num_disparities, st.block_size_px)
        self.sgm_plan: SgmPlan | None = None
        if self.matcher == "sgm":
            self.sgm_plan = plan_sgm(self.width_px, self.height_px, st.num_disparities, st.sgm_paths,
                                     self.layout.row_edges, cfg.gpu.sgm_lanes_per_line, cfg.gpu.sgm_prefetch_steps,
                                     self.sm_count)
        self.disparity_scale = 16 if self.matcher == "sgm" else 1
        self.obstacle_layout: ObstacleLayout | None = (
            obstacle_layout(self.geometry, st.num_disparities, cfg.obstacle_distance)
            if cfg.obstacle_distance.send != "off"
            else None
        )
        self._identity = bool(rectifier.is_identity)
        try:
            with self._device:
                self.device_name = cp.cuda.runtime.getDeviceProperties(self._device.id)["name"].decode()
                self._build(cfg, rectifier)
                # Warm-up: loads the module, captures the graph and checks that the kernels run.
                blank = self.frame_buffer(3)
                blank.fill(0)
                self.estimate(blank)
        except (cp.cuda.runtime.CUDARuntimeError, cp.cuda.driver.CUDADriverError) as err:
            raise BackendError(f"CUDA error while preparing the GPU estimator: {err}") from None
        except cp.cuda.compiler.CompileException as err:
            raise BackendError(f"the CUDA kernels failed to compile: {err}") from None

    # ----------------------------------------------------------------------------------------------
    # construction

    def _build(self, cfg: CompanionConfig, rectifier: Any) -> None:
        cp = self._cp
        p, w, h = self.plan, self.width_px, self.height_px
        st = cfg.stereo
        # Only the shape is compiled in; the uniqueness and texture thresholds are kernel arguments,
        # so estimators that differ only in them share one compiled module.
        defines = kernel_defines(p, self.layout.row_edges, self.layout.col_edges)
        self._match_args = (
            np.uint32(st.uniqueness_ratio_pct),
            np.uint32(st.texture_threshold_grey * st.block_size_px**2),
        )
        # --fmad=false: the remap's float arithmetic must round exactly like OpenCV's (explicit fmaf
        # only); nothing else in the module is floating point on the hot path.
        self._module = cp.RawModule(code=defines + kernel_source(), options=("--std=c++17", "--fmad=false"))
        get = self._module.get_function
        self._k_grey = {
            (1, False): get("grey_c1"), (2, False): get("grey_c2"), (3, False): get("grey_c3"), (4, False): get("grey_c4"),
            (3, True): get("grey_c3_rgb"), (4, True): get("grey_c4_rgb"),
        }
        self._k_remap = get("remap_linear")
        self._k_fast = {False: get("sad_fast_regions"), True: get("sad_fast_regions_disp")}
        self._k_fast_unfused = get("sad_fast_disp")
        self._k_naive = get("sad_naive")
        self._k_regions = get("regions_from_disp")
        self._k_preview = get("preview_max")
        self._k_memory = get("memory_max")
        self._near: _Near | None = None
        if self.sgm_plan is not None:
            sp = self.sgm_plan
            self._sgm_module = cp.RawModule(
                code=sgm_defines(sp, p.pitch_bytes, self.layout.row_edges, self.layout.col_edges)
                + kernel_source("sgm.cu"),
                options=("--std=c++17", "--fmad=false"),
            )
            sget = self._sgm_module.get_function
            self._k_sgm = {name: sget(name) for name in ("sgm_census", "sgm_paths", "sgm_wta", "sgm_post", "sgm_shrink")}
            self._sgm_args = (
                np.uint32(st.sgm_p1),
                np.uint32(st.sgm_p2),
                np.uint32(st.sgm_uniqueness_ratio_pct),
                np.int32(st.sgm_lr_max_diff_px),
                np.int32(1 if st.sgm_median else 0),
            )
            self._near = self._build_near(cfg)

        if self.obstacle_layout is not None:
            lay = self.obstacle_layout
            self._od_module = cp.RawModule(
                code=obstacle_defines(OBSTACLE_THREADS) + kernel_source("obstacle.cu"),
                options=("--std=c++17", "--fmad=false"),
            )
            self._k_obstacle = self._od_module.get_function("obstacle_bins")
            self._od_row_thr = cp.asarray(lay.row_threshold_px, dtype=cp.float32)
            self._od_col_fbk = cp.asarray(lay.column_fbk, dtype=cp.float32)
            self._od_cols = cp.asarray(lay.bin_columns.astype(np.int32).reshape(-1))
            # each bin's totals over its row slices; the bin's last block zeroes them for the next frame
            self._od_hist = cp.zeros(N_BINS * OBSTACLE_HIST_BINS, dtype=cp.uint32)
            self._od_counts = cp.zeros(N_BINS * 4, dtype=cp.uint32)
            self._od_grid = (N_BINS, obstacle_slices(h))

        if p.fast:
            blocks_per_sm = cp.cuda.driver.occupancyMaxActiveBlocksPerMultiprocessor(
                self._k_fast[False].kernel.ptr, p.nt, 0
            )
            if blocks_per_sm < 1:
                raise BackendError(f"the disparity kernel cannot run on {self.device_name} ({p.nt} threads per block)")
        else:
            blocks_per_sm = 1
        self.blocks_per_sm = int(blocks_per_sm)
        self.rows_per_block = p.choose_rows_per_block(self.sm_count, self.blocks_per_sm, cfg.gpu.rows_per_block)
        self._grid_fast = (p.tiles_x, p.tiles_y(self.rows_per_block), 1)
        self._rows_regions = max(1, -(-p.valid_rows // (2 * self.sm_count)))
        self._grid_regions = (max(1, -(-p.valid_rows // self._rows_regions)), 1, 1)
        self._bands = self._plan_bands(cfg, rectifier)

        self._stream = cp.cuda.Stream(non_blocking=True)  # compute
        self._copy_stream = cp.cuda.Stream(non_blocking=True)  # host-to-device DMA
        self._band_events = [cp.cuda.Event(disable_timing=True) for _ in self._bands]
        # Pinned staging for the largest frame (4 channels); per-channel views share it.
        frame_bytes = h * 2 * w * _MAX_CHANNELS
        self._host_frame_mem, self._host_frame, mapped_ptr = self._pinned(frame_bytes)
        if self._gpu_cfg.zero_copy:
            self._frame_dev_ptr = mapped_ptr
            self._dev_frame = None
        else:
            self._dev_frame = cp.empty(frame_bytes, dtype=cp.uint8)
            self._frame_dev_ptr = int(self._dev_frame.data.ptr)

        shape_p = (h, p.pitch_bytes)
        self._rect_l = cp.zeros(shape_p, dtype=cp.uint8)
        self._rect_r = cp.zeros(shape_p, dtype=cp.uint8)
        if self._identity:
            self._raw_l, self._raw_r = self._rect_l, self._rect_r
            self._maps = None
        else:
            self._raw_l = cp.zeros(shape_p, dtype=cp.uint8)
            self._raw_r = cp.zeros(shape_p, dtype=cp.uint8)
            self._maps = tuple(
                cp.asarray(np.ascontiguousarray(m, dtype=np.float32))
                for m in (rectifier.map_left_x, rectifier.map_left_y, rectifier.map_right_x, rectifier.map_right_y)
            )
        # Pixels outside the valid area are never written by the kernels: -1 (invalid) once, here.
        self._disp = cp.full((h, w), -1, dtype=cp.int16)
        if self.sgm_plan is None:
            self._hist = cp.zeros(N_REGIONS * p.num_disparities, dtype=cp.uint32)
        else:
            sp = self.sgm_plan
            # left, right, right shifted by one (sgm.cu); the zero padding is written once, here
            self._census = cp.zeros((3, h, sp.census_stride_px), dtype=cp.uint64)
            self._volumes = cp.zeros((sp.paths, h, w, sp.dpad), dtype=cp.uint8)
            self._winner = cp.zeros((h, w), dtype=cp.int32)
            self._right_keys = cp.zeros((h, w), dtype=cp.uint32)
            self._hist = cp.zeros(N_REGIONS * sp.nbins, dtype=cp.uint32)
        self._counter = cp.zeros(1, dtype=cp.uint32)
        # The 9 depths and 9 valid fractions (float64), then OBSTACLE_DISTANCE's 72 bins (uint16): one
        # buffer each side, so that one copy brings both back.
        region_bytes = 2 * N_REGIONS * 8
        self._out_bytes = region_bytes + (N_BINS * 2 if self.obstacle_layout is not None else 0)
        self._out_dev = cp.zeros(region_bytes + N_BINS * 2, dtype=cp.uint8)
        self._result_dev = self._out_dev[:region_bytes].view(cp.float64)
        self._od_out = self._out_dev[region_bytes:].view(cp.uint16)
        self._result_host = cp.cuda.alloc_pinned_memory(region_bytes + N_BINS * 2)
        self._result = np.frombuffer(self._result_host, dtype=np.float64, count=2 * N_REGIONS)
        self._od_host = np.frombuffer(self._result_host, dtype=np.uint16, count=N_BINS, offset=region_bytes)

        f = self._gpu_cfg.disparity_preview_downsample
        self._preview_factor = f if f >= 2 else 1
        if self._preview_factor > 1:
            ow, oh = -(-w // f), -(-h // f)
            self._preview_shape = (oh, ow)
            self._preview_dev = cp.empty((oh, ow), dtype=cp.float32)
            self._preview_host_mem = cp.cuda.alloc_pinned_memory(oh * ow * 4)
            self._preview_host = np.frombuffer(self._preview_host_mem, dtype=np.float32, count=oh * ow).reshape(oh, ow)
            # The map's eroded blocks (planner.block_erode_px, which a reload may switch on: always here).
            self._memory_dev = cp.empty((oh, ow), dtype=cp.float32)
            self._memory_host_mem = cp.cuda.alloc_pinned_memory(oh * ow * 4)
            self._memory_host = np.frombuffer(self._memory_host_mem, dtype=np.float32, count=oh * ow).reshape(oh, ow)
        else:
            self._disp_host_mem = cp.cuda.alloc_pinned_memory(h * w * 2)
            self._disp_host = np.frombuffer(self._disp_host_mem, dtype=np.int16, count=h * w).reshape(h, w)

        fb = np.float32(self.geometry.focal_baseline_px_m)
        rc = self._regions_cfg
        self._region_args = (
            fb,
            np.float64(rc.robust_percentile_pct),
            np.float64(rc.min_valid_fraction),
            np.float64(rc.max_depth_m),
        )
        self._registered = 0  # caller frame page-locked for the DMA in flight (register_frames)
        # The pinned buffers a frame is read from in place (the staging buffer, frame_pool()'s): host
        # pointer -> where the kernels read the frame (the device copy; zero copy: the buffer's mapping).
        self._pool: FramePool | None = None
        self._pool_mem: list[Any] = []
        self._in_place_ptrs: dict[int, int] = {int(self._host_frame_mem.ptr): self._frame_dev_ptr}
        self._frame_shapes = {self.frame_buffer(c).shape: c for c in (1, 2, 3, 4)}  # shape -> channels
        self._kernel_frame_ptr = self._frame_dev_ptr  # where this frame's kernels read it
        self._graphs: dict[tuple[int, int, bool, bool, int], Any] = {}
        self._graph_ok = bool(self._gpu_cfg.use_cuda_graph) and not self._gpu_cfg.stage_timing
        # a frame read in place (no host copy): one graph for the whole frame (_frame_graph)
        self._frame_graphs: dict[tuple[int, bool, bool, int, int], Any] = {}
        self._frame_graph_ok = self._graph_ok
        self._fork_event = cp.cuda.Event(disable_timing=True)
        self._events = [cp.cuda.Event() for _ in range(5)] if self._gpu_cfg.stage_timing else []
        n_threads = self._gpu_cfg.host_copy_threads
        self._crew = _CopyCrew(n_threads, self._device.id) if n_threads > 1 else None
        if self.sgm_plan is None:
            log.info(
                "cupy estimator on %s: %dx%d, D=%d, b=%d, %s kernel, tile %s, %d blocks/SM, bands %s",
                self.device_name, w, h, p.num_disparities, p.block_size, "fast" if p.fast else "fallback",
                f"{p.tx}x{p.cpad}" if p.fast else "-", self.blocks_per_sm,
                [(b.src, b.out, b.rows_per_block, b.grid[:2]) for b in self._bands],
            )
        else:
            sp = self.sgm_plan
            log.info(
                "cupy estimator on %s: %dx%d, D=%d, SGM %d paths, %d lanes x %d groups per line, %.1f MB of "
                "device buffers, bands %s",
                self.device_name, w, h, sp.num_disparities, sp.paths, sp.lanes_per_line, sp.words_per_lane,
                sum(sp.device_bytes().values()) / 1e6, [(b.src, b.rect) for b in self._bands],
            )

    def _build_near(self, cfg: CompanionConfig) -> _Near | None:
        """The near-range check's coarse pair (the reference's rule 11): a second module of the SGM
        kernels built for the pair shrunk :data:`~companion.core.disparity.sgm.NEAR_SCALE` times with half the disparities, and its
        buffers (1/32 of the full size's); None where the rule skips the check."""
        cp = self._cp
        st = cfg.stereo
        shape = near_range_shape(self.height_px, self.width_px, st.num_disparities)
        if shape is None:
            return None
        hc, wc, dc = shape
        rows_e, cols_e = [0, hc // 3, 2 * hc // 3, hc], [0, wc // 3, 2 * wc // 3, wc]
        plan = plan_sgm(wc, hc, dc, st.sgm_paths, rows_e, 0, cfg.gpu.sgm_prefetch_steps, self.sm_count)
        pitch = -(-(wc + 16) // 16) * 16
        module = cp.RawModule(
            code=sgm_defines(plan, pitch, rows_e, cols_e) + kernel_source("sgm.cu"),
            options=("--std=c++17", "--fmad=false"),
        )
        get = module.get_function
        return _Near(
            plan=plan,
            width_px=wc,
            height_px=hc,
            pitch_bytes=pitch,
            module=module,
            kernels={name: get(name) for name in ("sgm_census", "sgm_paths", "sgm_wta", "sgm_post")},
            left=cp.zeros((hc, pitch), dtype=cp.uint8),
            right=cp.zeros((hc, pitch), dtype=cp.uint8),
            census=cp.zeros((3, hc, plan.census_stride_px), dtype=cp.uint64),
            volumes=cp.zeros((plan.paths, hc, wc, plan.dpad), dtype=cp.uint8),
            winner=cp.zeros((hc, wc), dtype=cp.int32),
            right_keys=cp.zeros((hc, wc), dtype=cp.uint32),
            disp=cp.full((hc, wc), -1, dtype=cp.int16),
            hist=cp.zeros(N_REGIONS * plan.nbins, dtype=cp.uint32),
            counter=cp.zeros(1, dtype=cp.uint32),
            result=cp.zeros(2 * N_REGIONS, dtype=cp.float64),
        )

    def _plan_bands(self, cfg: CompanionConfig, rectifier: Any) -> list[_Band]:
        """Split the frame into row bands whose GPU work needs only the rows uploaded so far.

        Disparity band k covers output rows ``[o_k, o_k+1)``; its windows read rectified rows up to
        ``o_k+1 + r``; those read source rows up to the largest ``floor(map_y) + 2`` among them (the
        two bilinear taps), or the same rows for an ideal rig. The upload of band k is the source rows
        from the previous band's end to that row.
        """
        p, h = self.plan, self.height_px
        k_bands = cfg.gpu.pipeline_bands
        sgm = self.sgm_plan is not None
        if sgm:
            # The SGM kernels need the whole pair: bands only overlap the upload with grey + remap.
            if cfg.gpu.stage_timing or h < 2 * k_bands:
                k_bands = 1
            r = 0
            outs = [(h * k) // k_bands for k in range(k_bands + 1)]
        else:
            if not p.fast or cfg.gpu.stage_timing or p.valid_rows < 2 * k_bands:
                k_bands = 1
            r = p.radius
            outs = [p.y_start + (p.valid_rows * k) // k_bands for k in range(k_bands + 1)]
            if p.valid_rows == 0:
                outs = [p.y_start, p.y_end]
        rect_end = [h if k == k_bands - 1 else min(h, outs[k + 1] + r) for k in range(k_bands)]
        if self._identity:
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
            rpb = p.choose_rows_per_block(self.sm_count, self.blocks_per_sm, cfg.gpu.rows_per_block, rows=rows)
            bands.append(
                _Band(
                    src=(src_end[k - 1] if k else 0, src_end[k]),
                    rect=(rect_end[k - 1] if k else 0, rect_end[k]),
                    out=(outs[k], outs[k + 1]),
                    census=(census_end[k - 1] if k else 0, census_end[k]),
                    rows_per_block=rpb,
                    grid=(p.tiles_x, max(1, -(-rows // rpb)), 1),
                )
            )
        total = sum(b.grid[0] * b.grid[1] for b in bands)
        self._total_blocks = np.uint32(total)
        return bands

    # ----------------------------------------------------------------------------------------------
    # public API

    def frame_buffer(self, channels: int = 3) -> np.ndarray:
        """The pinned staging buffer as a writable uint8 ``(H, 2W, channels)`` array (``(H, 2W)`` for 1;
        2 is YUYV, the bytes a UVC camera sends, 3 BGR, 4 BGRA).

        A camera that decodes straight into this array (e.g. ``VideoCapture.read(image=buf)``) and
        passes it to :meth:`estimate` saves the host copy of the frame. Its content is overwritten by
        every :meth:`estimate` of another array.
        """
        if channels not in (1, 2, 3, 4):
            raise ValueError(f"channels must be 1, 2, 3 or 4, got {channels}")
        shape = (self.height_px, 2 * self.width_px) + ((channels,) if channels > 1 else ())
        return self._host_frame[: math.prod(shape)].reshape(shape)

    def frame_pool(self, count: int = 3, channels: int = 3) -> FramePool:
        """``count`` more pinned buffers of the frame's shape (``(H, 2W, channels)``, uint8) for a camera to
        decode into (:mod:`companion.framepool`): a frame in one of them goes to the device with no host
        copy, as from :meth:`frame_buffer`, but the camera may fill the next buffer while this frame is
        processed. Made once; later calls return the same pool (``count`` and ``channels`` of the first).

        Raises:
            ValueError: ``count`` < 1, or ``channels`` not 1, 2, 3 or 4.
        """
        if self._pool is not None:
            return self._pool
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        shape = self.frame_buffer(channels).shape
        buffers = []
        with self._device:
            for _ in range(count):
                mem, buf, mapped_ptr = self._pinned(math.prod(shape))
                self._pool_mem.append(mem)
                # zero copy: the kernels read the buffer through its mapping; else the DMA reads it
                self._in_place_ptrs[int(mem.ptr)] = mapped_ptr if self._dev_frame is None else self._frame_dev_ptr
                buffers.append(buf.reshape(shape))
        self._pool = FramePool(buffers)
        return self._pool

    def _pinned(self, nbytes: int) -> tuple[Any, np.ndarray, int]:
        """Page-locked host memory for frames (mapped with ``gpu.zero_copy``): the allocation, a uint8
        ``(nbytes,)`` array over it, and its device-side pointer (0 when not mapped)."""
        cp = self._cp
        zero_copy = self._gpu_cfg.zero_copy
        flags = cp.cuda.runtime.hostAllocMapped if zero_copy else cp.cuda.runtime.hostAllocPortable
        mem = cp.cuda.PinnedMemory(nbytes, flags)
        array = np.frombuffer(cp.cuda.PinnedMemoryPointer(mem, 0), dtype=np.uint8, count=nbytes)
        mapped = int(cp.cuda.runtime.pointerGetAttributes(mem.ptr).devicePointer) if zero_copy else 0
        return mem, array, mapped

    def estimate(
        self, frame: np.ndarray, want_disparity: bool = False, near_block_px: int = 0, near_erode_px: int = 0
    ) -> RegionEstimate:
        """9 raw region depths of one side-by-side frame.

        Args:
            frame: uint8 ``(H, 2W, 3)`` BGR, ``(H, 2W, 4)`` BGRA, ``(H, 2W, 2)`` YUYV (its luma is the
                grey, as :func:`~companion.core.stereo.to_grey` takes it) or ``(H, 2W)`` grey, any strides.
            want_disparity: also return the disparity: float32 px, NaN invalid; downsampled by
                ``gpu.disparity_preview_downsample`` (each cell the largest valid disparity of its
                block), or at full resolution when that is 0 or 1.
            near_block_px: > 0: also return ``near_blocks``, the largest valid disparity of each
                block of this many pixels (the local planner's map input; a multiple of the preview
                factor, which the device computes); the CPU reference is
                :func:`~companion.core.blocks.block_max`.
            near_erode_px: the map's blocks of the disparity eroded along rows by this many pixels
                (:class:`~companion.core.blocks.BlockMax`; on the device with a preview).

        Returns:
            :class:`~companion.core.estimator.RegionEstimate` with ``timings_ms``: ``upload_ms`` (host
            copies into pinned memory and queueing every band's DMA and kernels), ``gpu_ms`` (from then
            until the results are on the host); with ``gpu.stage_timing`` (one band) also the GPU
            times ``h2d_ms``, ``grey_rectify_ms``, ``disparity_regions_ms``, ``d2h_ms`` from events.

        Raises:
            FrameError: wrong dtype, layout or size.
            BackendError: a CUDA error.
        """
        t0 = self._clock()
        in_place = self._in_place(frame)
        if in_place is None:
            split_frame(frame, self.width_px, self.height_px)  # the checks; the eyes are split on the device
            channels = 1 if frame.ndim == 2 else int(frame.shape[2])
        else:  # one of this estimator's pinned buffers, as one: shape and dtype are right by construction
            channels = in_place[0]
        timings: dict[str, float] = {}
        try:
            return self._estimate(frame, channels, in_place, want_disparity, near_block_px, near_erode_px, t0, timings)
        finally:
            if self._registered:  # an error left the caller's frame page-locked: wait, then unlock
                try:
                    with self._device:
                        self._copy_stream.synchronize()
                        self._stream.synchronize()
                        self._unregister()
                except Exception as err:  # noqa: BLE001 - the original error is the one to report
                    log.error("could not unlock the caller's frame after an error: %s", err)

    def _estimate(
        self,
        frame: np.ndarray,
        channels: int,
        in_place: tuple[int, int, int] | None,
        want_disparity: bool,
        near_block_px: int,
        near_erode_px: int,
        t0: float,
        timings: dict[str, float],
    ) -> RegionEstimate:
        cp = self._cp
        # The map's blocks come from the same device disparity and preview as an overlay's.
        want_device_disparity = want_disparity or near_block_px > 0
        # The device erodes and reduces the map's blocks where it reduces the preview's.
        erode = int(near_erode_px) if near_block_px > 0 and self._preview_factor > 1 else 0
        clock = self._clock
        comp = self._stream
        try:
            with self._device:
                src = self._source(frame, channels, in_place)
                self._kernel_frame_ptr = src.kernel_ptr
                ev = self._events
                frame_graph = None
                if self._frame_graph_ok and src.copy is None and not self._registered:
                    frame_graph = self._frame_graph(src, channels, want_device_disparity, erode)
                if frame_graph is not None:
                    frame_graph.launch(comp)
                else:
                    for k, band in enumerate(self._bands):
                        self._upload_band(src, band, self._band_events[k])
                        comp.wait_event(self._band_events[k])
                        if ev:
                            self._enqueue_band(k, channels, src.swapped, want_device_disparity, erode, events=ev)
                        elif self._graph_ok:
                            self._graph(k, channels, src.swapped, want_device_disparity, erode).launch(comp)
                        else:
                            self._enqueue_band(k, channels, src.swapped, want_device_disparity, erode)
                t1 = clock()
                try:
                    comp.synchronize()
                finally:
                    self._unregister()  # after the DMA that read the caller's pages has finished
                t2 = clock()
                if ev:
                    elapsed = cp.cuda.get_elapsed_time
                    timings["h2d_ms"] = elapsed(ev[0], ev[1])
                    timings["grey_rectify_ms"] = elapsed(ev[1], ev[2])
                    timings["disparity_regions_ms"] = elapsed(ev[2], ev[3])
                    timings["d2h_ms"] = elapsed(ev[3], ev[4])
        except (cp.cuda.runtime.CUDARuntimeError, cp.cuda.driver.CUDADriverError) as err:
            self._recover()
            raise BackendError(f"CUDA error in the GPU estimator: {err}") from None
        timings["upload_ms"] = (t1 - t0) * 1e3
        timings["gpu_ms"] = (t2 - t1) * 1e3
        res = self._result
        regions = RegionDepths(depth_m=res[:N_REGIONS].copy(), valid_fraction=res[N_REGIONS:].copy())
        disparity = self._host_disparity() if want_disparity else None
        near = self._near_blocks(near_block_px, int(near_erode_px)) if near_block_px > 0 else None
        obstacle = None
        lay = self.obstacle_layout
        if lay is not None:
            obstacle = ObstacleDistance(self._od_host.copy(), lay.min_distance_cm, lay.max_distance_cm)
        return RegionEstimate(
            regions=regions, timings_ms=timings, disparity=disparity, near_blocks=near, obstacle=obstacle
        )

    def _enqueue_obstacle(self, stream: Any) -> None:
        """Queue the OBSTACLE_DISTANCE kernel on the device disparity (its 72 bins come back with the
        regions' copy)."""
        lay = self.obstacle_layout
        assert lay is not None
        self._k_obstacle(
            self._od_grid, (OBSTACLE_THREADS,),
            (self._disp, np.int32(self.width_px), np.int32(self.height_px), np.float32(1.0 / self.disparity_scale),
             self._od_row_thr, self._od_col_fbk, self._od_cols, np.float64(lay.percentile_pct),
             np.int32(lay.min_points), np.float64(lay.min_valid_fraction), np.float32(lay.max_distance_m),
             np.int32(lay.min_distance_cm), np.int32(lay.max_distance_cm), self._od_hist, self._od_counts,
             self._od_out),
            stream=stream,
        )

    def rectified_pair(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the last frame's rectified grey eyes, uint8 ``(H, W)`` each (tests, debugging)."""
        with self._device:
            w = self.width_px
            return self._rect_l[:, :w].get(), self._rect_r[:, :w].get()

    def disparity_int16(self) -> np.ndarray:
        """Copy of the device disparity image, int16 ``(H, W)``, px × :attr:`disparity_scale`, -1 invalid
        (tests, debugging).

        SAD: current only after a frame run with ``want_disparity=True`` (the plain path skips writing
        it). SGM: written every frame.
        """
        with self._device:
            return self._disp.get()

    def close(self) -> None:
        """Stop the copy threads; device memory goes with the object."""
        if self._crew is not None:
            self._crew.close()
            self._crew = None

    # ----------------------------------------------------------------------------------------------
    # per-frame internals

    def _in_place(self, frame: Any) -> tuple[int, int, int] | None:
        """``(channels, host pointer, where the kernels read it)`` for a frame written into
        :meth:`frame_buffer` or decoded into a :meth:`frame_pool` buffer, as a whole C-contiguous uint8
        frame; else None."""
        if type(frame) is not np.ndarray:
            return None
        ptr = frame.ctypes.data
        kernel_ptr = self._in_place_ptrs.get(ptr)
        if kernel_ptr is None or not frame.flags.c_contiguous or frame.dtype != np.uint8:
            return None
        channels = self._frame_shapes.get(frame.shape)
        return None if channels is None else (channels, ptr, kernel_ptr)

    def _source(self, frame: np.ndarray, channels: int, in_place: tuple[int, int, int] | None) -> _Source:
        """How this frame reaches the device: host copy function, DMA source, channel order
        (``in_place``: :meth:`_in_place`'s answer for it)."""
        zero_copy = self._dev_frame is None
        if in_place is not None:
            # written into frame_buffer() or decoded into a frame_pool() buffer: DMA (zero copy: read) it there
            return _Source(frame, frame, None, in_place[1], False, zero_copy, in_place[2])
        staging = self.frame_buffer(channels)
        host_ptr = self._host_frame_mem.ptr
        if (
            self._gpu_cfg.register_frames
            and not zero_copy
            and frame.flags.c_contiguous
            and self._register(frame)
        ):
            # The caller's own pages are locked for this frame: DMA straight from them.
            return _Source(frame, staging, None, frame.ctypes.data, False, zero_copy, self._frame_dev_ptr)
        if self._gpu_cfg.host_copy_engine == "opencv" and channels in (3, 4):
            import cv2

            code = cv2.COLOR_BGR2RGB if channels == 3 else cv2.COLOR_BGRA2RGBA

            def copy(dst: np.ndarray, src: np.ndarray) -> None:
                out = cv2.cvtColor(src, code, dst=dst)
                if out.__array_interface__["data"][0] != dst.__array_interface__["data"][0]:
                    np.copyto(dst, out)  # cv2 reallocated (not expected for these layouts)

            return _Source(frame, staging, copy, host_ptr, True, zero_copy, self._frame_dev_ptr)
        return _Source(frame, staging, np.copyto, host_ptr, False, zero_copy, self._frame_dev_ptr)

    def _upload_band(self, src: _Source, band: _Band, done: Any) -> None:
        """Host-copy band rows into the staging buffer, queue their DMA, record ``done`` after it."""
        cp = self._cp
        a, b = band.src
        copy_stream = self._copy_stream
        row_bytes = src.staging.strides[0]
        if b > a:

            def rows(ra: int, rb: int) -> None:
                if src.copy is not None:
                    src.copy(src.staging[ra:rb], src.frame[ra:rb])
                if self._events:  # stage timing (one band, no crew): h2d_ms is the DMA alone
                    self._events[0].record(copy_stream)
                if not src.zero_copy:
                    off = ra * row_bytes
                    cp.cuda.runtime.memcpyAsync(
                        self._frame_dev_ptr + off, src.dma_ptr + off, (rb - ra) * row_bytes,
                        cp.cuda.runtime.memcpyHostToDevice, copy_stream.ptr,
                    )

            crew = self._crew
            if crew is None or src.copy is None or self._events:
                rows(a, b)
            else:
                edges = [a + ((b - a) * i) // crew.size for i in range(crew.size + 1)]
                crew.run([(lambda ra=ra, rb=rb: rows(ra, rb)) for ra, rb in zip(edges, edges[1:])])
        elif self._events:
            self._events[0].record(copy_stream)
        done.record(copy_stream)

    def _register(self, frame: np.ndarray) -> bool:
        """Page-lock the caller's frame for one DMA (``gpu.register_frames``); False: use staging."""
        cp = self._cp
        try:
            cp.cuda.runtime.hostRegister(frame.ctypes.data, frame.nbytes, 0)
        except cp.cuda.runtime.CUDARuntimeError as err:
            # e.g. part of the range is already registered (by the caller): the staged path works.
            log.debug("could not page-lock the frame (%s); copying it into the staging buffer", err)
            return False
        self._registered = frame.ctypes.data
        return True

    def _unregister(self) -> None:
        if self._registered:
            ptr, self._registered = self._registered, 0
            self._cp.cuda.runtime.hostUnregister(ptr)

    def _graph(self, k: int, channels: int, swapped: bool, want_disparity: bool, erode: int) -> Any:
        key = (k, channels, swapped, want_disparity, erode, self._kernel_frame_ptr)  # a pool buffer read in place: its own
        graph = self._graphs.get(key)
        if graph is None:
            stream = self._stream
            try:
                stream.begin_capture()
                try:
                    self._enqueue_band(k, channels, swapped, want_disparity, erode)
                finally:
                    graph = stream.end_capture()
            except Exception as err:  # capture unsupported here: plain launches from now on
                log.warning("CUDA graph capture failed (%s); using plain kernel launches", err)
                self._graph_ok = False
                return _Direct(self, k, channels, swapped, want_disparity, erode)
            self._graphs[key] = graph
        return graph

    def _frame_graph(self, src: _Source, channels: int, want_disparity: bool, erode: int) -> Any | None:
        """One CUDA graph for a whole frame read in place from a pinned buffer (the staging buffer, a
        pool buffer): every band's DMA on the copy stream's branch, every band's kernels on the compute
        branch after its DMA, as the per-band path queues them, so band k's kernels still overlap band
        k+1's DMA; one launch per frame instead of a copy, an event, a wait and a launch per band.
        Captured on first use per (buffer, channels, order, disparity, erosion); None where capture fails (the
        per-band path then runs, from then on)."""
        key = (channels, src.swapped, want_disparity, erode, src.dma_ptr, src.kernel_ptr)
        graph = self._frame_graphs.get(key)
        if graph is not None:
            return graph
        s, cs = self._stream, self._copy_stream
        try:
            s.begin_capture()
            try:
                self._fork_event.record(s)  # the copy stream joins the capture here
                cs.wait_event(self._fork_event)
                for k, band in enumerate(self._bands):
                    self._upload_band(src, band, self._band_events[k])
                    s.wait_event(self._band_events[k])
                    self._enqueue_band(k, channels, src.swapped, want_disparity, erode)
            finally:
                graph = s.end_capture()
        except Exception as err:  # capture of two streams unsupported here: per-band launches from now on
            log.warning("CUDA graph capture of a whole frame failed (%s); launching per band", err)
            self._frame_graph_ok = False
            return None
        self._frame_graphs[key] = graph
        return graph

    def _enqueue_band(
        self,
        k: int,
        channels: int,
        swapped: bool,
        want_disparity: bool,
        erode: int = 0,
        events: list[Any] | None = None,
    ) -> None:
        """Queue band k's GPU work (module doc, step 2; step 3 after the last band) on the compute stream."""
        cp = self._cp
        p, w, h = self.plan, self.width_px, self.height_px
        band = self._bands[k]
        last = k == len(self._bands) - 1
        s = self._stream
        if events:
            events[1].record(s)
        a, b = band.src
        if b > a:
            quads = -(-w // 4)
            self._k_grey[(channels, swapped)](
                (-(-quads // _EW_THREADS), b - a, 2), (_EW_THREADS,),
                (np.uint64(self._kernel_frame_ptr), self._raw_l, self._raw_r, np.int32(a)), stream=s,
            )
        ra, rb = band.rect
        if self._maps is not None and rb > ra:
            self._k_remap(
                (-(-w // _EW_THREADS), rb - ra, 2), (_EW_THREADS,),
                (self._raw_l, self._raw_r, *self._maps, self._rect_l, self._rect_r, np.int32(ra)), stream=s,
            )
        if events:
            events[2].record(s)
        fb, pct, min_valid, max_depth = self._region_args
        if self.sgm_plan is not None:
            ca, cb = band.census
            if cb > ca:  # this band's share of the census overlaps the next bands' upload
                self._k_sgm["sgm_census"](self.sgm_plan.census_grid(cb - ca), SGM_CENSUS_TILE,
                                          (self._rect_l, self._rect_r, self._census, self._right_keys,
                                           np.int32(ca), np.int32(cb)), stream=s)
            if last:
                self._enqueue_sgm(s)
        elif p.fast:
            # The OBSTACLE_DISTANCE kernel reads the device disparity: the SAD kernel must write it
            # (SGM's sgm_post always does).
            self._k_fast[want_disparity or self.obstacle_layout is not None](
                band.grid, (p.nt,),
                (self._rect_l, self._rect_r, self._disp, self._hist, self._counter, self._result_dev,
                 np.int32(band.out[0]), np.int32(band.out[1]), np.int32(band.rows_per_block), self._total_blocks,
                 *self._match_args, fb, pct, min_valid, max_depth),
                stream=s,
            )
        else:
            if p.valid_cols > 0 and p.valid_rows > 0:
                self._k_naive(
                    (-(-p.valid_cols // _NAIVE_THREADS), p.valid_rows), (_NAIVE_THREADS,),
                    (self._rect_l, self._rect_r, self._disp, *self._match_args), stream=s,
                )
            self._k_regions(
                self._grid_regions, (_REGIONS_THREADS,),
                (self._disp, self._hist, self._counter, self._result_dev, np.int32(self._rows_regions),
                 fb, pct, min_valid, max_depth),
                stream=s,
            )
        if last and self.obstacle_layout is not None:
            self._enqueue_obstacle(s)
        if events:
            events[3].record(s)
        if not last:
            return
        d2h = cp.cuda.runtime.memcpyDeviceToHost
        cp.cuda.runtime.memcpyAsync(self._result_host.ptr, self._out_dev.data.ptr, self._out_bytes, d2h, s.ptr)
        if want_disparity:
            if self._preview_factor > 1:
                oh, ow = self._preview_shape
                self._k_preview(
                    (-(-ow // _EW_THREADS), oh), (_EW_THREADS,),
                    (self._disp, self._preview_dev, np.int32(self._preview_factor), np.int32(ow), np.int32(oh),
                     np.float32(1.0 / self.disparity_scale)),
                    stream=s,
                )
                cp.cuda.runtime.memcpyAsync(
                    self._preview_host_mem.ptr, self._preview_dev.data.ptr, oh * ow * 4, d2h, s.ptr
                )
                if erode:
                    self._k_memory(
                        (-(-ow // _EW_THREADS), oh), (_EW_THREADS,),
                        (self._disp, self._memory_dev, np.int32(self._preview_factor), np.int32(ow), np.int32(oh),
                         np.float32(1.0 / self.disparity_scale), np.int32(erode)),
                        stream=s,
                    )
                    cp.cuda.runtime.memcpyAsync(
                        self._memory_host_mem.ptr, self._memory_dev.data.ptr, oh * ow * 4, d2h, s.ptr
                    )
            else:
                cp.cuda.runtime.memcpyAsync(self._disp_host_mem.ptr, self._disp.data.ptr, h * w * 2, d2h, s.ptr)
        if events:
            events[4].record(s)

    def _enqueue_sgm(self, s: Any) -> None:
        """Queue the SGM kernels after the census on stream ``s`` (the rectified pair and its census
        are complete)."""
        sp = self.sgm_plan
        assert sp is not None
        k = self._k_sgm
        p1, p2, uniq, lr_max, median = self._sgm_args
        fb, pct, min_valid, max_depth = self._region_args
        warps = SGM_PATH_THREADS // 32
        k["sgm_paths"]((-(-sp.path_tasks // warps),), (SGM_PATH_THREADS,), (self._census, self._volumes, p1, p2),
                       stream=s)
        k["sgm_wta"]((-(-sp.wta_tasks // warps),), (SGM_PATH_THREADS,),
                     (self._volumes, self._winner, self._right_keys, uniq), stream=s)
        near_args = self._enqueue_near(s)
        k["sgm_post"]((sp.post_blocks,), (SGM_POST_THREADS,),
                      (self._winner, self._right_keys, self._disp, self._hist, self._counter, self._result_dev,
                       lr_max, median, fb, pct, min_valid, max_depth, *near_args),
                      stream=s)

    def _enqueue_near(self, s: Any) -> tuple[Any, ...]:
        """Queue the near-range check's coarse pair on stream ``s`` (after the rectification): shrink the
        rectified pair and match it whole with the coarse module. Returns ``sgm_post``'s last three
        arguments: the coarse disparity and its size, or a null pointer where the check is skipped."""
        n = self._near
        if n is None:
            return (np.uint64(0), np.int32(0), np.int32(0))
        k = self._k_sgm
        p1, p2, uniq, lr_max, median = self._sgm_args
        fb, pct, min_valid, max_depth = self._region_args
        warps = SGM_PATH_THREADS // 32
        k["sgm_shrink"]((-(-n.width_px // 64), n.height_px, 2), (64,),
                        (self._rect_l, self._rect_r, n.left, n.right, np.int32(n.width_px),
                         np.int32(n.height_px), np.int32(n.pitch_bytes)), stream=s)
        nk, npl = n.kernels, n.plan
        nk["sgm_census"](npl.census_grid(n.height_px), SGM_CENSUS_TILE,
                         (n.left, n.right, n.census, n.right_keys, np.int32(0), np.int32(n.height_px)), stream=s)
        nk["sgm_paths"]((-(-npl.path_tasks // warps),), (SGM_PATH_THREADS,), (n.census, n.volumes, p1, p2), stream=s)
        nk["sgm_wta"]((-(-npl.wta_tasks // warps),), (SGM_PATH_THREADS,), (n.volumes, n.winner, n.right_keys, uniq),
                      stream=s)
        # the coarse module's own region results are not used; its post reads no coarser pair (null)
        nk["sgm_post"]((npl.post_blocks,), (SGM_POST_THREADS,),
                       (n.winner, n.right_keys, n.disp, n.hist, n.counter, n.result, lr_max, median, fb, pct,
                        min_valid, max_depth, np.uint64(0), np.int32(0), np.int32(0)),
                       stream=s)
        return (n.disp, np.int32(n.width_px), np.int32(n.height_px))

    def _near_blocks(self, block_px: int, erode_px: int) -> np.ndarray:
        f = self._preview_factor
        if f > 1:
            _check_block_px(block_px, f)
            src = self._memory_host if erode_px else self._preview_host
            return src if block_px == f else block_max(src, block_px // f)
        return block_max(self._host_disparity(), block_px, erode_px)

    def _host_disparity(self) -> np.ndarray:
        if self._preview_factor > 1:
            return self._preview_host.copy()
        d = self._disp_host
        out = d.astype(np.float32)
        if self.disparity_scale != 1:
            out *= np.float32(1.0 / self.disparity_scale)  # exact: a power of two
        out[d < 0] = np.nan
        return out

    def _recover(self) -> None:
        """After a CUDA error: forget graphs and zero the histogram state a half-run kernel left."""
        self._graphs.clear()
        self._frame_graphs.clear()
        try:
            with self._device:
                self._copy_stream.synchronize()
                self._stream.synchronize()
                self._unregister()
                self._hist.fill(0)
                self._counter.fill(0)
                if self.obstacle_layout is not None:
                    self._od_hist.fill(0)
                    self._od_counts.fill(0)
        except Exception as err:  # the context may be unusable; the next frame reports it
            log.error("GPU estimator could not reset its state after an error: %s", err)


def _check_block_px(block_px: int, preview_factor: int) -> None:
    """The map's blocks are built from the device's preview blocks: a multiple of their size."""
    if preview_factor >= 2 and block_px % preview_factor != 0:
        raise ConfigError(
            f"planner.block_px ({block_px}) must be a multiple of gpu.disparity_preview_downsample "
            f"({preview_factor}): the GPU reduces the disparity to blocks of that size"
        )


class _CopyCrew:
    """``size - 1`` persistent threads plus the caller run one job each, in parallel, per frame.

    Started once (no per-frame thread or future objects); NumPy's copy and CuPy's memcpyAsync release
    the GIL, so the copies run on several cores. Each worker makes the estimator's device current once.
    """

    def __init__(self, size: int, device_id: int):
        self.size = size
        self._jobs: list[Callable[[], Any] | None] = [None] * size
        self._errors: list[BaseException | None] = [None] * size
        self._start = [threading.Event() for _ in range(size)]
        self._done = [threading.Event() for _ in range(size)]
        self._stop = False
        self._threads = [
            threading.Thread(target=self._work, args=(i, device_id), name=f"companion-upload-{i}", daemon=True)
            for i in range(1, size)
        ]
        for t in self._threads:
            t.start()

    def _work(self, i: int, device_id: int) -> None:
        import cupy

        cupy.cuda.runtime.setDevice(device_id)
        while True:
            self._start[i].wait()
            self._start[i].clear()
            if self._stop:
                return
            try:
                job = self._jobs[i]
                if job is not None:
                    job()
            except BaseException as err:  # handed to the caller of run()
                self._errors[i] = err
            finally:
                self._done[i].set()

    def run(self, jobs: list[Callable[[], Any]]) -> None:
        """Run ``jobs[0]`` here and ``jobs[i]`` on worker i; return when all are done (re-raising)."""
        for i in range(1, self.size):
            self._jobs[i] = jobs[i]
            self._start[i].set()
        try:
            jobs[0]()
        finally:
            for i in range(1, self.size):
                self._done[i].wait()
                self._done[i].clear()
        for i in range(1, self.size):
            err, self._errors[i] = self._errors[i], None
            if err is not None:
                raise err

    def close(self) -> None:
        self._stop = True
        for i in range(1, self.size):
            self._start[i].set()
        for t in self._threads:
            t.join(timeout=1.0)


class _Direct:
    """Stands in for a graph when capture is unavailable: ``launch`` queues the kernels directly."""

    def __init__(self, est: CupyRegionEstimator, k: int, channels: int, swapped: bool, want_disparity: bool, erode: int):
        self._est, self._args = est, (k, channels, swapped, want_disparity, erode)

    def launch(self, stream: Any) -> None:
        self._est._enqueue_band(*self._args)


@dataclass(frozen=True)
class _Band:
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


@dataclass(frozen=True)
class _Near:
    """The near-range check's coarse pair on the device: its plan and module (the SGM kernels built
    for ``width_px`` × ``height_px``), the shrunk eyes (uint8, ``pitch_bytes`` a row) and the SGM
    buffers; ``disp`` (int16 × 16, -1 invalid) is what the full size's ``sgm_post`` reads."""

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
    hist: Any
    counter: Any
    result: Any


@dataclass(frozen=True)
class _Source:
    """Where one frame's bytes come from: host copy into ``staging`` (None: no copy), DMA source, and
    where the kernels then read them."""

    frame: np.ndarray
    staging: np.ndarray
    copy: Callable[[np.ndarray, np.ndarray], Any] | None
    dma_ptr: int
    swapped: bool
    zero_copy: bool
    kernel_ptr: int  # where the kernels read the frame (the device copy, or a mapped buffer in place)

