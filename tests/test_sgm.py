"""The exact census + SGM reference (companion.core.disparity.sgm): its rules as literal loops, its
behaviour on pairs with a known disparity, its wiring into the CPU backends and its parameter checks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from stereo_pairs import shifted_pair

from companion.config import CompanionConfig
from companion.config.core import StereoConfig
from companion.core.disparity import SgmReferenceMatcher, make_cpu_matcher
from companion.core.disparity import sgm as S
from companion.core.estimator import CpuRegionEstimator

# --------------------------------------------------------------------------------------------------
# The module docstring's rules, literally: one pixel, one disparity, one direction at a time.


def _census_literal(img: np.ndarray) -> np.ndarray:
    h, w = img.shape
    out = np.zeros((h, w), dtype=np.uint64)
    for y in range(h):
        for x in range(w):
            bits, k = 0, 0
            for i in range(-3, 4):
                for j in range(-4, 5):
                    if i == 0 and j == 0:
                        continue
                    yy, xx = y + i, x + j
                    if 0 <= yy < h and 0 <= xx < w and int(img[yy, xx]) < int(img[y, x]):
                        bits |= 1 << k
                    k += 1
            out[y, x] = bits
    return out


def _brute_force(left, right, D, p1, p2, paths, u, lr, median):  # noqa: ANN001, ANN202 - test oracle
    h, w = left.shape
    cl, cr = _census_literal(left), _census_literal(right)

    def included(x: int) -> list[int]:
        return list(range(min(x, D - 1) + 1))

    def cost(y: int, x: int, d: int) -> int:
        return bin(int(cl[y, x]) ^ int(cr[y, x - d])).count("1")

    total: dict[tuple[int, int, int], int] = {}
    for dx, dy in S.PATH_DIRECTIONS[:paths]:
        Lr: dict[tuple[int, int], dict[int, int]] = {}
        ys = range(h) if dy >= 0 else range(h - 1, -1, -1)
        xs = list(range(w)) if dx >= 0 else list(range(w - 1, -1, -1))
        order = [(y, x) for y in ys for x in xs] if dy != 0 else [(y, x) for x in xs for y in range(h)]
        for y, x in order:
            py, px = y - dy, x - dx
            cur = {}
            if not (0 <= py < h and 0 <= px < w):
                for d in included(x):
                    cur[d] = cost(y, x, d)
            else:
                prev = Lr[(py, px)]
                m = min(prev.values())
                for d in included(x):
                    terms = [m + p2]
                    for dd, pen in ((d, 0), (d - 1, p1), (d + 1, p1)):
                        if dd in prev:
                            terms.append(prev[dd] + pen)
                    cur[d] = cost(y, x, d) + min(terms) - m
            assert max(cur.values()) <= 255
            Lr[(y, x)] = cur
        for (y, x), vals in Lr.items():
            for d, v in vals.items():
                total[(y, x, d)] = total.get((y, x, d), 0) + v
    out = np.full((h, w), -1, dtype=np.int16)
    d_right = np.zeros((h, w), dtype=int)
    for y in range(h):
        for xr in range(w):
            ds = range(min(D - 1, w - 1 - xr) + 1)
            best = min(total[(y, xr + d, d)] for d in ds)
            d_right[y, xr] = max(d for d in ds if total[(y, xr + d, d)] == best)
    for y in range(h):
        for x in range(w):
            s = {d: total[(y, x, d)] for d in included(x)}
            best = min(s.values())
            ds = max(d for d, v in s.items() if v == best)
            if any(abs(d - ds) >= 2 and 100 * v <= (100 + u) * best for d, v in s.items()):
                continue
            if lr >= 0 and abs(ds - d_right[y, x - ds]) > lr:
                continue
            v = 16 * ds
            if ds >= 1 and ds + 1 in s:
                c0, c1, c2 = s[ds - 1], best, s[ds + 1]
                den = c0 + c2 - 2 * c1
                assert den >= 1
                off = (16 * (c0 - c2) + den) // (2 * den)  # Python's // is floor division
                assert -8 <= off <= 8
                v += off
            out[y, x] = v
    if not median:
        return out
    med = out.copy()
    for y in range(h):
        for x in range(w):
            if out[y, x] < 0:
                continue
            vals = sorted(
                int(out[yy, xx])
                for yy in range(y - 1, y + 2)
                for xx in range(x - 1, x + 2)
                if 0 <= yy < h and 0 <= xx < w and out[yy, xx] >= 0
            )
            med[y, x] = vals[(len(vals) - 1) // 2]
    return med


def test_census_equals_the_literal_rule() -> None:
    img = np.random.default_rng(0).integers(0, 256, (11, 13), dtype=np.uint8)
    img[3:7, 2:9] = 50  # ties: equal neighbours give 0
    np.testing.assert_array_equal(S.census_9x7(img), _census_literal(img))
    assert S.CENSUS_BITS == 62 and S.MAX_P2 == 193


@pytest.mark.parametrize(
    ("D", "p1", "p2", "paths", "u", "lr", "median"),
    [
        (6, 10, 120, 4, 10, 1, True),
        (8, 3, 193, 8, 0, 0, False),  # largest P2: path costs reach 255
        (5, 192, 193, 8, 25, -1, True),
        (16, 7, 40, 4, 5, 2, True),  # D wider than the image
    ],
)
def test_reference_equals_the_literal_rules(D: int, p1: int, p2: int, paths: int, u: int, lr: int, median: bool) -> None:
    left, right = shifted_pair(9, 14, 2, seed=D + p1)
    left[2:6, 4:9] = 90  # a flat patch: equal sums, ties to the largest d
    right[2:6, 2:7] = 90
    got = S.sgm_match(left, right, D, p1=p1, p2=p2, paths=paths, uniqueness_ratio_pct=u, lr_max_diff_px=lr,
                      median=median)
    np.testing.assert_array_equal(got, _brute_force(left, right, D, p1, p2, paths, u, lr, median))


def test_a_shifted_pair_is_matched_at_its_disparity() -> None:
    h, w, shift = 60, 120, 9
    left, right = shifted_pair(h, w, shift, seed=1)
    v = S.sgm_match(left, right, 32, p1=10, p2=120)
    d = S.fixed_to_float(v)
    matchable = np.zeros((h, w), bool)
    matchable[:, shift:] = True
    ok = np.abs(d - shift) <= 1
    assert ok[matchable].mean() > 0.95
    # left of column `shift` the true match is outside the right image: the left-right check rejects
    # most of those pixels rather than returning a wrong disparity (a path that starts at x = 0 has paid
    # fewer penalties, so the first few columns win the right view's diagonal minimum and some of them
    # pass with d = 0: a too-far error confined to the image's first columns)
    assert np.isnan(d[:, :shift]).mean() > 0.7
    assert np.isnan(d[:, 5:shift]).mean() > 0.9
    assert v.dtype == np.int16 and (v[v >= 0] <= 16 * 31).all()


def test_subpixel_offsets_follow_a_fractional_shift() -> None:
    h, w = 40, 160
    rng = np.random.default_rng(4)
    base = cv2.GaussianBlur(rng.integers(0, 256, (h, 4 * (w + 16))).astype(np.float32), (0, 0), 3.0)
    base = np.clip((base - base.mean()) * 3 + 128, 0, 255)
    # downsample by 4 after shifting by 26 fine pixels: a disparity of 6.5 px
    left = cv2.resize(base[:, : 4 * w], (w, h), interpolation=cv2.INTER_AREA).astype(np.uint8)
    right = cv2.resize(base[:, 26 : 26 + 4 * w], (w, h), interpolation=cv2.INTER_AREA).astype(np.uint8)
    d = S.fixed_to_float(S.sgm_match(left, right, 16, p1=10, p2=120))
    inner = d[5:-5, 20:-5]
    assert np.nanmedian(inner) == pytest.approx(6.5, abs=0.2)
    assert np.nanstd(inner) < 0.5


def test_matcher_from_config_and_cpu_estimator() -> None:
    m = make_cpu_matcher(StereoConfig(backend="reference"))
    assert isinstance(m, SgmReferenceMatcher) and m.name == "reference"
    assert m.params == dict(p1=10, p2=120, paths=4, uniqueness_ratio_pct=10, lr_max_diff_px=1, median=True,
                            speckle_window_px=100, speckle_range_px=2)
    sad = make_cpu_matcher(StereoConfig(backend="reference", matcher="sad"))
    assert not isinstance(sad, SgmReferenceMatcher)
    left, right = shifted_pair(40, 90, 5, seed=2)
    out = np.empty(left.shape, np.float32)
    assert m.compute(left, right, out=out) is out
    np.testing.assert_array_equal(out, S.fixed_to_float(m.compute_fixed(left, right)))
    cfg = CompanionConfig.model_validate({"stereo": {"backend": "reference", "num_disparities": 16}})
    est = CpuRegionEstimator(cfg, 90, 40)
    res = est.estimate(np.ascontiguousarray(np.hstack([left, right])), want_disparity=True)
    assert est.name == "reference"
    expected = S.sgm_match(left, right, 16, p1=10, p2=120, speckle_window_px=100, speckle_range_px=2)
    np.testing.assert_array_equal(res.disparity, S.fixed_to_float(expected))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_disparities": 1}, "num_disparities"),
        ({"num_disparities": 257}, "num_disparities"),
        ({"p1": 120, "p2": 120}, "P1 < P2"),
        ({"p2": 194}, "P2 <= 193"),
        ({"paths": 6}, "paths"),
        ({"uniqueness_ratio_pct": -1}, "uniqueness"),
        ({"lr_max_diff_px": -2}, "lr_max_diff_px"),
    ],
)
def test_bad_parameters_are_rejected(kwargs: dict, match: str) -> None:
    args = dict(num_disparities=16, p1=10, p2=120, paths=4, uniqueness_ratio_pct=10, lr_max_diff_px=1)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        SgmReferenceMatcher(args.pop("num_disparities"), **args)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"speckle_window_px": -1}, "speckle_window_px"), ({"speckle_range_px": 256}, "speckle_range_px")],
)
def test_bad_peak_parameters_are_rejected(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        SgmReferenceMatcher(16, p1=10, p2=120, **kwargs)


# --------------------------------------------------------------------------------------------------
# Rule 10's peak removal


def test_peak_removal_is_opencvs_filter_speckles() -> None:
    """The oracle's segments (label propagation) against OpenCV's (a flood fill): the same pixels."""
    rng = np.random.default_rng(11)
    for _ in range(150):
        h, w = (int(n) for n in rng.integers(1, 40, 2))
        steps = rng.integers(-1, 6, (h, w)) * int(rng.integers(8, 40)) + rng.integers(0, 20, (h, w))
        disp = np.where(rng.random((h, w)) < 0.2, -1, steps).astype(np.int16)
        disp[disp < 0] = -1
        window, rng_px = int(rng.integers(1, 30)), int(rng.integers(0, 3))
        expected = disp.copy()
        cv2.filterSpeckles(expected, -1, window, 16 * rng_px)
        np.testing.assert_array_equal(S.remove_peaks(disp, 200, window, rng_px), expected)


def test_a_segment_of_the_window_goes_and_one_pixel_more_stays() -> None:
    disp = np.full((6, 10), -1, np.int16)
    disp[1, 1:5] = 160  # 4 pixels
    disp[3, 1:6] = [160, 176, 192, 208, 224]  # 5 pixels, each a one-pixel step from the next
    disp[5, 1:4] = [160, 177, 160]  # steps just over one pixel: three segments of one
    out = S.remove_peaks(disp, 64, 4, 1)
    assert (out[1] == -1).all() and (out[5] == -1).all()
    np.testing.assert_array_equal(out[3], disp[3])
    np.testing.assert_array_equal(S.remove_peaks(disp, 64, 0, 1), disp)  # 0 = off


def test_a_match_at_the_ranges_end_is_never_a_peak() -> None:
    """A surface just beyond the range breaks up into small segments at its end: they keep it near."""
    disp = np.full((5, 8), -1, np.int16)
    disp[1, 1], disp[1, 3], disp[3, 1] = 16 * 15, 16 * 15 - 1, 16 * 9  # D = 16: the end is v = 240
    out = S.remove_peaks(disp, 16, 10, 1)
    assert out[1, 1] == 16 * 15 and out[1, 3] == -1 and out[3, 1] == -1


def _plain_wall(seed: int, noise_grey: float) -> tuple[np.ndarray, np.ndarray, int]:
    """A plain fronto-parallel wall under sensor noise with a textured poster in the middle, 672×376,
    at a disparity of 4–19 px: (left, right, disparity)."""
    rng = np.random.default_rng(seed)
    w, h = 672, 376
    shift = int(rng.integers(4, 20))
    scene = np.full((h, w + shift), 120.0)
    scene[h // 3 : h // 3 + h // 4, w // 3 : w // 3 + w // 4] += rng.uniform(-40, 40, (h // 4, w // 4))
    left = scene[:, :w] + rng.standard_normal((h, w)) * noise_grey
    right = scene[:, shift:] + rng.standard_normal((h, w)) * noise_grey
    grey = [np.clip(np.rint(e), 0, 255).astype(np.uint8) for e in (left, right)]
    return grey[0], grey[1], shift


@pytest.mark.parametrize(("seed", "noise_grey"), [(0, 1.0), (1, 2.0)])
def test_a_plain_wall_under_noise_shows_no_phantom_region(seed: int, noise_grey: float) -> None:
    """The sensor's noise alone makes the census on a plain wall: without peak removal the paths turn it
    into streaks that pass every check at any disparity, and most regions read the wall far nearer than
    it is. With it no region does: the wall is unknown (too few valid pixels) where it is plain, and
    the poster reads the wall's depth."""
    from companion.core.regions import RegionLayout, reduce_regions_from_disparity
    from companion.config.core import RegionsConfig

    left, right, shift = _plain_wall(seed, noise_grey)
    h, w = left.shape
    layout = RegionLayout(np.array([0, h // 3, 2 * h // 3, h]), np.array([0, w // 3, 2 * w // 3, w]))
    fb = 50.0
    wall_m = fb / shift

    def regions(window: int) -> np.ndarray:
        disp = S.fixed_to_float(S.sgm_match(left, right, 64, p1=10, p2=120, speckle_window_px=window))
        return reduce_regions_from_disparity(disp, layout, RegionsConfig(), fb).depth_m

    assert (regions(0) < 0.75 * wall_m).sum() >= 5
    depth = regions(100)
    assert not (depth < 0.75 * wall_m).any()
    assert depth[4] == pytest.approx(wall_m, rel=0.05)


def test_config_rejects_p2_not_above_p1() -> None:
    from companion.config import parse_config
    from companion.errors import ConfigError

    with pytest.raises(ConfigError, match="sgm_p2"):
        parse_config({"stereo": {"sgm_p1": 50, "sgm_p2": 50}})
    with pytest.raises(ConfigError, match="stereo.sgm_p2"):
        parse_config({"stereo": {"sgm_p2": 194}})
    with pytest.raises(ConfigError, match="stereo.sgm_paths"):
        parse_config({"stereo": {"sgm_paths": 6}})
