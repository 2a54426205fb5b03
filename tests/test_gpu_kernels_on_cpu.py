"""The CUDA kernels' exact source, run on the CPU (companion.gpu.hostemu), must equal the NumPy reference.

CI has no GPU; this keeps the kernel source itself under test there: stereo.cu is compiled as C++
against a small CUDA emulation (random fiber scheduling, so a missing barrier gives a wrong answer)
and compared pixel for pixel with ``sad_block_match`` and the region reduction. The same comparison on
a real GPU is tests/test_gpu.py (marker ``gpu``).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from companion.config.core import RegionsConfig
from companion.core.disparity.reference import sad_block_match
from companion.core.regions import RegionLayout, reduce_regions_from_disparity

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++ to compile the kernels for the CPU"),
]


@pytest.mark.parametrize(
    ("w", "h", "d", "b", "u", "t", "rows", "bands"),
    [
        (200, 90, 128, 9, 10, 3, 11, 2),  # the fast tiled kernel, two row bands
        (190, 70, 16, 11, 0, 0, 5, 3),  # u = 0: exact ties elsewhere are rejected
        (150, 60, 32, 17, 10, 3, 9, 1),  # the fallback kernel for blocks above 15
    ],
)
def test_kernel_source_equals_the_reference(w: int, h: int, d: int, b: int, u: int, t: int, rows: int, bands: int) -> None:
    from companion.gpu.hostemu import HostKernels

    rng = np.random.default_rng([w, d, b])
    left = rng.integers(0, 256, (h, w), dtype=np.uint8)
    right = np.roll(left, -int(rng.integers(3, 20)), axis=1)
    right = np.clip(right.astype(int) + rng.integers(-3, 4, right.shape), 0, 255).astype(np.uint8)
    left[20:40, 30:70] = 90  # a flat patch: texture rejection and ties
    right[20:40, 30:70] = 90
    rows_e, cols_e = [0, h // 3, 2 * h // 3, h], [0, w // 3, 2 * w // 3, w]
    kernels = HostKernels(w, h, d, b, u, t, rows_e, cols_e)
    disparity, regions = kernels.disparity(left, right, rows_per_block=rows, bands=bands)

    reference = sad_block_match(left, right, d, b, u, t)
    np.testing.assert_array_equal(disparity, reference)
    ref_f = reference.astype(np.float32)
    ref_f[reference < 0] = np.nan
    expected = reduce_regions_from_disparity(
        ref_f, RegionLayout(np.array(rows_e), np.array(cols_e)), RegionsConfig(), 50.0
    )
    np.testing.assert_array_equal(regions[:9], expected.depth_m)
    np.testing.assert_array_equal(regions[9:], expected.valid_fraction)
