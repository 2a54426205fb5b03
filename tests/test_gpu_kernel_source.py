"""Checks of the CUDA kernel source that need neither a GPU nor a compiler."""

from __future__ import annotations

import itertools
import re

from companion.gpu.estimator import kernel_source


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
