"""The GPU estimator's kernel launches: each band's work queued on the compute stream, and its CUDA graphs.

Band k's kernels wait for its DMA: ``grey_*`` converts its rows, ``remap_linear`` rectifies the rows
whose taps are uploaded, then the matcher: ``sad_fast_regions`` (the region histograms fused in; the
last block turns them into the 9 depths), the fallback ``sad_naive`` + ``regions_from_disp``, or SGM's
``sgm_census`` per band and the rest of ``kernels/sgm.cu`` after the last band. After the last band:
OBSTACLE_DISTANCE's bins, the results' copy back, and the preview's and the map's blocks when asked.
Each band's work is captured once as a CUDA graph and replayed (a frame read in place: one graph for
the whole frame, its DMA included).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from companion.core.blocks import block_max
from companion.errors import ConfigError
from companion.gpu.plan import (
    OBSTACLE_THREADS,
    SGM_CENSUS_TILE,
    SGM_PATH_THREADS,
    SGM_PEAK_THREADS,
    SGM_POST_THREADS,
)
from companion.gpu.upload import FrameSource

log = logging.getLogger(__name__)

#: Threads per block of the element-wise kernels (grey, remap, preview).
_EW_THREADS = 128
#: Threads per block of the fallback kernels.
_NAIVE_THREADS = 64
_REGIONS_THREADS = 256


class BandLaunch:
    """The launches of :class:`~companion.gpu.estimator.CupyRegionEstimator`: per band, the kernels
    (module doc) and the graphs that replay them.

    A part of the estimator, not used alone: it reads the compiled kernels (``_k_*``), the device
    buffers, the streams and events and the bands the estimator builds, and uploads through
    :class:`~companion.gpu.upload.FrameUpload`'s ``_upload_band``; it owns the captured graphs.
    """

    def _build_graphs(self) -> None:
        """The graphs' caches (each captured on first use) and the events of a whole frame's capture
        and of ``gpu.stage_timing``."""
        cp = self._cp
        self._graphs: dict[tuple[int, int, bool, bool, int], Any] = {}
        self._graph_ok = bool(self._gpu_cfg.use_cuda_graph) and not self._gpu_cfg.stage_timing
        # a frame read in place (no host copy): one graph for the whole frame (_frame_graph)
        self._frame_graphs: dict[tuple[int, bool, bool, int, int], Any] = {}
        self._frame_graph_ok = self._graph_ok
        self._fork_event = cp.cuda.Event(disable_timing=True)
        self._events = [cp.cuda.Event() for _ in range(5)] if self._gpu_cfg.stage_timing else []

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
                return DirectLaunch(self, k, channels, swapped, want_disparity, erode)
            self._graphs[key] = graph
        return graph

    def _frame_graph(self, src: FrameSource, channels: int, want_disparity: bool, erode: int) -> Any | None:
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
        p1, p2, uniq, _, _ = self._sgm_args
        warps = SGM_PATH_THREADS // 32
        k["sgm_paths"]((-(-sp.path_tasks // warps),), (SGM_PATH_THREADS,), (self._census, self._volumes, p1, p2),
                       stream=s)
        k["sgm_wta"]((-(-sp.wta_tasks // warps),), (SGM_PATH_THREADS,),
                     (self._volumes, self._winner, self._right_keys, uniq), stream=s)
        self._enqueue_post(s, self._enqueue_near(s))

    def _enqueue_post(self, s: Any, near_args: tuple[Any, ...]) -> None:
        """Queue the full pair's ``sgm_post`` (left-right check, median, peak removal, the near-range check
        with ``near_args`` from :meth:`_enqueue_near`, the disparity and the 9 depths) on stream ``s``."""
        sp = self.sgm_plan
        assert sp is not None
        _, _, _, lr_max, median = self._sgm_args
        fb, pct, min_valid, max_depth = self._region_args
        post = (self._winner, self._right_keys, self._disp, self._hist, self._counter, self._result_dev,
                lr_max, median, fb, pct, min_valid, max_depth, *near_args)
        peak_max, tol = self._peak_args
        _enqueue_post(self._k_sgm, sp.post_blocks, post, self._disp, self._peak_labels, self._peak_counts, peak_max,
                      tol, s)

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
        post = (n.winner, n.right_keys, n.disp, n.hist, n.counter, n.result, lr_max, median, fb, pct, min_valid,
                max_depth, np.uint64(0), np.int32(0), np.int32(0))
        peak_max, tol = self._peak_args
        _enqueue_post(nk, npl.post_blocks, post, n.disp, n.peak_labels, n.peak_counts, peak_max, tol, s)
        return (n.disp, np.int32(n.width_px), np.int32(n.height_px))

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

    # ----------------------------------------------------------------------------------------------
    # what the last band brought back, read on the host

    def _near_blocks(self, block_px: int, erode_px: int) -> np.ndarray:
        f = self._preview_factor
        if f > 1:
            check_block_px(block_px, f)
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


def _enqueue_post(k: dict[str, Any], post_blocks: int, post: tuple[Any, ...], disp: Any, labels: Any, counts: Any,
                  peak_max: Any, tol: Any, s: Any) -> None:
    """Queue ``sgm_post`` on stream ``s``: one launch without peak removal (``peak_max`` 0), else its
    first stage, the segments (``sgm_peaks_*``, one thread per pixel) and its second stage."""
    if int(peak_max) <= 0:
        k["sgm_post"]((post_blocks,), (SGM_POST_THREADS,), (*post, np.int32(0), labels, counts, np.int32(0)),
                      stream=s)
        return
    k["sgm_post"]((post_blocks,), (SGM_POST_THREADS,), (*post, np.int32(1), labels, counts, peak_max), stream=s)
    grid = (-(-int(disp.size) // SGM_PEAK_THREADS),)
    k["sgm_peaks_init"](grid, (SGM_PEAK_THREADS,), (labels, counts), stream=s)
    k["sgm_peaks_link"](grid, (SGM_PEAK_THREADS,), (disp, labels, tol), stream=s)
    k["sgm_peaks_count"](grid, (SGM_PEAK_THREADS,), (disp, labels, counts), stream=s)
    k["sgm_post"]((post_blocks,), (SGM_POST_THREADS,), (*post, np.int32(2), labels, counts, peak_max), stream=s)


def check_block_px(block_px: int, preview_factor: int) -> None:
    """The map's blocks are built from the device's preview blocks: a multiple of their size."""
    if preview_factor >= 2 and block_px % preview_factor != 0:
        raise ConfigError(
            f"planner.block_px ({block_px}) must be a multiple of gpu.disparity_preview_downsample "
            f"({preview_factor}): the GPU reduces the disparity to blocks of that size"
        )


class DirectLaunch:
    """Stands in for a graph when capture is unavailable: ``launch`` queues the kernels directly."""

    def __init__(self, est: BandLaunch, k: int, channels: int, swapped: bool, want_disparity: bool, erode: int):
        self._est, self._args = est, (k, channels, swapped, want_disparity, erode)

    def launch(self, stream: Any) -> None:
        self._est._enqueue_band(*self._args)

