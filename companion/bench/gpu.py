"""``companion bench --backend cupy``: the GPU path against OpenCV StereoBM and StereoSGBM on all host cores.

``--matcher sgm`` (the default) times the semi-global matcher (``--sgm-paths`` 4 or 8), ``--matcher
sad`` the SAD block matcher. For the SGM matcher the per-kernel times are its four kernels (census,
first-pass paths, last path with the winner and the left-right check, median with the regions) and the
device memory its buffers take.

For each size (default 672x376 with 64 disparities and 1280x720 with 128, block 9) on the same
rendered frames:

* **stages** (CUDA events, ``gpu.stage_timing``): host-to-device copy, grey + rectification,
  disparity with the fused regions, device-to-host copy; median and p99;
* **kernels alone** (CUDA events around each launch, inputs already on the device): the fused
  disparity+regions kernel, the same kernel without the histograms, and the unfused pair
  (disparity kernel, then a regions kernel over the disparity image);
* **whole frame** (host wall clock): a pageable NumPy frame in, 9 region depths on the host out,
  for a few upload settings (row bands, copy threads); the default config's figure is the headline;
* **OpenCV StereoBM** with ``cv2.setNumThreads(os.cpu_count())`` on the same frames (grey + BM), and
  the CPU pipeline (``opencv-bm`` estimator, whole frame); the ratios against the GPU whole frame;
* **device ceilings** measured once: device-to-device copy bandwidth, pinned and pageable
  host-to-device bandwidth, and the host's copy bandwidth from pageable memory; and what they imply
  for the disparity kernel (bytes moved over bandwidth versus its time, and the instruction budget
  its time leaves per pixel and disparity against the issue rate).

Prints a table and returns every figure as a dict (``--json`` writes it).
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from companion.bench.common import BenchSize, rendered_frames, stats_ms, write_bench_calibration
from companion.config import CompanionConfig
from companion.config.core import StereoConfig
from companion.core.disparity import OpenCVSGBMMatcher
from companion.core.estimator import CpuRegionEstimator
from companion.core.stereo import split_side_by_side, to_grey
from companion.gpu import CupyRegionEstimator
from companion.gpu.plan import SGM_CENSUS_TILE
from companion.report import format_table, machine_description

#: Upload settings tried for the whole-frame figure (gpu config overrides), besides the default.
UPLOAD_VARIANTS: tuple[dict[str, Any], ...] = (
    {"pipeline_bands": 1},
    {"pipeline_bands": 2},
    {"pipeline_bands": 4},
    {"pipeline_bands": 2, "host_copy_threads": 2},
    {"pipeline_bands": 2, "host_copy_threads": 4},
    {"register_frames": True},
    {"host_copy_engine": "opencv", "pipeline_bands": 1},
    {"host_copy_engine": "opencv", "pipeline_bands": 2},
    {"host_copy_engine": "opencv", "pipeline_bands": 3},
    {"host_copy_engine": "opencv", "pipeline_bands": 4},
)


def _variant_name(opts: dict[str, Any]) -> str:
    return ",".join(
        f"{k.replace('pipeline_', '').replace('host_copy_', '').replace('_frames', '')}="
        f"{v if isinstance(v, str) else int(v)}"
        for k, v in opts.items()
    )

#: Lane-instructions per (pixel, disparity) of the fused kernel at 1280x720, D=128, b=9 on sm_90:
#: Nsight Compute counted 1.679e9 thread-instructions (smsp__thread_inst_executed.sum) for 1.0435e8
#: (pixel, disparity) pairs on an H100 (2026-11-21), warm-up rows and region finalisation included.
#: The measured time is compared with this count at the device's issue rate.
SASS_LANE_INSTR_PER_PX_D = 16.1


#: Upload settings tried for the SGM matcher's whole-frame figure (its kernels dominate; fewer variants).
SGM_UPLOAD_VARIANTS: tuple[dict[str, Any], ...] = (
    {"host_copy_engine": "opencv", "pipeline_bands": 1},
    {"host_copy_engine": "opencv", "pipeline_bands": 4},
    {"host_copy_engine": "numpy", "pipeline_bands": 2},
)


def _cfg(size: BenchSize, calib: Path | None, matcher: str = "sad", sgm_paths: int = 4, **gpu: Any) -> Any:
    """The benchmark config; ``calib``: a calibration file (the remap is timed) or None (identity)."""
    calibration: dict[str, Any] = {"ideal_hfov_deg": 87.0}
    if calib is not None:
        calibration["file"] = str(calib)
    return CompanionConfig.model_validate(
        {
            "stereo": {
                "backend": "cupy",
                "matcher": matcher,
                "sgm_paths": sgm_paths,
                "num_disparities": size.num_disparities,
                "block_size_px": 9,
            },
            "calibration": calibration,
            "gpu": gpu,
        }
    )


def _sgm_kernel_times(est: Any, cp: Any, n: int) -> dict[str, dict[str, float]]:
    """CUDA-event times of each SGM kernel, and of the four together, on the estimator's last rectified pair."""
    s = est._stream
    events = [cp.cuda.Event() for _ in range(6)]
    names = ("census", "paths", "wta_right", "near_range", "lr_median_peaks_regions")
    samples: dict[str, list[float]] = {k: [] for k in (*names, "sgm_total")}
    k = est._k_sgm
    sp = est.sgm_plan
    p1, p2, uniq, _, _ = est._sgm_args
    with est._device:
        for i in range(n + 10):
            events[0].record(s)
            k["sgm_census"](sp.census_grid(sp.height_px), SGM_CENSUS_TILE,
                            (est._rect_l, est._rect_r, est._census, est._right_keys, np.int32(0),
                             np.int32(sp.height_px)), stream=s)
            events[1].record(s)
            k["sgm_paths"]((-(-sp.path_tasks // 4),), (128,), (est._census, est._volumes, p1, p2), stream=s)
            events[2].record(s)
            k["sgm_wta"]((-(-sp.wta_tasks // 4),), (128,), (est._volumes, est._winner, est._right_keys, uniq),
                         stream=s)
            events[3].record(s)
            near_args = est._enqueue_near(s)  # the near-range check's coarse pair
            events[4].record(s)
            est._enqueue_post(s, near_args)  # left-right check, median, peaks, near-range fill, regions
            events[5].record(s)
            events[5].synchronize()
            if i >= 10:
                for j, name in enumerate(names):
                    samples[name].append(cp.cuda.get_elapsed_time(events[j], events[j + 1]))
                samples["sgm_total"].append(cp.cuda.get_elapsed_time(events[0], events[5]))
    return {key: stats_ms(v) for key, v in samples.items()}


def _max_sm_clock_mhz(dev: Any) -> float:
    """The SM clock the issue-rate estimate uses (device attribute, else nvidia-smi's maximum)."""
    khz = dev.attributes.get("ClockRate", 0)
    if khz and khz > 0:
        return khz / 1000.0
    import subprocess

    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=clocks.max.sm", "--format=csv,noheader,nounits", f"--id={dev.id}"],
            capture_output=True, text=True, timeout=10, check=True,
        )
        return float(out.stdout.strip().splitlines()[0])
    except (OSError, subprocess.SubprocessError, ValueError, IndexError):
        return float("nan")


def _device_ceilings(cp: Any, frame_bytes: int) -> dict[str, float]:
    """Copy bandwidths that bound the pipeline: D2D (read + write), H2D pinned and pageable, host copy."""
    out: dict[str, float] = {}
    n = 1 << 30
    a = cp.empty(n, dtype=cp.uint8)
    a.fill(1)
    b = cp.empty_like(a)
    e0, e1 = cp.cuda.Event(), cp.cuda.Event()
    times = []
    for _ in range(6):
        e0.record()
        b[...] = a
        e1.record()
        e1.synchronize()
        times.append(cp.cuda.get_elapsed_time(e0, e1))
    out["d2d_copy_GBps"] = 2 * n / (float(np.median(times[1:])) * 1e-3) / 1e9
    del a, b
    m = 64 << 20
    pinned = cp.cuda.alloc_pinned_memory(m)
    dev = cp.empty(m, dtype=cp.uint8)
    pageable = np.ones(m, dtype=np.uint8)
    s = cp.cuda.Stream(non_blocking=True)
    for label, ptr in (("h2d_pinned_GBps", pinned.ptr), ("h2d_pageable_GBps", pageable.ctypes.data)):
        times = []
        for _ in range(6):
            e0.record(s)
            cp.cuda.runtime.memcpyAsync(dev.data.ptr, ptr, m, cp.cuda.runtime.memcpyHostToDevice, s.ptr)
            e1.record(s)
            e1.synchronize()
            times.append(cp.cuda.get_elapsed_time(e0, e1))
        out[label] = m / (float(np.median(times[1:])) * 1e-3) / 1e9
    # Host copy of frame-sized buffers from a set larger than the caches (like a camera's frames).
    k = max(4, (256 << 20) // frame_bytes)
    srcs = [np.full(frame_bytes, i, dtype=np.uint8) for i in range(k)]
    dst = np.frombuffer(pinned, dtype=np.uint8, count=frame_bytes)
    times = []
    for i in range(3 * k):
        t0 = time.perf_counter()
        np.copyto(dst, srcs[i % k])
        times.append(time.perf_counter() - t0)
    out["host_copy_GBps"] = frame_bytes / float(np.median(times[k:])) / 1e9
    # The same copy split over N threads (NumPy releases the GIL), and through OpenCV's own thread
    # pool (cvtColor BGR->RGB is a parallel byte shuffle): is the host's copy bandwidth per core or
    # per machine?
    import threading

    import cv2

    for n_thr in (2, 4, 8):
        edges = [(frame_bytes * i) // n_thr for i in range(n_thr + 1)]
        times = []
        for i in range(k + 20):
            src = srcs[i % k]
            threads = [
                threading.Thread(target=np.copyto, args=(dst[a:b], src[a:b])) for a, b in zip(edges, edges[1:])
            ]
            t0 = time.perf_counter()
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            times.append(time.perf_counter() - t0)
        out[f"host_copy_{n_thr}threads_GBps"] = frame_bytes / float(np.median(times[k:])) / 1e9
    cv2.setNumThreads(os.cpu_count() or 1)
    cols = frame_bytes // 3
    times = []
    for i in range(2 * k):
        src = srcs[i % k].reshape(1, cols, 3)
        t0 = time.perf_counter()
        cv2.cvtColor(src, cv2.COLOR_BGR2RGB, dst=dst.reshape(1, cols, 3))
        times.append(time.perf_counter() - t0)
    out["host_cvtcolor_swap_GBps"] = frame_bytes / float(np.median(times[k:])) / 1e9
    # Page-locking a frame in place (cudaHostRegister) and unlocking it, per frame.
    times = []
    for i in range(2 * k):
        src = srcs[i % k]
        t0 = time.perf_counter()
        cp.cuda.runtime.hostRegister(src.ctypes.data, frame_bytes, 0)
        cp.cuda.runtime.hostUnregister(src.ctypes.data)
        times.append(time.perf_counter() - t0)
    out["register_unregister_frame_ms"] = float(np.median(times[k:])) * 1e3
    return out


def _kernel_times(est: Any, cp: Any, n: int) -> dict[str, dict[str, float]]:
    """CUDA-event times of the disparity kernels alone on the estimator's last rectified frame."""
    p = est.plan
    s = est._stream
    e0, e1 = cp.cuda.Event(), cp.cuda.Event()
    fb, pct, min_valid, max_depth = est._region_args
    band = est._bands[0]  # the stage-timing estimator runs one band: the whole frame in one launch
    grid = band.grid
    args_fused = (
        est._rect_l, est._rect_r, est._disp, est._hist, est._counter, est._result_dev,
        np.int32(band.out[0]), np.int32(band.out[1]), np.int32(band.rows_per_block),
        np.uint32(grid[0] * grid[1]), *est._match_args, fb, pct, min_valid, max_depth,
    )
    variants: dict[str, Any] = {}
    if p.fast:
        variants["fused_regions"] = lambda: est._k_fast[False](grid, (p.nt,), args_fused, stream=s)
        variants["no_regions"] = lambda: est._k_fast_unfused(grid, (p.nt,), args_fused, stream=s)

        def unfused() -> None:
            est._k_fast_unfused(grid, (p.nt,), args_fused, stream=s)
            est._k_regions(
                est._grid_regions, (256,),
                (est._disp, est._hist, est._counter, est._result_dev, np.int32(est._rows_regions),
                 fb, pct, min_valid, max_depth),
                stream=s,
            )

        variants["unfused_two_kernels"] = unfused
    out = {}
    with est._device:
        for name, launch in variants.items():
            times = []
            for i in range(n + 10):
                e0.record(s)
                launch()
                e1.record(s)
                e1.synchronize()
                if i >= 10:
                    times.append(cp.cuda.get_elapsed_time(e0, e1))
            out[name] = stats_ms(times)
    return out


def _time_in_place(
    est: Any, frames: list[np.ndarray], warmup: int, n: int, buffer: Callable[[], np.ndarray | None]
) -> dict[str, Any]:
    """Wall times of ``est.estimate`` on frames written first into ``buffer()`` (a pinned buffer the
    estimator reads in place; each frame's buffer is dropped before the next is asked for)."""
    times = []
    for i in range(warmup + n):
        buf = buffer()
        if buf is None:
            raise RuntimeError("no free frame buffer in the benchmark")
        buf[...] = frames[i % len(frames)]
        t0 = time.perf_counter()
        est.estimate(buf)
        if i >= warmup:
            times.append((time.perf_counter() - t0) * 1e3)
        del buf
    return stats_ms(times)


def _time_estimator(est: Any, frames: list[np.ndarray], warmup: int, n: int) -> tuple[dict[str, Any], dict[str, Any]]:
    wall = []
    stages: dict[str, list[float]] = {}
    for i in range(warmup + n):
        frame = frames[i % len(frames)]
        t0 = time.perf_counter()
        res = est.estimate(frame)
        t1 = time.perf_counter()
        if i >= warmup:
            wall.append((t1 - t0) * 1e3)
            for k, v in res.timings_ms.items():
                stages.setdefault(k, []).append(v)
    return stats_ms(wall), {k: stats_ms(v) for k, v in stages.items()}


def _opencv(size: BenchSize, calib: Path | None, frames: list[np.ndarray], warmup: int, n: int) -> dict[str, Any]:
    import cv2

    threads = os.cpu_count() or 1
    cv2.setNumThreads(threads)
    bm = cv2.StereoBM_create(numDisparities=size.num_disparities, blockSize=9)
    # StereoSGBM as the opencv-sgbm backend builds it (block 9, P1 = 8·81, P2 = 32·81, mode sgbm_3way,
    # which OpenCV runs on its thread pool)
    sgbm = OpenCVSGBMMatcher(StereoConfig(backend="opencv-sgbm", num_disparities=size.num_disparities))
    greys = []
    for f in frames:
        left, right = split_side_by_side(f)
        greys.append((to_grey(left), to_grey(right)))
    bm_t, grey_bm_t, sgbm_t = [], [], []
    for i in range(warmup + n):
        f = frames[i % len(frames)]
        gl, gr = greys[i % len(frames)]
        t0 = time.perf_counter()
        bm.compute(gl, gr)
        t1 = time.perf_counter()
        left, right = split_side_by_side(f)
        a, b = to_grey(left), to_grey(right)
        bm.compute(a, b)
        t2 = time.perf_counter()
        if i >= warmup:
            bm_t.append((t1 - t0) * 1e3)
            grey_bm_t.append((t2 - t1) * 1e3)
    for i in range(warmup + min(n, 100)):
        gl, gr = greys[i % len(frames)]
        t0 = time.perf_counter()
        sgbm.compute(gl, gr)
        if i >= warmup:
            sgbm_t.append((time.perf_counter() - t0) * 1e3)
    cfg = _cfg(size, calib)
    cfg = cfg.model_copy(update={"stereo": cfg.stereo.model_copy(update={"backend": "opencv-bm", "cpu_threads": 0})})
    cpu = CpuRegionEstimator(cfg, size.width_px, size.height_px)
    cpu_t = []
    for i in range(warmup + min(n, 100)):
        f = frames[i % len(frames)]
        t0 = time.perf_counter()
        cpu.estimate(f)
        t1 = time.perf_counter()
        if i >= warmup:
            cpu_t.append((t1 - t0) * 1e3)
    # A UVC camera's YUYV frame: what decoding it to BGR costs the host (camera.pixels bgr), and the
    # CPU estimator on its bytes as they come (camera.pixels luma)
    yuyv = [cv2.cvtColor(f, cv2.COLOR_BGR2YUV_YUYV) for f in frames]
    decode_t, cpu_yuyv_t = [], []
    for i in range(warmup + min(n, 100)):
        y = yuyv[i % len(yuyv)]
        t0 = time.perf_counter()
        cv2.cvtColor(y, cv2.COLOR_YUV2BGR_YUYV)
        t1 = time.perf_counter()
        cpu.estimate(y)
        t2 = time.perf_counter()
        if i >= warmup:
            decode_t.append((t1 - t0) * 1e3)
            cpu_yuyv_t.append((t2 - t1) * 1e3)
    return {
        "threads": threads,
        "stereobm": stats_ms(bm_t),
        "grey_plus_stereobm": stats_ms(grey_bm_t),
        "stereosgbm": stats_ms(sgbm_t),
        "cpu_estimator_opencv_bm": stats_ms(cpu_t),
        "yuyv_decode_to_bgr": stats_ms(decode_t),
        "cpu_estimator_opencv_bm_yuyv": stats_ms(cpu_yuyv_t),
    }


def run_gpu_bench(args: argparse.Namespace, sizes: list[BenchSize]) -> dict[str, Any]:
    """Time the GPU path and OpenCV StereoBM at each size; print a table; return the figures."""
    import cupy as cp

    n, warmup = int(args.frames), int(args.warmup)
    matcher = getattr(args, "matcher", "sgm")
    paths = int(getattr(args, "sgm_paths", 4))
    report: dict[str, Any] = {
        "date": datetime.date.today().isoformat(),
        "machine": machine_description(),
        "backend": "cupy",
        "matcher": matcher,
        "sgm_paths": paths if matcher == "sgm" else None,
        "sizes": {},
    }
    opts = {"matcher": matcher, "sgm_paths": paths}
    dev = cp.cuda.Device(0)
    props = cp.cuda.runtime.getDeviceProperties(dev.id)
    report["device"] = props["name"].decode()
    report["sm_count"] = int(dev.attributes["MultiProcessorCount"])
    report["sm_clock_mhz"] = _max_sm_clock_mhz(dev)
    print(f"machine: {report['machine']}")
    print(f"device: {report['device']}, {report['sm_count']} SMs, {report['sm_clock_mhz']:.0f} MHz max SM clock")
    largest = max(sizes, key=lambda s: s.width_px * s.height_px)
    ceilings = _device_ceilings(cp, largest.height_px * largest.width_px * 2 * 3)
    report["ceilings"] = ceilings
    report["pageable_memory_access"] = int(dev.attributes.get("PageableMemoryAccess", -1))
    print(
        "ceilings: D2D copy {d2d_copy_GBps:.0f} GB/s (read+write), H2D pinned {h2d_pinned_GBps:.1f} GB/s, "
        "H2D pageable {h2d_pageable_GBps:.1f} GB/s, host copy (1 thread) {host_copy_GBps:.1f} GB/s, "
        "register+unregister one frame {register_unregister_frame_ms:.3f} ms, host copy with threads "
        "2/4/8 {host_copy_2threads_GBps:.1f}/{host_copy_4threads_GBps:.1f}/{host_copy_8threads_GBps:.1f} GB/s "
        "(thread start included), cv2 BGR->RGB {host_cvtcolor_swap_GBps:.1f} GB/s".format(**ceilings)
        + f"; pageable memory access by kernels: {report['pageable_memory_access']}"
    )
    sys.stdout.flush()
    rows = []
    tmp = tempfile.TemporaryDirectory(prefix="companion-bench-")
    report["rectify"] = not args.no_rectify
    for size in sizes:
        calib = None if args.no_rectify else write_bench_calibration(size, Path(tmp.name))
        _, frames = rendered_frames(size, n=min(16, max(2, n + warmup)))
        entry: dict[str, Any] = {}
        # stages (CUDA events)
        import gc

        pool = cp.get_default_memory_pool()
        est = None
        gc.collect()  # the previous size's estimators go first: the difference below is this one's alone
        gc.disable()
        try:
            used_before = pool.used_bytes()
            est = CupyRegionEstimator(_cfg(size, calib, stage_timing=True, **opts), size.width_px, size.height_px)
            entry["device_memory_bytes"] = pool.used_bytes() - used_before
        finally:
            gc.enable()
        _, stages = _time_estimator(est, frames, warmup, n)
        entry["stages"] = stages
        if est.sgm_plan is not None:
            sp = est.sgm_plan
            entry["plan"] = {
                "matcher": "sgm", "paths": sp.paths, "lanes_per_line": sp.lanes_per_line,
                "words_per_lane": sp.words_per_lane, "run_px": sp.run_px, "slab_rows": sp.slab_rows, "dpad": sp.dpad,
                "prefetch_steps": sp.prefetch_steps,
                "buffers_bytes": sp.device_bytes(),
                "kernel_regs_smem": {
                    name: [int(k.attributes["num_regs"]), int(k.attributes["shared_size_bytes"])]
                    for name, k in est._k_sgm.items()
                },
            }
            entry["kernels"] = _sgm_kernel_times(est, cp, n)
            # the other lane layouts (same results; which is fastest here?)
            for lanes in (8, 16, 32):
                if lanes == sp.lanes_per_line or 4 * lanes > 4 * sp.dpad // 4 or lanes * 4 > max(16, sp.dpad):
                    continue
                alt = CupyRegionEstimator(_cfg(size, calib, stage_timing=True, sgm_lanes_per_line=lanes, **opts),
                                          size.width_px, size.height_px)
                _time_estimator(alt, frames, 2, 3)
                entry[f"kernels_lanes_{lanes}"] = _sgm_kernel_times(alt, cp, min(n, 100))
                alt.close()
            # the other load distance of the path kernel (the plan picks by warps per SM: is it right here?)
            other_pf = 2 if sp.prefetch_steps == 4 else 4
            alt = CupyRegionEstimator(_cfg(size, calib, stage_timing=True, sgm_prefetch_steps=other_pf, **opts),
                                      size.width_px, size.height_px)
            _time_estimator(alt, frames, 2, 3)
            entry[f"kernels_prefetch_{other_pf}"] = _sgm_kernel_times(alt, cp, min(n, 100))
            alt.close()
        else:
            entry["plan"] = {
                "fast": est.plan.fast, "tile_cols": est.plan.tx, "threads": est.plan.nt,
                "rows_per_block": est._bands[0].rows_per_block, "grid": list(est._bands[0].grid),
                "blocks_per_sm": est.blocks_per_sm, "smem_bytes": est.plan.smem_bytes,
            }
            entry["kernels"] = _kernel_times(est, cp, n)
        est.close()
        # whole frame: the default config first and again after the variants (the host's copy and
        # PCIe bandwidth drift within a run; the slower of the two is the headline)
        whole: dict[str, Any] = {}
        e = CupyRegionEstimator(_cfg(size, calib, **opts), size.width_px, size.height_px)
        whole["default_first"], _ = _time_estimator(e, frames, warmup, n)
        e.close()
        for variant in SGM_UPLOAD_VARIANTS if matcher == "sgm" else UPLOAD_VARIANTS:
            e = CupyRegionEstimator(_cfg(size, calib, **opts, **variant), size.width_px, size.height_px)
            whole[_variant_name(variant)], _ = _time_estimator(e, frames, warmup, n)
            e.close()
        e = CupyRegionEstimator(_cfg(size, calib, **opts), size.width_px, size.height_px)
        whole["default_last"], _ = _time_estimator(e, frames, warmup, n)
        whole["default"] = max(whole["default_first"], whole["default_last"], key=lambda v: v["median_ms"])
        # frames already in pinned memory, no host copy: the staging buffer, and a camera decoding into
        # the estimator's pool (the service's UVC path)
        staging = e.frame_buffer(3)
        whole["frame_in_staging_buffer"] = _time_in_place(e, frames, warmup, n, lambda: staging)
        pool = e.frame_pool(3)
        whole["frame_in_pool_buffer"] = _time_in_place(e, frames, warmup, n, pool.acquire)
        e.close()
        # the service's UVC path by default (camera.pixels luma): the camera's YUYV bytes in a pool buffer
        import cv2

        yuyv = [cv2.cvtColor(f, cv2.COLOR_BGR2YUV_YUYV) for f in frames]
        e = CupyRegionEstimator(_cfg(size, calib, **opts), size.width_px, size.height_px)
        pool = e.frame_pool(3, channels=2)
        whole["yuyv_frame_in_pool_buffer"] = _time_in_place(e, yuyv, warmup, n, pool.acquire)
        e.close()
        entry["whole_frame"] = whole
        entry["opencv"] = _opencv(size, calib, frames, warmup, n)
        gpu_med = whole["default"]["median_ms"]
        entry["speedup_vs_stereobm"] = entry["opencv"]["stereobm"]["median_ms"] / gpu_med
        entry["speedup_vs_grey_plus_stereobm"] = entry["opencv"]["grey_plus_stereobm"]["median_ms"] / gpu_med
        entry["speedup_vs_cpu_estimator"] = entry["opencv"]["cpu_estimator_opencv_bm"]["median_ms"] / gpu_med
        entry["speedup_vs_stereosgbm"] = entry["opencv"]["stereosgbm"]["median_ms"] / gpu_med
        # what limits the kernel
        p = est.plan
        if est.sgm_plan is None and p.fast and "fused_regions" in entry["kernels"]:
            t = entry["kernels"]["fused_regions"]["median_ms"] * 1e-3
            ty = est._bands[0].rows_per_block
            blocks = est._bands[0].grid[0] * est._bands[0].grid[1]
            bytes_in = blocks * (ty + p.block_size - 1) * (p.lww + p.rww) * 4
            bytes_total = bytes_in + 9 * p.num_disparities * 4 * blocks  # + histogram atomics (upper bound)
            px_d = p.valid_cols * p.valid_rows * p.num_disparities
            issue = report["sm_count"] * 4 * 32 * report["sm_clock_mhz"] * 1e6  # lane-instructions/s
            entry["limits"] = {
                "bytes_moved": bytes_total,
                "memory_floor_ms": bytes_total / (ceilings["d2d_copy_GBps"] * 1e9) * 1e3,
                "pixel_disparities": px_d,
                "lane_instr_budget_per_px_d_at_measured_time": issue * t / px_d,
                "sass_lane_instr_per_px_d": SASS_LANE_INSTR_PER_PX_D,
                "issue_utilisation": SASS_LANE_INSTR_PER_PX_D * px_d / (issue * t),
            }
        report["sizes"][size.label] = entry
        for k, v in stages.items():
            rows.append([size.label, f"stage {k.removesuffix('_ms')}", f"{v['median_ms']:.3f}", f"{v['p99_ms']:.3f}"])
        for k, v in entry["kernels"].items():
            rows.append([size.label, f"kernel {k}", f"{v['median_ms']:.3f}", f"{v['p99_ms']:.3f}"])
        for key in [key for key in entry if key.startswith(("kernels_lanes_", "kernels_prefetch_"))]:
            for k, v in entry[key].items():
                rows.append([size.label, f"{key.removeprefix('kernels_')} {k}", f"{v['median_ms']:.3f}",
                             f"{v['p99_ms']:.3f}"])
        for k, v in whole.items():
            if k == "default":
                continue
            rows.append([size.label, f"whole frame {k}", f"{v['median_ms']:.3f}", f"{v['p99_ms']:.3f}"])
        for k in ("stereobm", "grey_plus_stereobm", "stereosgbm", "cpu_estimator_opencv_bm", "yuyv_decode_to_bgr",
                  "cpu_estimator_opencv_bm_yuyv"):
            v = entry["opencv"][k]
            rows.append([size.label, f"cpu {k} ({entry['opencv']['threads']} thr)", f"{v['median_ms']:.3f}",
                         f"{v['p99_ms']:.3f}"])
        sys.stdout.flush()
    end = _device_ceilings(cp, largest.height_px * largest.width_px * 2 * 3)
    report["ceilings_end"] = end
    print(format_table(rows, ["size/disp", "what", "median ms", "p99 ms"]))
    print(
        f"ceilings again at the end: H2D pinned {end['h2d_pinned_GBps']:.1f} GB/s, host copy "
        f"{end['host_copy_GBps']:.1f} GB/s"
    )
    for label, entry in report["sizes"].items():
        d = entry["whole_frame"]["default"]
        line = (
            f"{label}: GPU whole frame (default config, slower of two passes) {d['median_ms']:.3f} ms median, "
            f"{d['p99_ms']:.3f} ms p99; "
            f"x{entry['speedup_vs_stereobm']:.1f} vs StereoBM alone, x{entry['speedup_vs_grey_plus_stereobm']:.1f} "
            f"vs grey+StereoBM, x{entry['speedup_vs_stereosgbm']:.1f} vs StereoSGBM, "
            f"x{entry['speedup_vs_cpu_estimator']:.1f} vs the CPU estimator; device memory "
            f"{entry['device_memory_bytes'] / 1e6:.1f} MB"
        )
        print(line)
        if "limits" in entry:
            lim = entry["limits"]
            print(
                f"  kernel limits: {lim['bytes_moved'] / 1e6:.1f} MB moved -> memory floor "
                f"{lim['memory_floor_ms'] * 1e3:.1f} us; time allows {lim['lane_instr_budget_per_px_d_at_measured_time']:.1f} "
                f"lane-instr per (px, d) vs {lim['sass_lane_instr_per_px_d']:.1f} executed: issue utilisation "
                f"{lim['issue_utilisation'] * 100:.0f}%"
            )
    sys.stdout.flush()
    tmp.cleanup()  # (on an error, TemporaryDirectory cleans up when collected)
    return report
