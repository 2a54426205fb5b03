"""Checks of the CUDA kernel source that need no GPU: the comparator network and the plan, and, where the
CUDA toolkit's ``nvcc`` is installed, that every module compiles (the kernels run only on a device, which
CI does not have; a syntax or type error would otherwise first show as a BackendError at start-up)."""

from __future__ import annotations

import itertools
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from companion.gpu.nvrtc import kernel_source


def test_the_median_network_puts_the_five_smallest_in_order() -> None:
    """``sgm_post``'s comparator network (SGM_MED_PAIRS in sgm.cu) leaves the 5 smallest of its 9 inputs
    sorted in positions 0..4 (ranks up to 4 are the lower medians of 1..9 valid values). A comparator
    network commutes with every monotone map, so checking all 512 inputs of 0s and 1s proves it for all
    inputs (the 0-1 principle)."""
    m = re.search(r"#define SGM_MED_PAIRS ([0-9, ]+)\n", kernel_source("sgm.cu"))
    assert m is not None
    flat = [int(v) for v in m.group(1).split(",")]
    pairs = list(zip(flat[::2], flat[1::2]))
    assert all(0 <= a < b < 9 for a, b in pairs)
    for bits in itertools.product((0, 1), repeat=9):
        v = list(bits)
        for a, b in pairs:
            v[a], v[b] = min(v[a], v[b]), max(v[a], v[b])
        assert v[:5] == sorted(bits)[:5], bits


def test_the_path_kernel_loads_further_ahead_only_where_few_warps_hide_latency() -> None:
    """``plan_sgm`` picks ``SGM_PF`` 4 where ``sgm_paths`` has few warps per SM (the ZED's VGA on an H100),
    2 where it has many (HD on an H100, VGA on a 16-SM Jetson Orin) or the GPU is unknown."""
    from companion.gpu.plan import plan_sgm, sgm_defines

    def pf(w: int, h: int, d: int, paths: int = 4, **kw: int) -> int:
        return plan_sgm(w, h, d, paths, [0, h // 3, 2 * h // 3, h], **kw).prefetch_steps

    assert pf(672, 376, 64, sm_count=132) == 4  # 1048 warps: 8 per SM
    assert pf(1280, 720, 128, sm_count=132) == 2  # 4000 warps: 30 per SM
    assert pf(1280, 720, 128, paths=8, sm_count=132) == 2
    assert pf(672, 376, 64, sm_count=16) == 2  # 65 per SM
    assert pf(672, 376, 64) == 2  # unknown GPU
    assert pf(1280, 720, 128, prefetch_steps=4, sm_count=132) == 4  # the config's choice wins
    with pytest.raises(ValueError, match="prefetch_steps"):
        pf(672, 376, 64, prefetch_steps=3)
    plan = plan_sgm(672, 376, 64, 4, [0, 125, 250, 376], sm_count=132)
    assert "#define SGM_PF 4\n" in sgm_defines(plan, 688, [0, 125, 250, 376], [0, 224, 448, 672])


def _module_sources() -> dict[str, str]:
    """Each module's full source (defines + kernel file) as the estimator builds it, for the ZED's VGA
    and HD at 4 and 8 paths, 16 lanes a line, and the near-range check's coarse pairs of both; the
    regions in thirds (the layout only sets the values of the region edges' defines)."""
    from companion.core.disparity.sgm import near_range_shape
    from companion.gpu.plan import (
        OBSTACLE_THREADS,
        kernel_defines,
        obstacle_defines,
        plan_disparity,
        plan_sgm,
        sgm_defines,
        sgm_pitch_bytes,
    )

    def edges(n: int) -> list[int]:
        return [0, n // 3, 2 * n // 3, n]

    sources = {"obstacle": obstacle_defines(OBSTACLE_THREADS) + kernel_source("obstacle.cu")}
    for w, h, d, paths, lanes in ((672, 376, 64, 4, 0), (1280, 720, 128, 8, 0), (1280, 720, 128, 4, 16)):
        plan = plan_disparity(w, h, d, 9)
        sources[f"stereo-{w}x{h}-{d}"] = kernel_defines(plan, edges(h), edges(w)) + kernel_source()
        sp = plan_sgm(w, h, d, paths, edges(h), lanes, 0, 132)
        sources[f"sgm-{w}x{h}-{d}-{paths}p-{lanes}l"] = (
            sgm_defines(sp, plan.pitch_bytes, edges(h), edges(w)) + kernel_source("sgm.cu")
        )
        near = near_range_shape(h, w, d)
        assert near is not None
        hc, wc, dc = near
        npl = plan_sgm(wc, hc, dc, paths, edges(hc), 0, 0, 16)
        sources[f"near-{wc}x{hc}-{dc}-{paths}p"] = (
            sgm_defines(npl, sgm_pitch_bytes(wc), edges(hc), edges(wc)) + kernel_source("sgm.cu")
        )
    return sources


@pytest.mark.parametrize("arch", ["sm_87", "sm_90"])  # Jetson Orin; H100
def test_every_module_compiles_where_nvcc_is_installed(tmp_path: Path, arch: str) -> None:
    """nvcc with NVRTC's options (:data:`~companion.gpu.nvrtc.NVRTC_OPTIONS`) compiles every module to
    PTX, without errors, for the Jetson Orin and the H100."""
    from companion.gpu.nvrtc import NVRTC_OPTIONS

    nvcc = shutil.which("nvcc")
    if nvcc is None:
        pytest.skip("no nvcc on PATH (the CUDA toolkit)")
    for name, code in _module_sources().items():
        src = tmp_path / f"{name}.cu"
        src.write_text(code, encoding="utf-8")
        done = subprocess.run(
            [nvcc, *NVRTC_OPTIONS, f"-arch={arch}", "-ptx", str(src), "-o", str(tmp_path / f"{name}.ptx")],
            capture_output=True, text=True, check=False, timeout=300,
        )
        assert done.returncode == 0, f"{name} ({arch}):\n{done.stderr[-3000:]}"
