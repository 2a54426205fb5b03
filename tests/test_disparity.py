"""Disparity matchers and disparity -> depth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config.core import StereoConfig
from companion.core.depth import disparity_to_depth
from companion.core.disparity import (
    DisparityMatcher,
    ReferenceMatcher,
    make_cpu_matcher,
    sad_block_match,
    valid_area,
)
from companion.errors import BackendError, FrameError

# --------------------------------------------------------------------------------------------------
# Helpers


def brute_force(
    left: np.ndarray, right: np.ndarray, D: int, b: int, u: int, t: int
) -> tuple[np.ndarray, dict[str, int]]:
    """The reference rules as a literal triple loop (y, x, d).

    Returns (int16 disparity, counts of tied pixels and of uniqueness / texture rejections).
    """
    H, W = left.shape
    r = b // 2
    L = left.astype(np.int64)
    R = right.astype(np.int64)
    out = np.full((H, W), -1, dtype=np.int16)
    counts = {"ties": 0, "uniqueness": 0, "texture": 0}
    for y in range(r, H - r):
        for x in range(r + D - 1, W - r):
            win = L[y - r : y + r + 1, x - r : x + r + 1]
            costs = []
            for d in range(D):
                costs.append(int(np.abs(win - R[y - r : y + r + 1, x - r - d : x + r + 1 - d]).sum()))
            best = min(costs)
            d_star = max(d for d in range(D) if costs[d] == best)
            if sum(c == best for c in costs) > 1:
                counts["ties"] += 1
            ambiguous = any(abs(d - d_star) > 1 and 100 * costs[d] <= (100 + u) * best for d in range(D))
            tex = int(np.abs(win - L[y - r : y + r + 1, x - r - 1 : x + r]).sum())
            flat = tex < t * b * b
            counts["uniqueness"] += ambiguous
            counts["texture"] += flat
            if not (ambiguous or flat):
                out[y, x] = d_star
    return out, counts


def shifted_pair(
    h: int, w: int, disparities: np.ndarray, seed: int = 0, blur: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random texture ``right``; ``left(y, x) = right(y, x - d)`` with ``d`` constant per block.

    ``disparities`` is a (by, bx) grid of integer disparities laid over the image in equal blocks.
    Returns (left, right, true disparity int (H, W)).
    """
    rng = np.random.default_rng(seed)
    right = rng.integers(0, 256, size=(h, w), dtype=np.uint8)
    if blur:
        right = cv2.GaussianBlur(right, (3, 3), 0.8)
    by, bx = disparities.shape
    rows = np.minimum(np.arange(h) * by // h, by - 1)
    cols = np.minimum(np.arange(w) * bx // w, bx - 1)
    true_d = disparities[rows[:, None], cols[None, :]]
    xs = np.arange(w)[None, :] - true_d
    left = right[np.arange(h)[:, None], np.clip(xs, 0, w - 1)]
    return left, right, true_d


def interior_mask(true_d: np.ndarray, margin: int) -> np.ndarray:
    """Pixels whose (2·margin+1)² neighbourhood has a single true disparity."""
    k = 2 * margin + 1
    img = true_d.astype(np.float32)
    mx = cv2.dilate(img, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    mn = cv2.erode(img, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return mx == mn


# --------------------------------------------------------------------------------------------------
# Depth


def test_depth_known_values() -> None:
    d = np.array([[21.0, 42.0, 7.0]], dtype=np.float32)
    z = disparity_to_depth(d, 350.0 * 0.12)
    assert z.dtype == np.float32
    np.testing.assert_allclose(z, [[2.0, 1.0, 6.0]], rtol=1e-6)


def test_depth_nan_zero_negative() -> None:
    d = np.array([np.nan, 0.0, -0.0, -3.0, 0.5], dtype=np.float32)
    z = disparity_to_depth(d, 42.0)
    assert np.isnan(z[0])
    assert z[1] == np.inf and z[2] == np.inf
    assert np.isnan(z[3])
    assert z[4] == pytest.approx(84.0)


def test_depth_out_in_place() -> None:
    d = np.array([[21.0, 0.0], [np.nan, -1.0]], dtype=np.float32)
    out = np.empty_like(d)
    assert disparity_to_depth(d, 42.0, out=out) is out
    same = disparity_to_depth(d, 42.0, out=d)  # aliasing is allowed
    np.testing.assert_array_equal(same, out)


def test_depth_rejects_bad_focal_baseline() -> None:
    with pytest.raises(ValueError, match="focal_baseline_px_m"):
        disparity_to_depth(np.ones((2, 2), np.float32), 0.0)


# --------------------------------------------------------------------------------------------------
# Reference: exactness against the brute force


@pytest.mark.parametrize(
    ("h", "w", "D", "b", "u", "t", "levels", "band_rows"),
    [
        (40, 60, 8, 5, 10, 3, 256, None),
        (41, 57, 7, 5, 0, 0, 3, None),  # few grey levels: many ties; u=0 rejects separated ties
        (37, 61, 5, 3, 15, 2, 2, 3),  # binary image, odd sizes, banded
        (23, 45, 2, 1, 5, 10, 4, 1),  # D=2, b=1
        (30, 50, 3, 3, 0, 1, 2, None),  # D=3: some pixels have no non-adjacent disparity
        (35, 64, 17, 7, 25, 4, 256, 4),  # D not a multiple of 16, bands not dividing the height
    ],
)
def test_reference_equals_brute_force(
    h: int, w: int, D: int, b: int, u: int, t: int, levels: int, band_rows: int | None
) -> None:
    rng = np.random.default_rng(h * 1000 + w)
    left = rng.integers(0, levels, size=(h, w)).astype(np.uint8) * (255 // max(levels - 1, 1))
    right = np.roll(left, -2, axis=1)  # true disparity +2 (left(x) = right(x - 2))
    right[::4] = rng.integers(0, levels, size=right[::4].shape) * (255 // max(levels - 1, 1))
    left[5:15, 20:35] = 128  # a flat patch: ties everywhere, texture rejection
    right[5:15, 18:33] = 128
    expected, counts = brute_force(left, right, D, b, u, t)
    got = sad_block_match(left, right, D, b, u, t, band_rows=band_rows)
    assert got.dtype == np.int16 and got.shape == (h, w)
    np.testing.assert_array_equal(got, expected)
    # The case really exercised ties and both rejections.
    assert counts["ties"] > 0
    assert (counts["uniqueness"] > 0) == (D > 2)  # D = 2: no disparity is non-adjacent
    assert (counts["texture"] > 0) == (t > 0)
    assert (expected >= 0).any()


def test_reference_tie_break_prefers_largest_disparity() -> None:
    # Constant images: every disparity costs 0. With D=2 there is no non-adjacent disparity, so the
    # tie is accepted and the larger disparity wins.
    img = np.full((9, 12), 77, dtype=np.uint8)
    got = sad_block_match(img, img, 2, 3, 0, 0)
    rows, cols = valid_area(9, 12, 2, 3)
    assert (got[rows, cols] == 1).all()
    # Adjacent ties, non-adjacent costs higher: columns repeat in pairs, so with b=1 the true
    # disparity ties with one neighbour at every pixel; the larger of the two must win.
    x = np.arange(40)
    row = (x // 2 * 9).astype(np.uint8)  # pairs of equal values, steps of 9
    left = np.tile(row, (7, 1))
    right = np.roll(left, -3, axis=1)  # true disparity 3; pairs make d=2,3 (even x) or 3,4 (odd x) tie
    got = sad_block_match(left, right, 8, 1, 0, 0)
    expected, counts = brute_force(left, right, 8, 1, 0, 0)
    np.testing.assert_array_equal(got, expected)
    assert counts["ties"] > 0
    valid = got[got >= 0]
    assert set(np.unique(valid)) <= {3, 4}
    assert (valid == 4).any()  # where 3 and 4 tie, 4 (the larger) wins


def test_reference_uniqueness_rejects_separated_ties_even_at_u0() -> None:
    # Period-4 pattern, right = left: costs are 0 at d = 0, 4 and 8 -> ambiguous, always rejected.
    row = np.tile(np.array([0, 200, 50, 120], dtype=np.uint8), 10)
    img = np.tile(row, (9, 1))
    got = sad_block_match(img, img, 10, 3, 0, 0)
    assert (got == -1).all()
    # With D = 3 only d = 0 of the periodic minima is in range: accepted.
    got3 = sad_block_match(img, img, 3, 3, 0, 0)
    rows, cols = valid_area(9, 40, 3, 3)
    assert (got3[rows, cols] == 0).all()


def test_reference_uniqueness_margin() -> None:
    # Noisy match (C(d*) > 0): a larger u rejects at least as many pixels, and some more.
    rng = np.random.default_rng(3)
    left = rng.integers(0, 4, (30, 60), dtype=np.uint8) * 60
    noise = rng.integers(-40, 41, left.shape)
    right = np.clip(np.roll(left, -2, axis=1).astype(int) + noise, 0, 255).astype(np.uint8)
    counts = [int((sad_block_match(left, right, 16, 5, u, 0) >= 0).sum()) for u in (0, 10, 50, 100, 400)]
    assert counts == sorted(counts, reverse=True)
    assert counts[-1] < counts[0]


def test_reference_texture_threshold_boundary() -> None:
    # A ramp of +1 per column: T = b·b exactly at every pixel.
    b, D = 3, 6
    left = np.tile(np.arange(60, dtype=np.uint8), (10, 1))
    right = left + np.uint8(2)  # right(x) = left(x + 2): disparity 2, C(d) = |d - 2|·b²
    rows, cols = valid_area(10, 60, D, b)
    passes = sad_block_match(left, right, D, b, 10, 1)  # T = 9 is not < 1·9
    assert (passes[rows, cols] == 2).all()
    rejected = sad_block_match(left, right, D, b, 10, 2)  # T = 9 < 2·9
    assert (rejected == -1).all()


def test_reference_texture_rejects_flat_patch() -> None:
    rng = np.random.default_rng(4)
    right = rng.integers(0, 256, (40, 80), dtype=np.uint8)
    right[:, 30:60] = 90
    left = np.roll(right, 4, axis=1)
    out_t0 = sad_block_match(left, right, 16, 5, 100, 0)
    out_t3 = sad_block_match(left, right, 16, 5, 0, 3)
    flat = (slice(5, 35), slice(38, 60))  # windows fully inside the flat patch of the left image
    assert (out_t3[flat] == -1).all()
    # Without the texture test, the flat patch is only rejected by uniqueness (ties everywhere).
    assert (out_t0[flat] == -1).all()
    textured = (slice(5, 35), slice(20, 30))
    assert (out_t3[textured] == 4).all()


def test_reference_border_is_invalid() -> None:
    rng = np.random.default_rng(5)
    left = rng.integers(0, 256, (30, 70), dtype=np.uint8)
    right = np.roll(left, -3, axis=1)  # disparity 3
    D, b = 12, 7
    got = sad_block_match(left, right, D, b, 0, 0)
    rows, cols = valid_area(30, 70, D, b)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (3, 27, 3 + 11, 67)
    inside = np.zeros(got.shape, bool)
    inside[rows, cols] = True
    assert (got[~inside] == -1).all()
    assert (got[inside] == 3).all()


@pytest.mark.parametrize(("h", "w"), [(4, 40), (20, 14), (1, 1), (5, 5)])
def test_reference_too_small_is_all_invalid(h: int, w: int) -> None:
    rng = np.random.default_rng(h * w)
    left = rng.integers(0, 256, (h, w), dtype=np.uint8)
    right = np.roll(left, -1, axis=1)  # disparity 1
    got = sad_block_match(left, right, 10, 5, 10, 0)  # needs H >= 5 and W >= 5 + 10 - 1
    m = ReferenceMatcher(10, 5, 10, 0).compute(left, right)
    assert m.dtype == np.float32
    if h >= 5 and w >= 14:
        rows, cols = valid_area(h, w, 10, 5)
        assert (got[rows, cols] == 1).all() and (got >= 0).sum() == (h - 4) * (w - 13)
    else:
        assert (got == -1).all()
        assert np.isnan(m).all()


def test_reference_exactly_one_valid_pixel() -> None:
    rng = np.random.default_rng(6)
    left = rng.integers(0, 256, (5, 14), dtype=np.uint8)
    right = np.roll(left, -1, axis=1)  # disparity 1
    got = sad_block_match(left, right, 10, 5, 0, 0)
    assert (got >= 0).sum() == 1 and got[2, 2 + 9] == 1


def test_reference_rejects_bad_parameters() -> None:
    img = np.zeros((10, 10), np.uint8)
    with pytest.raises(ValueError, match="num_disparities"):
        sad_block_match(img, img, 1, 3, 0, 0)
    with pytest.raises(ValueError, match="block_size"):
        sad_block_match(img, img, 4, 4, 0, 0)
    with pytest.raises(FrameError):
        sad_block_match(img, img[:, :9], 4, 3, 0, 0)
    with pytest.raises(FrameError):
        sad_block_match(img.astype(np.float32), img, 4, 3, 0, 0)  # type: ignore[arg-type]


def test_reference_recovers_shifted_pair_exactly() -> None:
    grid = np.array([[3, 10, 17], [25, 0, 31]])
    left, right, true_d = shifted_pair(120, 240, grid, seed=1)
    D, b = 40, 7
    m = ReferenceMatcher(D, b, 10, 3)
    out = np.empty(left.shape, np.float32)
    disp = m.compute(left, right, out=out)
    assert disp is out and disp.dtype == np.float32
    rows, cols = valid_area(*left.shape, D, b)
    # Windows that see one true disparity (in the left image, and in the source columns of right).
    core = interior_mask(true_d, b // 2 + 1)
    area = np.zeros_like(core)
    area[rows, cols] = True
    sel = core & area
    assert sel.sum() > 0.5 * area.sum()
    np.testing.assert_array_equal(disp[sel], true_d[sel].astype(np.float32))
    assert np.isnan(disp[~area]).all()
    # Reuse with the same buffer: same answer.
    np.testing.assert_array_equal(m.compute(left, right, out=out), disp)


# --------------------------------------------------------------------------------------------------
# OpenCV matchers


@pytest.mark.parametrize("backend", ["opencv-bm", "opencv-sgbm"])
def test_opencv_invalid_is_nan_and_disparity_is_right(backend: str) -> None:
    grid = np.array([[4, 12, 20], [28, 8, 36]])
    left, right, true_d = shifted_pair(180, 320, grid, seed=2, blur=True)
    cfg = StereoConfig(backend=backend, num_disparities=48, block_size_px=9, bm_scale_check="off")
    m = make_cpu_matcher(cfg)
    assert m.name == backend and isinstance(m, DisparityMatcher)
    disp = m.compute(left, right)
    assert disp.dtype == np.float32 and disp.shape == left.shape

    # Same OpenCV call, raw: every negative (invalid) value must be NaN, every other value raw/16.
    raw = m._matcher.compute(left, right)  # type: ignore[attr-defined]
    invalid = raw < 0
    assert invalid.any()
    assert np.isnan(disp[invalid]).all()
    np.testing.assert_array_equal(disp[~invalid], raw[~invalid].astype(np.float32) / 16)
    assert not (disp[invalid] == 0).any()

    core = interior_mask(true_d, 6)
    core[:, : cfg.num_disparities + 5] = False
    valid = core & ~np.isnan(disp)
    assert valid.sum() > 0.6 * core.sum()
    close = np.abs(disp[valid] - true_d[valid]) <= 1.0
    assert close.mean() > 0.95


def test_opencv_reuses_buffers_and_out() -> None:
    left, right, _ = shifted_pair(60, 120, np.array([[5]]), seed=3, blur=True)
    m = make_cpu_matcher(StereoConfig(backend="opencv-bm", num_disparities=16, block_size_px=7))
    out = np.empty(left.shape, np.float32)
    first = m.compute(left, right, out=out).copy()
    buf = m._raw  # type: ignore[attr-defined]
    assert m.compute(left, right, out=out) is out
    assert m._raw is buf  # type: ignore[attr-defined]
    np.testing.assert_array_equal(out, first)
    with pytest.raises(ValueError, match="out must be"):
        m.compute(left, right, out=np.empty((2, 2), np.float32))


def test_sgbm_penalties_from_config() -> None:
    m = make_cpu_matcher(StereoConfig(backend="opencv-sgbm", block_size_px=5))
    assert (m.p1, m.p2) == (8 * 25, 32 * 25)  # type: ignore[attr-defined]
    m = make_cpu_matcher(StereoConfig(backend="opencv-sgbm", block_size_px=5, sgbm_p1=2000))
    assert (m.p1, m.p2) == (2000, 2001)  # type: ignore[attr-defined]


# --------------------------------------------------------------------------------------------------
# Factory


def test_factory_backends() -> None:
    assert make_cpu_matcher(StereoConfig()).name == "opencv-bm"  # auto
    assert make_cpu_matcher(StereoConfig(backend="reference")).name == "reference"
    with pytest.raises(BackendError, match="GPU"):
        make_cpu_matcher(StereoConfig(backend="cupy"))


def test_matchers_reject_bad_frames() -> None:
    m = make_cpu_matcher(StereoConfig())
    with pytest.raises(FrameError):
        m.compute(np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(FrameError):
        m.compute(np.zeros((10, 10), np.uint8), np.zeros((10, 11), np.uint8))


@settings(max_examples=100, deadline=None)
@given(
    h=st.integers(1, 16),
    w=st.integers(1, 28),
    D=st.integers(2, 9),
    b=st.sampled_from([1, 3, 5]),
    u=st.integers(0, 60),
    t=st.integers(0, 6),
    levels=st.sampled_from([2, 3, 256]),
    shift=st.integers(0, 6),
    band_rows=st.one_of(st.none(), st.integers(1, 5)),
    seed=st.integers(0, 2**16),
)
def test_reference_equals_brute_force_property(
    h: int, w: int, D: int, b: int, u: int, t: int, levels: int, shift: int, band_rows: int | None, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    scale = 255 // (levels - 1)
    left = (rng.integers(0, levels, size=(h, w)) * scale).astype(np.uint8)
    right = np.roll(left, -shift, axis=1)
    right[::3] = rng.integers(0, levels, size=right[::3].shape) * scale
    expected, _ = brute_force(left, right, D, b, u, t)
    np.testing.assert_array_equal(sad_block_match(left, right, D, b, u, t, band_rows=band_rows), expected)


@pytest.mark.parametrize("backend", ["opencv-bm", "opencv-sgbm"])
@pytest.mark.parametrize(("h", "w"), [(5, 5), (9, 200), (40, 60), (40, 72)])
def test_opencv_tiny_images_are_all_nan(backend: str, h: int, w: int) -> None:
    m = make_cpu_matcher(StereoConfig(backend=backend, num_disparities=64, block_size_px=9))
    img = np.random.default_rng(0).integers(0, 256, (h, w), dtype=np.uint8)
    assert np.isnan(m.compute(img, img)).all()


def test_left_right_checks_of_the_opencv_matchers() -> None:
    """BM gets OpenCV's disp12MaxDiff; SGBM's mirrored check only removes pixels, and removes some."""
    from companion.core.disparity import OpenCVBMMatcher, OpenCVSGBMMatcher

    assert OpenCVBMMatcher(StereoConfig(disp12_max_diff_px=3))._matcher.getDisp12MaxDiff() == 3
    assert StereoConfig().disp12_max_diff_px == 1 and StereoConfig().uniqueness_ratio_pct == 5
    rng = np.random.default_rng(7)
    left = cv2.GaussianBlur(rng.integers(0, 256, (80, 200)).astype(np.float32), (0, 0), 1.0)
    left = np.clip((left - left.mean()) * 3 + 128, 0, 255).astype(np.uint8)
    right = np.roll(left, -6, axis=1)
    right[:, 120:] = rng.integers(0, 256, (80, 80), dtype=np.uint8)  # no true match there
    base = StereoConfig(backend="opencv-sgbm", num_disparities=32, block_size_px=5)
    plain = OpenCVSGBMMatcher(base).compute(left, right)
    checked = OpenCVSGBMMatcher(base.model_copy(update={"sgbm_lr_check": True})).compute(left, right)
    kept = ~np.isnan(checked)
    np.testing.assert_array_equal(checked[kept], plain[kept])
    assert kept.sum() < (~np.isnan(plain)).sum()
    assert np.nanmedian(checked[:, 40:110]) == 6.0


# --------------------------------------------------------------------------------------------------
# StereoBM's half-size check (stereo.bm_scale_check)


class _FixedHalf:
    """Stands in for the half-size StereoBM: writes a fixed int16 result (1/16 px, < 0 invalid)."""

    def __init__(self, raw16: np.ndarray) -> None:
        self.raw16 = raw16

    def compute(self, left: np.ndarray, right: np.ndarray, dst: np.ndarray) -> np.ndarray:
        assert left.shape == right.shape == dst.shape == self.raw16.shape
        dst[...] = self.raw16
        return dst


def test_bm_scale_check_keeps_a_disparity_only_where_the_half_size_one_agrees() -> None:
    """agree: kept where twice the half-size disparity is within the tolerance (2 px by default),
    rejected where it differs or is missing; no_conflict: a missing half-size match rejects nothing."""
    from companion.core.disparity import OpenCVBMMatcher

    left, right, _ = shifted_pair(80, 240, np.array([[10]]), seed=5, blur=True)
    plain = OpenCVBMMatcher(StereoConfig(num_disparities=32, bm_scale_check="off")).compute(left, right)
    ok = np.isfinite(plain)
    assert ok.sum() > 1000
    raw = np.where(ok, np.round(plain * 16), -16).astype(np.int32)
    # Bands of 8 rows: twice the half-size value is the full-size one plus about 0, 2 (the tolerance),
    # 2 1/8 and 5 px (1/16 px units, within one unit of rounding below), or missing.
    offsets16 = (0, 32, 34, 80, None)
    band = (np.arange(80) // 8) % 5
    half = np.full((40, 120), -16, np.int16)
    for hy in range(40):
        off = offsets16[band[2 * hy]]
        row = raw[2 * hy, 0::2]  # the full-size pixel each half-size one stands for, exactly (2x nearest)
        if off is not None:
            half[hy] = np.where(row >= 0, (row + off) >> 1, -16)
    even = np.zeros_like(ok)
    even[0::2, 0::2] = True
    even[:, : 2 * (16 - 1 + 4)] = False  # the half-size matcher's own unmatched band: left unchecked
    for mode, kept_bands in (("agree", {0, 1}), ("no_conflict", {0, 1, 4})):
        m = OpenCVBMMatcher(StereoConfig(num_disparities=32, bm_scale_check=mode))
        m._half = _FixedHalf(half)  # type: ignore[assignment]
        d = m.compute(left, right)
        kept = np.isfinite(d)
        np.testing.assert_array_equal(d[kept], plain[kept])  # the check only removes pixels
        np.testing.assert_array_equal(kept[:, :38], ok[:, :38])
        for b in range(5):
            sel = even & ok & (band[:, None] == b)
            assert sel.sum() > 50
            assert (kept[sel] == (b in kept_bands)).all(), (mode, b)


def test_bm_scale_check_leaves_true_matches() -> None:
    """On a textured pair with one true disparity per patch both modes keep most of StereoBM's
    matches right of the half-size matcher's unmatched band, with the same values."""
    grid = np.array([[4, 12, 20], [28, 8, 36]])
    left, right, true_d = shifted_pair(180, 320, grid, seed=2, blur=True)
    base = StereoConfig(backend="opencv-bm", num_disparities=48, block_size_px=9)
    plain = make_cpu_matcher(base.model_copy(update={"bm_scale_check": "off"})).compute(left, right)
    core = interior_mask(true_d, 12)
    core[:, : 2 * (32 + 5)] = False  # the half-size matcher's band: 32 disparities, a 9 px window
    for mode in ("agree", "no_conflict"):
        d = make_cpu_matcher(base.model_copy(update={"bm_scale_check": mode})).compute(left, right)
        kept = np.isfinite(d)
        np.testing.assert_array_equal(d[kept], plain[kept])
        assert kept[core].sum() > 0.9 * np.isfinite(plain[core]).sum()


def test_bm_scale_check_removes_the_office_fence_aliases() -> None:
    """The office's start view (fence bars ahead): StereoBM alone matches many pixels too near by more
    than 2 px (bars matched a period off); with the half-size check (the default) far fewer remain over
    the three views (some views keep more than others), at most a fifth less density in each."""
    from companion.core.geometry import StereoGeometry
    from companion.sim.courses import make_course
    from companion.sim.render import Photometry, Pose, StereoRenderer, TextureBank

    geo = StereoGeometry.ideal(336, 188, hfov_deg=90.0, baseline_m=0.12)  # the simulator's eye
    assert StereoConfig().bm_scale_check == "agree"
    too_near = {"off": 0, "agree": 0}
    for seed in (0, 2, 6):
        scene = make_course("office", seed).scene
        res = StereoRenderer(geo, scene, seed=seed, textures=TextureBank(0, 1024, pad=512)).render(
            Pose.at(0.0, 0.0, 1.5), left=Photometry(1.01, 2.0), right=Photometry(0.99, 2.0),
            rng=np.random.default_rng(seed))
        left, right = res.left_bgr[:, :, 0].copy(), res.right_bgr[:, :, 0].copy()
        truth = geo.focal_baseline_px_m / res.depth_m
        counts = {}
        for mode in ("off", "agree"):
            d = make_cpu_matcher(StereoConfig(backend="opencv-bm", cpu_threads=1, bm_scale_check=mode)).compute(left, right)
            ok = np.isfinite(d)
            counts[mode] = (ok.sum(), (ok & (d > truth + 2.0)).sum())
        assert counts["off"][1] > 300
        assert counts["agree"][0] > 0.75 * counts["off"][0], (seed, counts)
        for mode in too_near:
            too_near[mode] += counts[mode][1]
    assert too_near["agree"] < 0.4 * too_near["off"], too_near
