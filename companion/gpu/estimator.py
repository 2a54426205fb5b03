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
``sgm_post`` (left-right check, median, the disparity image and the 9 region depths; with peak removal on, in
two stages around ``sgm_peaks_*``, which find the disparity's segments), exactly
:mod:`companion.core.disparity.sgm`'s rules. Before ``sgm_post``, the near-range check (rule 11):
``sgm_shrink`` shrinks the rectified pair 4 times and a second module of the same kernels, built for
that size and half the disparities, matches it; ``sgm_post`` then reads its disparity.

Each band's GPU work is captured once as a CUDA graph and replayed. The results equal
:class:`~companion.core.estimator.CpuRegionEstimator` with the ``reference`` backend and the same matcher.

The estimator's parts: :mod:`~companion.gpu.upload` (step 1), :mod:`~companion.gpu.launch` (steps 2
and 3, the graphs), :mod:`~companion.gpu.bands` (the row bands), :mod:`~companion.gpu.near` (the
near-range check's coarse pair) and :mod:`~companion.gpu.nvrtc` (the kernel sources, compiled once
per shape).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.config import CompanionConfig
from companion.core.disparity.sgm import SUBPIXEL_SCALE
from companion.core.geometry import StereoGeometry
from companion.core.estimator import RegionEstimate
from companion.core.obstacle import N_BINS, ObstacleDistance, ObstacleLayout, obstacle_layout
from companion.core.rectifier import make_rectifier
from companion.core.regions import RegionLayout, region_layout
from companion.core.stereo import split_frame
from companion.core.types import N_REGIONS, RegionDepths
from companion.errors import BackendError
from companion.gpu.bands import Band, plan_bands
from companion.gpu.launch import BandLaunch, check_block_px
from companion.gpu.near import NearPair, build_near_pair
from companion.gpu.nvrtc import import_cupy, obstacle_module, sgm_module, stereo_module
from companion.gpu.plan import (
    OBSTACLE_HIST_BINS,
    DisparityPlan,
    SgmPlan,
    obstacle_slices,
    plan_disparity,
    plan_sgm,
)
from companion.gpu.upload import CopyCrew, FrameUpload

log = logging.getLogger(__name__)

Clock = Callable[[], float]


class CupyRegionEstimator(FrameUpload, BandLaunch):
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
        cp = import_cupy()
        self._cp = cp
        self.width_px = int(width_px)
        self.height_px = int(height_px)
        self._clock = clock
        self._gpu_cfg = cfg.gpu
        self._regions_cfg = cfg.regions
        check_block_px(cfg.planner.block_px, cfg.gpu.disparity_preview_downsample)
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
        self._match_args = (
            np.uint32(st.uniqueness_ratio_pct),
            np.uint32(st.texture_threshold_grey * st.block_size_px**2),
        )
        self._module = stereo_module(cp, p, self.layout.row_edges, self.layout.col_edges)
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
        self._near: NearPair | None = None
        if self.sgm_plan is not None:
            sp = self.sgm_plan
            self._sgm_module = sgm_module(cp, sp, p.pitch_bytes, self.layout.row_edges, self.layout.col_edges)
            sget = self._sgm_module.get_function
            self._k_sgm = {name: sget(name) for name in ("sgm_census", "sgm_paths", "sgm_wta", "sgm_post", "sgm_shrink",
                                                         "sgm_peaks_init", "sgm_peaks_link", "sgm_peaks_count")}
            self._sgm_args = (
                np.uint32(st.sgm_p1),
                np.uint32(st.sgm_p2),
                np.uint32(st.sgm_uniqueness_ratio_pct),
                np.int32(st.sgm_lr_max_diff_px),
                np.int32(1 if st.sgm_median else 0),
            )
            # rule 10's peak removal: the largest segment removed (0 = off) and the link tolerance, v units
            self._peak_args = (np.int32(st.speckle_window_px), np.int32(SUBPIXEL_SCALE * st.speckle_range_px))
            self._near = build_near_pair(cp, cfg, self.width_px, self.height_px, self.sm_count)

        if self.obstacle_layout is not None:
            lay = self.obstacle_layout
            self._od_module = obstacle_module(cp)
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
        self._bands: list[Band] = plan_bands(
            p, self.sgm_plan is not None, h, rectifier, cfg.gpu, self.sm_count, self.blocks_per_sm
        )
        self._total_blocks = np.uint32(sum(b.grid[0] * b.grid[1] for b in self._bands))

        self._stream = cp.cuda.Stream(non_blocking=True)  # compute
        self._copy_stream = cp.cuda.Stream(non_blocking=True)  # host-to-device DMA
        self._band_events = [cp.cuda.Event(disable_timing=True) for _ in self._bands]
        self._build_staging()

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
            # rule 10's peak removal: each pixel's segment label and each segment's count
            self._peak_labels = cp.zeros(h * w, dtype=cp.uint32)
            self._peak_counts = cp.zeros(h * w, dtype=cp.uint32)
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
        self._build_graphs()
        n_threads = self._gpu_cfg.host_copy_threads
        self._crew = CopyCrew(n_threads, self._device.id) if n_threads > 1 else None
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

    # ----------------------------------------------------------------------------------------------
    # per frame (the frame's way to the device: FrameUpload; the kernels: BandLaunch)

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
            BackendError: a CUDA error; its context's ``device_lost`` is True where the error left
                the GPU unusable in this process (an illegal address, a launch failure), so that
                the caller matches on the CPU from then on.
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
            if self._recover():
                raise BackendError(f"CUDA error in the GPU estimator: {err}", device_lost=False) from None
            # A fault such as an illegal address leaves the context unusable for the rest of the process.
            raise BackendError(
                f"CUDA error in the GPU estimator: {err}; the GPU is unusable in this process", device_lost=True
            ) from None
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

    def _recover(self) -> bool:
        """After a CUDA error: forget graphs and zero the histogram state a half-run kernel left.
        False when that fails: the error was one that leaves the context unusable (it is sticky)."""
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
        except Exception as err:  # noqa: BLE001 - any failure here means the context is gone
            log.error("GPU estimator could not reset its state after an error: %s", err)
            return False
        return True
