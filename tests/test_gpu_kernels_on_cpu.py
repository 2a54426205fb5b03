"""The CUDA kernels' exact source, run on the CPU (companion.gpu.hostemu), must equal the NumPy reference.

CI has no GPU; this keeps the kernel source itself under test there: stereo.cu (SAD) and sgm.cu (SGM) are
compiled as C++ against a small CUDA emulation (random fiber scheduling, so a missing barrier gives a
wrong answer) and compared pixel for pixel with ``sad_block_match`` / ``sgm_match`` (every path volume
too) and the region reduction. Images are small: the emulation switches fibers at every shuffle. The
same comparison on a real GPU is tests/test_gpu.py (marker ``gpu``).
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


# 98 and 99: the last 4-pixel group of a row is partial (a YUYV eye is an even number of pixels wide)
@pytest.mark.parametrize(("w", "channels"), [(100, 1), (100, 2), (100, 3), (100, 4), (98, 2), (99, 1), (99, 3), (99, 4)])
def test_grey_kernel_source_equals_to_grey(w: int, channels: int) -> None:
    from companion.core.stereo import split_side_by_side, to_grey
    from companion.gpu.hostemu import HostKernels

    h = 9
    shape = (h, 2 * w, channels) if channels > 1 else (h, 2 * w)
    frame = np.random.default_rng([w, channels]).integers(0, 256, shape, dtype=np.uint8)
    gl, gr = HostKernels(w, h, 16, 5, 10, 3, [0, 3, 6, h], [0, w // 3, 2 * w // 3, w]).grey(frame)
    left, right = split_side_by_side(frame)
    np.testing.assert_array_equal(gl, to_grey(left))
    np.testing.assert_array_equal(gr, to_grey(right))


# 4 px blocks as the map's; 3 on 50 x 19: partial edge blocks; erosion reaching past a block and the
# image; k = 0: the preview's reduction (preview_max shares it)
@pytest.mark.parametrize(("w", "h", "f", "k"), [(64, 20, 4, 1), (50, 19, 3, 2), (40, 9, 4, 4), (50, 19, 4, 0)])
def test_map_blocks_kernel_source_equals_block_max_of_the_eroded_disparity(w: int, h: int, f: int, k: int) -> None:
    from companion.core.blocks import block_max
    from companion.gpu.hostemu import HostKernels

    rng = np.random.default_rng([w, k])
    disp = rng.integers(-1, 40, (h, w)).astype(np.int16)
    disp[rng.random((h, w)) < 0.2] = -1  # invalid pixels: the smallest
    out = HostKernels(w, h, 16, 5, 10, 3, [0, 3, 6, h], [0, w // 3, 2 * w // 3, w]).memory_blocks(disp, f, k)
    ref = np.where(disp < 0, np.nan, disp).astype(np.float32)
    np.testing.assert_array_equal(out, block_max(ref, f, k))


@pytest.mark.parametrize(
    ("w", "h", "d", "paths", "p1", "p2", "u", "lr", "median", "lanes", "prefetch"),
    [
        # a whole warp per line (96 padded disparities), diagonals; loads 4 steps ahead
        (40, 18, 32, 8, 10, 120, 10, 1, True, 32, 4),
        (48, 12, 128, 4, 8, 80, 0, 0, False, 16, 0),  # 16 lanes x 2 groups (the faster 128 layout), u = 0, strict LR
        # padded (48 of 64), 2 groups per lane, costs up to 255, no LR; loads 4 steps ahead
        (56, 16, 48, 4, 192, 193, 5, -1, True, 8, 4),
        # census tiles over 3 block rows (the last partial), 1-row post slabs
        (24, 70, 16, 4, 10, 120, 10, 1, True, 0, 2),
    ],
)
def test_sgm_kernel_source_equals_the_reference(
    w: int, h: int, d: int, paths: int, p1: int, p2: int, u: int, lr: int, median: bool, lanes: int, prefetch: int
) -> None:
    from companion.core.disparity import sgm as S
    from companion.gpu.hostemu import HostSgmKernels

    rng = np.random.default_rng([w, d, paths])
    left = rng.integers(0, 256, (h, w), dtype=np.uint8)
    right = np.roll(left, -int(rng.integers(3, 12)), axis=1)
    right = np.clip(right.astype(int) + rng.integers(-3, 4, right.shape), 0, 255).astype(np.uint8)
    left[h // 4 : h // 2, w // 3 : w // 2] = 90  # a flat patch: equal sums everywhere
    right[h // 4 : h // 2, w // 3 : w // 2] = 90
    rows_e, cols_e = [0, h // 3, 2 * h // 3, h], [0, w // 3, 2 * w // 3, w]
    kernels = HostSgmKernels(w, h, d, paths, rows_e, cols_e, lanes_per_line=lanes, prefetch_steps=prefetch)
    # the census in three launches of rows, as the estimator's row bands run it (cuts at arbitrary rows)
    out = kernels.run(left, right, p1, p2, u, lr, median, census_splits=(h // 3, h // 3 + 5))

    np.testing.assert_array_equal(out["census_left"], S.census_9x7(left))
    np.testing.assert_array_equal(out["census_right"], S.census_9x7(right))
    cost = S.census_costs(left, right, d)
    for k, (dx, dy) in enumerate(S.PATH_DIRECTIONS[:paths]):
        np.testing.assert_array_equal(out["volumes"][k][:, :, :d], S.aggregate_path(cost, dx, dy, p1, p2))
    reference = S.sgm_match(left, right, d, p1=p1, p2=p2, paths=paths, uniqueness_ratio_pct=u,
                            lr_max_diff_px=lr, median=median)
    np.testing.assert_array_equal(out["disparity"], reference)
    expected = reduce_regions_from_disparity(
        S.fixed_to_float(reference), RegionLayout(np.array(rows_e), np.array(cols_e)), RegionsConfig(), 50.0
    )
    np.testing.assert_array_equal(out["regions"][:9], expected.depth_m)
    np.testing.assert_array_equal(out["regions"][9:], expected.valid_fraction)


@pytest.mark.parametrize(("window", "rng_px"), [(12, 2), (40, 0)])
def test_sgm_peak_removal_source_equals_the_reference(window: int, rng_px: int) -> None:
    """Rule 10's peak removal: sgm_post's two stages around the union-find kernels, the coarse pair's
    with a sixteenth of the window, as the estimator launches them."""
    from companion.core.disparity import sgm as S
    from companion.gpu.hostemu import HostSgmKernels

    w, h, d = 72, 44, 16
    rng = np.random.default_rng([window, rng_px])
    left = rng.integers(0, 256, (h, w), dtype=np.uint8)
    right = np.roll(left, -5, axis=1)
    # a plain patch under noise: the matches there are short streaks at any disparity
    plain = (slice(8, 36), slice(30, 66))
    left[plain] = 120 + rng.integers(-2, 3, left[plain].shape)
    right[plain] = 120 + rng.integers(-2, 3, right[plain].shape)
    params = dict(p1=10, p2=120, paths=4, uniqueness_ratio_pct=10, lr_max_diff_px=1, median=True)
    reference = S.sgm_match(left, right, d, speckle_window_px=window, speckle_range_px=rng_px, **params)
    assert (reference != S.sgm_match(left, right, d, **params)).any()  # some peaks were removed
    rows_e, cols_e = [0, h // 3, 2 * h // 3, h], [0, w // 3, 2 * w // 3, w]
    out = HostSgmKernels(w, h, d, 4, rows_e, cols_e).run(
        left, right, 10, 120, 10, 1, True, speckle_window_px=window, speckle_range_px=rng_px
    )
    np.testing.assert_array_equal(out["disparity"], reference)
    expected = reduce_regions_from_disparity(
        S.fixed_to_float(reference), RegionLayout(np.array(rows_e), np.array(cols_e)), RegionsConfig(), 50.0
    )
    np.testing.assert_array_equal(out["regions"][:9], expected.depth_m)
    np.testing.assert_array_equal(out["regions"][9:], expected.valid_fraction)
