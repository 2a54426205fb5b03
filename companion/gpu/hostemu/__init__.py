"""Run the CUDA kernels of ``stereo.cu`` on the CPU, bit for bit (a development tool, no GPU needed).

The kernel source is compiled as C++ (g++ with C++20) against a small emulation of the CUDA subset it
uses (``cuda_emu.h``): every CUDA thread is a ucontext fiber, ``__syncthreads``/``__syncwarp`` and the
warp shuffles are cooperative barriers, and the scheduler picks a random runnable fiber at each yield,
so a missing barrier shows up as a wrong result. Slow (one core, seconds per small image) but it runs
the exact kernel code, which made it possible to check every configuration against the NumPy reference
before spending GPU time. ``python -m companion.gpu.hostemu`` runs a self-check.

Not imported by the package; needs ``g++`` on the PATH. tests/test_gpu_kernels_on_cpu.py runs it in CI,
which has no GPU, so the kernel source itself is checked against the reference on every change.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from companion.core.disparity.sgm import SUBPIXEL_SCALE, near_range_shape
from companion.gpu.plan import (
    OBSTACLE_HIST_BINS,
    SGM_PATH_THREADS,
    SGM_PEAK_THREADS,
    kernel_defines,
    obstacle_defines,
    obstacle_slices,
    plan_disparity,
    plan_sgm,
    sgm_defines,
    sgm_pitch_bytes,
)

_HERE = Path(__file__).resolve().parent
_KERNEL = _HERE.parent / "kernels" / "stereo.cu"
_SGM_KERNEL = _HERE.parent / "kernels" / "sgm.cu"


#: The folder of the compiled kernels, when set (tests give each run its own); else one in the
#: temporary directory, shared between runs as a cache.
BUILD_DIR_ENV = "COMPANION_HOSTEMU_DIR"


def _build_dir() -> Path:
    d = Path(os.environ.get(BUILD_DIR_ENV) or Path(tempfile.gettempdir()) / "companion-hostemu")
    d.mkdir(exist_ok=True)
    return d


def _object() -> Path:
    obj = _build_dir() / "cuda_emu.o"
    src = _HERE / "cuda_emu.cpp"
    if not obj.exists() or obj.stat().st_mtime < max(src.stat().st_mtime, (_HERE / "cuda_emu.h").stat().st_mtime):
        subprocess.run(
            ["g++", "-O1", "-std=c++20", "-fno-strict-aliasing", "-fPIC", "-c", str(src), "-o", str(obj)], check=True
        )
    return obj


def _build(src: str, harness: str) -> ctypes.CDLL:
    """Compile ``src`` (the #defines and a kernel file) with ``harness`` into a cached shared library."""
    key = hashlib.sha1((src + (_HERE / harness).read_text()).encode()).hexdigest()[:16]
    cu = _build_dir() / f"k_{key}.cu"
    so = _build_dir() / f"k_{key}.so"
    if not so.exists():
        cu.write_text(src, encoding="utf-8")
        tmp = so.with_suffix(f".{os.getpid()}.tmp")
        subprocess.run(
            ["g++", "-O1", "-std=c++20", "-fno-strict-aliasing", "-fPIC", "-shared", "-w",
             f'-DKERNEL_FILE="{cu}"', f"-I{_HERE}", str(_HERE / harness), str(_object()), "-o", str(tmp)],
            check=True,
        )
        tmp.replace(so)
    return ctypes.CDLL(str(so))


class HostKernels:
    """The kernels of one (size, D, b, uniqueness, texture, region layout), compiled for the CPU.

    Args:
        width_px, height_px: eye size, px.
        num_disparities, block_size, uniqueness_ratio_pct, texture_threshold_grey: matcher settings.
        row_edges, col_edges: the region layout's edges (4 ints each).
    """

    def __init__(
        self,
        width_px: int,
        height_px: int,
        num_disparities: int,
        block_size: int,
        uniqueness_ratio_pct: int,
        texture_threshold_grey: int,
        row_edges: Any,
        col_edges: Any,
    ):
        self.plan = p = plan_disparity(width_px, height_px, num_disparities, block_size)
        src = kernel_defines(p, row_edges, col_edges) + _KERNEL.read_text(encoding="utf-8")
        self._lib = _build(src, "harness.cpp")
        self.w, self.h, self.D = width_px, height_px, num_disparities
        self.uniq, self.texmin = int(uniqueness_ratio_pct), int(texture_threshold_grey) * block_size**2

    @staticmethod
    def _ptr(a: np.ndarray) -> ctypes.c_void_p:
        return ctypes.c_void_p(a.ctypes.data)

    def _pitched(self, img: np.ndarray) -> np.ndarray:
        out = np.zeros((self.h, self.plan.pitch_bytes), np.uint8)
        out[:, : self.w] = img
        return out

    def disparity(
        self,
        left: np.ndarray,
        right: np.ndarray,
        rows_per_block: int = 8,
        bands: int = 1,
        fused: bool = True,
        fb: float = 50.0,
        pct: float = 2.0,
        min_valid: float = 0.1,
        max_depth: float = 20.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """int16 disparity (-1 invalid) and the 18 region results (9 depths, 9 valid fractions).

        ``bands`` > 1 launches the fast kernel once per row band, like the estimator's pipeline;
        ``fused=False`` runs the disparity kernel without histograms, then ``regions_from_disp``.
        """
        p = self.plan
        rl, rr = self._pitched(left), self._pitched(right)
        disp = np.full((self.h, self.w), -1, np.int16)
        hist = np.zeros(9 * self.D, np.uint32)
        counter = np.zeros(1, np.uint32)
        result = np.full(18, -7.0)
        d, f32, u32 = ctypes.c_double, ctypes.c_float, ctypes.c_uint32
        if p.fast:
            k = bands if p.valid_rows >= 2 * bands else 1
            outs = [p.y_start + (p.valid_rows * i) // k for i in range(k + 1)] if p.valid_rows else [p.y_start, p.y_end]
            grids = [max(1, -(-(outs[i + 1] - outs[i]) // rows_per_block)) for i in range(len(outs) - 1)]
            total = p.tiles_x * sum(grids)
            for i, gy in enumerate(grids):
                self._lib.run_fast(
                    1 if fused else 2, self._ptr(rl), self._ptr(rr), self._ptr(disp), self._ptr(hist),
                    self._ptr(counter), self._ptr(result), outs[i], outs[i + 1], rows_per_block, u32(total),
                    u32(self.uniq), u32(self.texmin), f32(fb), d(pct), d(min_valid), d(max_depth), p.tiles_x, gy,
                )
        else:
            self._lib.run_naive(
                self._ptr(rl), self._ptr(rr), self._ptr(disp), u32(self.uniq), u32(self.texmin),
                max(1, -(-p.valid_cols // 64)), max(1, p.valid_rows), 64,
            )
        if not fused or not p.fast:
            self._lib.run_regions(
                self._ptr(disp), self._ptr(hist), self._ptr(counter), self._ptr(result), rows_per_block,
                f32(fb), d(pct), d(min_valid), d(max_depth), max(1, -(-p.valid_rows // rows_per_block)), 128,
            )
        if counter[0] != 0 or hist.any():
            raise AssertionError("the last block did not reset the histogram state")
        return disp, result

    def grey(self, frame: np.ndarray, rgb: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Grey eyes (uint8 ``(H, W)`` each) of a side-by-side frame; ``rgb``: channels are RGB(A)."""
        ch = 1 if frame.ndim == 2 else frame.shape[2]
        code = ch + (10 if rgb and ch > 1 else 0)
        out_l = np.full((self.h, self.plan.pitch_bytes), 0xAB, np.uint8)
        out_r = out_l.copy()
        f = np.ascontiguousarray(frame)
        self._lib.run_grey(code, self._ptr(f), self._ptr(out_l), self._ptr(out_r), -(-(-(-self.w // 4)) // 32), 32, 0, self.h)
        return out_l[:, : self.w], out_r[:, : self.w]

    def remap(self, grey_l: np.ndarray, grey_r: np.ndarray, maps: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Rectified eyes from raw grey eyes and the four float32 maps (left x, left y, right x, right y)."""
        rl, rr = self._pitched(grey_l), self._pitched(grey_r)
        out_l = np.full((self.h, self.plan.pitch_bytes), 0xAB, np.uint8)
        out_r = out_l.copy()
        m = [np.ascontiguousarray(a, dtype=np.float32) for a in maps]
        self._lib.run_remap(
            self._ptr(rl), self._ptr(rr), *[self._ptr(a) for a in m], self._ptr(out_l), self._ptr(out_r),
            -(-self.w // 64), 64, 0, self.h,
        )
        return out_l[:, : self.w], out_r[:, : self.w]

    def memory_blocks(self, disparity: np.ndarray, factor: int, erode_px: int) -> np.ndarray:
        """``memory_max`` of an int16 disparity image (``(H, W)``, -1 invalid): float32
        ``(ceil(H/f), ceil(W/f))``, px, NaN none."""
        d = np.ascontiguousarray(disparity, dtype=np.int16)
        oh, ow = -(-self.h // factor), -(-self.w // factor)
        out = np.full((oh, ow), -7.0, np.float32)
        self._lib.run_memory(self._ptr(d), self._ptr(out), int(factor), ow, oh, int(erode_px), -(-ow // 32), 32)
        return out


class HostSgmKernels:
    """The SGM kernels (``sgm.cu``) of one (size, D, paths, region layout), compiled for the CPU.

    Args:
        width_px, height_px: eye size, px.
        num_disparities: ``D``.
        paths: 4 or 8.
        row_edges, col_edges: the region layout's edges (4 ints each).
        lanes_per_line: force the lane layout (0: the plan's choice).
        prefetch_steps: force ``sgm_paths``' load distance (0: the plan's choice).
    """

    def __init__(self, width_px: int, height_px: int, num_disparities: int, paths: int, row_edges: Any,
                 col_edges: Any, lanes_per_line: int = 0, prefetch_steps: int = 0):
        self.plan = p = plan_sgm(width_px, height_px, num_disparities, paths, row_edges, lanes_per_line,
                                 prefetch_steps)
        self.pitch = sgm_pitch_bytes(width_px)
        src = sgm_defines(p, self.pitch, row_edges, col_edges) + _SGM_KERNEL.read_text(encoding="utf-8")
        self._lib = _build(src, "harness_sgm.cpp")
        self.w, self.h = width_px, height_px
        self._args = (num_disparities, paths, lanes_per_line, prefetch_steps)
        self._coarse: HostSgmKernels | None = None

    def coarse(self) -> HostSgmKernels | None:
        """The kernels of the near-range check's coarse pair (reference rule 11), None where it is skipped."""
        D, paths, lanes, prefetch = self._args
        shape = near_range_shape(self.h, self.w, D)
        if shape is None:
            return None
        if self._coarse is None:
            hc, wc, dc = shape
            self._coarse = HostSgmKernels(wc, hc, dc, paths, [0, hc // 3, 2 * hc // 3, hc],
                                          [0, wc // 3, 2 * wc // 3, wc], lanes, prefetch)
        return self._coarse

    @staticmethod
    def _ptr(a: np.ndarray) -> ctypes.c_void_p:
        return ctypes.c_void_p(a.ctypes.data)

    def run(
        self,
        left: np.ndarray,
        right: np.ndarray,
        p1: int,
        p2: int,
        uniqueness_ratio_pct: int,
        lr_max_diff_px: int,
        median: bool,
        fb: float = 50.0,
        pct: float = 2.0,
        min_valid: float = 0.1,
        max_depth: float = 20.0,
        census_splits: tuple[int, ...] = (),
        near_range: bool = True,
        speckle_window_px: int = 0,
        speckle_range_px: int = 2,
    ) -> dict[str, np.ndarray]:
        """Every stage's output: ``census_left``/``census_right`` (uint64), ``volumes`` (uint8
        ``(paths, H, W, DPAD)``), ``winner`` (int32), ``right_keys`` (uint32), ``disparity`` (int16 × 16,
        -1 invalid) and ``regions`` (9 depths, 9 valid fractions); with ``near_range`` (the
        estimator's way) also ``coarse_left``/``coarse_right`` (the shrunk pair, uint8) and
        ``coarse_disparity`` (int16 × 16) where the check runs. ``census_splits``: rows where the
        census is cut into separate launches (the estimator's row bands). ``speckle_window_px`` > 0:
        rule 10's peak removal, ``sgm_post`` in two stages around the ``sgm_peaks_*`` kernels, as the
        estimator runs them."""
        p, w, h = self.plan, self.w, self.h
        u32, f32, d = ctypes.c_uint32, ctypes.c_float, ctypes.c_double
        rl = np.zeros((h, self.pitch), np.uint8)
        rr = np.zeros((h, self.pitch), np.uint8)
        rl[:, :w], rr[:, :w] = left, right
        pad = p.census_pad_px
        cen = _zeros_aligned((3, h, p.census_stride_px), np.uint64)  # as on the device: zero padding, 16-B aligned
        vols = np.full((p.paths, h, w, p.dpad), 0xEE, np.uint8)
        dl = np.full((h, w), -7, np.int32)
        drkey = np.full((h, w), 7, np.uint32)  # sgm_census resets it
        disp = np.full((h, w), -7, np.int16)
        hist = np.zeros(9 * p.nbins, np.uint32)
        counter = np.zeros(1, np.uint32)
        result = np.full(18, -7.0)
        # the census in pieces of rows, as the estimator runs it per row band
        edges = [0, *sorted({int(e) for e in census_splits if 0 < int(e) < h}), h]
        for y_lo, y_hi in zip(edges, edges[1:]):
            gx, gy, _ = p.census_grid(y_hi - y_lo)
            self._lib.run_census(self._ptr(rl), self._ptr(rr), self._ptr(cen), self._ptr(drkey), y_lo, y_hi, gx, gy)
        warps = SGM_PATH_THREADS // 32
        self._lib.run_paths(self._ptr(cen), self._ptr(vols), u32(p1), u32(p2), -(-p.path_tasks // warps))
        self._lib.run_wta(self._ptr(vols), self._ptr(dl), self._ptr(drkey), u32(uniqueness_ratio_pct),
                          -(-p.wta_tasks // warps))
        extra: dict[str, np.ndarray] = {}
        near, nw, nh = ctypes.c_void_p(0), 0, 0
        coarse = self.coarse() if near_range else None
        if coarse is not None:
            # the estimator's order: the coarse pair shrunk by this module's kernel, matched whole by the
            # coarse module, then this module's post reads its disparity
            cl = np.full((coarse.h, coarse.pitch), 0xAB, np.uint8)
            cr = cl.copy()
            self._lib.run_shrink(self._ptr(rl), self._ptr(rr), self._ptr(cl), self._ptr(cr), coarse.w, coarse.h,
                                 coarse.pitch)
            sub = coarse.run(cl[:, : coarse.w], cr[:, : coarse.w], p1, p2, uniqueness_ratio_pct, lr_max_diff_px,
                             median, near_range=False, speckle_window_px=speckle_window_px,
                             speckle_range_px=speckle_range_px)
            cd = np.ascontiguousarray(sub["disparity"])
            extra = {"coarse_left": cl[:, : coarse.w], "coarse_right": cr[:, : coarse.w], "coarse_disparity": cd}
            near, nw, nh = self._ptr(cd), coarse.w, coarse.h
        lab = np.full(h * w, 0xDEADBEEF, np.uint32)  # sgm_peaks_init sets them
        cnt = np.full(h * w, 77, np.uint32)
        post = (self._ptr(dl), self._ptr(drkey), self._ptr(disp), self._ptr(hist), self._ptr(counter),
                self._ptr(result), int(lr_max_diff_px), int(bool(median)), f32(fb), d(pct), d(min_valid),
                d(max_depth), near, nw, nh)
        peaks = (self._ptr(lab), self._ptr(cnt), int(speckle_window_px))
        if speckle_window_px > 0:
            self._lib.run_post(*post, 1, *peaks, p.post_blocks)
            self._lib.run_peaks(self._ptr(disp), self._ptr(lab), self._ptr(cnt), SUBPIXEL_SCALE * int(speckle_range_px),
                                -(-h * w // SGM_PEAK_THREADS))
            self._lib.run_post(*post, 2, *peaks, p.post_blocks)
        else:
            self._lib.run_post(*post, 0, *peaks, p.post_blocks)
        if counter[0] != 0 or hist.any():
            raise AssertionError("the last block did not reset the histogram state")
        if cen[:, :, :pad].any() or cen[:2, :, pad + w :].any():
            raise AssertionError("sgm_census wrote outside the images")
        if not np.array_equal(cen[2, :, pad + 1 : pad + 1 + w], cen[1, :, pad : pad + w]):
            raise AssertionError("the shifted copy of the right census differs from it")
        return {"census_left": cen[0, :, pad : pad + w], "census_right": cen[1, :, pad : pad + w], "volumes": vols, "winner": dl, "right_keys": drkey,
                "disparity": disp, "regions": result, **extra}


def _zeros_aligned(shape: tuple[int, ...], dtype: type, align: int = 256) -> np.ndarray:
    """Zeros whose first byte is ``align``-byte aligned (CuPy's allocations are 256-byte aligned; the
    kernels' 16-byte loads rely on it)."""
    n = int(np.prod(shape)) * np.dtype(dtype).itemsize
    raw = np.zeros(n + align, np.uint8)
    off = (-raw.ctypes.data) % align
    return raw[off : off + n].view(dtype).reshape(shape)


class HostObstacleKernel:
    """The OBSTACLE_DISTANCE kernel (``obstacle.cu``) compiled for the CPU, for one block size.

    Args:
        threads: threads per block (``OD_THREADS``).
    """

    def __init__(self, threads: int = 256) -> None:
        self.threads = int(threads)
        src = obstacle_defines(self.threads) + (_HERE.parent / "kernels" / "obstacle.cu").read_text(encoding="utf-8")
        self._lib = _build(src, "harness_obstacle.cpp")

    def run(self, disparity: np.ndarray, scale: int, layout: Any, slices: int | None = None) -> np.ndarray:
        """uint16 ``(72,)`` bins of an int16 disparity (px × ``scale``, -1 invalid) with an
        :class:`~companion.core.obstacle.ObstacleLayout`; ``slices``: row slices per bin (default: the
        estimator's choice for the height)."""
        disp = np.ascontiguousarray(disparity, dtype=np.int16)
        h, w = disp.shape
        thr = np.ascontiguousarray(layout.row_threshold_px, dtype=np.float32)
        fbk = np.ascontiguousarray(layout.column_fbk, dtype=np.float32)
        cols = np.ascontiguousarray(layout.bin_columns, dtype=np.int32).reshape(-1)
        out = np.full(72, 0xBEEF, np.uint16)
        hist = np.zeros(72 * OBSTACLE_HIST_BINS, np.uint32)
        counts = np.zeros(72 * 4, np.uint32)
        ptr = lambda a: ctypes.c_void_p(a.ctypes.data)  # noqa: E731
        self._lib.run_obstacle(
            ptr(disp), w, h, ctypes.c_float(1.0 / scale), ptr(thr), ptr(fbk), ptr(cols),
            ctypes.c_double(layout.percentile_pct), int(layout.min_points), ctypes.c_double(layout.min_valid_fraction),
            ctypes.c_float(float(layout.max_distance_m)), int(layout.min_distance_cm), int(layout.max_distance_cm),
            ptr(hist), ptr(counts), ptr(out), self.threads, obstacle_slices(h) if slices is None else int(slices),
        )
        if hist.any() or counts.any():
            raise AssertionError("the bins' last blocks did not reset the totals")
        return out
