"""Checks of the CUDA kernel source that need neither a GPU nor a compiler."""

from __future__ import annotations

import itertools
import re

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
    import pytest

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
