"""Nine-region layout and the robust per-region minimum."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config.core import RegionsConfig
from companion.core.depth import disparity_to_depth
from companion.core.geometry import StereoGeometry
from companion.core.regions import (
    RegionLayout,
    reduce_regions,
    reduce_regions_from_disparity,
    region_layout,
)
from companion.core.types import REGION_INDEX, REGION_NAMES, RegionDepths

ZED_VGA = StereoGeometry(
    width_px=672, height_px=376, focal_px=450.0, cx_px=335.5, cy_px=187.5, baseline_m=0.12
)


def _check_layout(layout: RegionLayout, w: int, h: int) -> None:
    assert layout.row_edges[0] == 0 and layout.row_edges[3] == h
    assert layout.col_edges[0] == 0 and layout.col_edges[3] == w
    assert (np.diff(layout.row_edges) >= 1).all() and (np.diff(layout.col_edges) >= 1).all()
    assert layout.area_px.shape == (9,) and layout.area_px.sum() == w * h
    covered = np.zeros((h, w), np.int32)
    for i in range(9):
        rs, cs = layout.region_slices(i)
        covered[rs, cs] += 1
    assert (covered == 1).all()


# --------------------------------------------------------------------------------------------------
# Layout


def test_centre_is_150_px_at_450_px_focal() -> None:
    layout = region_layout(ZED_VGA, RegionsConfig())
    rs, cs = layout.region_slices(REGION_INDEX["center"])
    assert (rs.stop - rs.start, cs.stop - cs.start) == (150, 150)
    # Centred on the principal point: equal bands either side.
    assert (layout.col_edges.tolist(), layout.row_edges.tolist()) == ([0, 261, 411, 672], [0, 113, 263, 376])
    assert layout.area_px[REGION_INDEX["center"]] == 150 * 150
    assert not layout.clamped
    _check_layout(layout, 672, 376)


def test_ideal_rig_about_150_px() -> None:
    # The ZED VGA ideal rig at 73.4° hfov has f ≈ 450 px.
    g = StereoGeometry.ideal(672, 376, hfov_deg=73.5, baseline_m=0.12)
    layout = region_layout(g, RegionsConfig())
    rs, cs = layout.region_slices_by_name("center")
    assert abs((cs.stop - cs.start) - 150) <= 1 and abs((rs.stop - rs.start) - 150) <= 1


def test_region_order_is_row_major() -> None:
    layout = region_layout(ZED_VGA, RegionsConfig())
    assert layout.region_slices_by_name("up_left") == (slice(0, 113), slice(0, 261))
    assert layout.region_slices_by_name("right") == (slice(113, 263), slice(411, 672))
    assert layout.region_slices_by_name("down") == (slice(263, 376), slice(261, 411))
    by_name = [layout.region_slices_by_name(n) for n in REGION_NAMES]
    assert [layout.region_slices(i) for i in range(9)] == by_name


def test_principal_point_shifts_the_centre() -> None:
    g = StereoGeometry(672, 376, 450.0, 335.5 + 20, 187.5 - 10, 0.12)
    layout = region_layout(g, RegionsConfig())
    assert layout.col_edges.tolist() == [0, 281, 431, 672]
    assert layout.row_edges.tolist() == [0, 103, 253, 376]


def test_window_too_large_is_clamped_with_margins() -> None:
    cfg = RegionsConfig(safe_window_width_m=10.0, safe_window_height_m=10.0, reference_distance_m=0.2)
    layout = region_layout(ZED_VGA, cfg)
    assert layout.clamped
    assert layout.col_edges.tolist() == [0, 1, 671, 672]
    assert layout.row_edges.tolist() == [0, 1, 375, 376]
    _check_layout(layout, 672, 376)


def test_principal_point_off_image_slides_centre_inside() -> None:
    g = StereoGeometry(672, 376, 450.0, 5.0, 370.0, 0.12)
    layout = region_layout(g, RegionsConfig())
    assert layout.clamped
    assert layout.col_edges.tolist() == [0, 1, 151, 672]
    assert layout.row_edges.tolist() == [0, 225, 375, 376]


def test_too_small_image_is_refused() -> None:
    with pytest.raises(ValueError, match="too small"):
        region_layout(StereoGeometry(2, 10, 100.0, 1.0, 5.0, 0.1), RegionsConfig())
    layout = region_layout(StereoGeometry(3, 3, 1000.0, 1.0, 1.0, 0.1), RegionsConfig())
    assert layout.area_px.tolist() == [1] * 9


def test_layout_is_frozen_and_validated() -> None:
    layout = region_layout(ZED_VGA, RegionsConfig())
    with pytest.raises(ValueError):
        layout.row_edges[1] = 5
    with pytest.raises(ValueError, match="row_edges"):
        RegionLayout(row_edges=np.array([0, 5, 5, 10]), col_edges=np.array([0, 1, 2, 3]))


@settings(max_examples=60, deadline=None)
@given(
    w=st.integers(3, 2000),
    h=st.integers(3, 1200),
    f=st.floats(50.0, 3000.0),
    cx=st.floats(-100.0, 2100.0),
    cy=st.floats(-100.0, 1300.0),
    win=st.floats(0.06, 10.0),
    z=st.floats(0.11, 50.0),
)
def test_layout_property(w: int, h: int, f: float, cx: float, cy: float, win: float, z: float) -> None:
    g = StereoGeometry(w, h, f, cx, cy, 0.12)
    cfg = RegionsConfig(safe_window_width_m=win, safe_window_height_m=win, reference_distance_m=z)
    _check_layout(region_layout(g, cfg), w, h)


# --------------------------------------------------------------------------------------------------
# Robust minimum


def _small_layout() -> RegionLayout:
    return RegionLayout(row_edges=np.array([0, 10, 60, 70]), col_edges=np.array([0, 10, 60, 70]))


def test_single_false_near_pixel_is_ignored_by_robust_minimum() -> None:
    layout = _small_layout()
    depth = np.full((70, 70), 5.0, np.float32)
    depth[20:50, 20:50] = np.linspace(3.0, 6.0, 900, dtype=np.float32).reshape(30, 30)
    depth[35, 35] = 0.3  # one false match in the centre
    c = REGION_INDEX["center"]
    robust = reduce_regions(depth, layout, RegionsConfig(robust_percentile_pct=2.0))
    raw = reduce_regions(depth, layout, RegionsConfig(robust_percentile_pct=0.0))
    assert raw.depth_m[c] == pytest.approx(0.3)
    # 2500 valid pixels -> k = 50: the 50th nearest, far above the false match.
    assert robust.depth_m[c] > 3.0
    vals = np.sort(depth[10:60, 10:60].ravel())
    assert robust.depth_m[c] == pytest.approx(float(vals[49]))
    assert raw.depth_m[REGION_INDEX["up_left"]] == 5.0 and robust.valid_fraction[c] == 1.0


def test_rank_definition() -> None:
    layout = RegionLayout(row_edges=np.array([0, 1, 11, 12]), col_edges=np.array([0, 1, 11, 12]))
    depth = np.full((12, 12), 9.0, np.float32)
    depth[1:11, 1:11] = np.arange(1, 101, dtype=np.float32).reshape(10, 10)
    depth[1:3, 1:11] = np.nan  # 80 valid in the centre
    c = REGION_INDEX["center"]
    cases = [(0.0, 21.0), (1.0, 21.0), (1.25, 21.0), (1.26, 22.0), (2.0, 22.0), (10.0, 28.0), (50.0, 60.0)]
    for pct, expect in cases:
        cfg = RegionsConfig(robust_percentile_pct=pct, min_valid_fraction=0.5, max_depth_m=200.0)
        assert reduce_regions(depth, layout, cfg).depth_m[c] == expect, pct  # k = max(1, ceil(pct·80/100))


def test_too_few_valid_pixels_is_unknown() -> None:
    layout = _small_layout()
    depth = np.full((70, 70), np.nan, np.float32)
    depth[10:60, 10:60][:24, :10] = 2.0  # 240 of 2500 valid = 9.6 %
    cfg = RegionsConfig(min_valid_fraction=0.10)
    res = reduce_regions(depth, layout, cfg)
    c = REGION_INDEX["center"]
    assert np.isnan(res.depth_m[c]) and res.valid_fraction[c] == pytest.approx(0.096)
    assert np.isnan(res.depth_m).all()  # the others have nothing at all
    depth[10:60, 10:60][24, :10] = 2.0  # 250 = 10 %: known
    res = reduce_regions(depth, layout, cfg)
    assert res.depth_m[c] == 2.0
    assert not res.known[REGION_INDEX["up"]]


def test_infinite_depth_reports_max_depth() -> None:
    layout = _small_layout()
    depth = np.full((70, 70), np.inf, np.float32)
    depth[0:10, 0:10] = 30.0
    depth[0:10, 10:60] = 7.0
    res = reduce_regions(depth, layout, RegionsConfig(max_depth_m=20.0))
    assert res.depth_m[REGION_INDEX["center"]] == 20.0
    assert res.depth_m[REGION_INDEX["up_left"]] == 20.0
    assert res.depth_m[REGION_INDEX["up"]] == 7.0


def test_out_is_filled_and_returned() -> None:
    layout = _small_layout()
    out = RegionDepths(depth_m=np.zeros(9), valid_fraction=np.zeros(9))
    depth = np.full((70, 70), 4.0, np.float32)
    assert reduce_regions(depth, layout, RegionsConfig(), out=out) is out
    assert (out.depth_m == 4.0).all() and (out.valid_fraction == 1.0).all()
    with pytest.raises(ValueError, match="does not match"):
        reduce_regions(np.zeros((10, 10), np.float32), layout, RegionsConfig())


def test_input_is_not_modified() -> None:
    layout = RegionLayout(row_edges=np.array([0, 1, 2, 3]), col_edges=np.array([0, 5, 10, 15]))
    rng = np.random.default_rng(1)
    depth = rng.uniform(1, 10, (3, 15)).astype(np.float32)
    keep = depth.copy()
    reduce_regions(depth, layout, RegionsConfig(robust_percentile_pct=50.0))
    np.testing.assert_array_equal(depth, keep)


@pytest.mark.parametrize("pct", [0.0, 2.0, 5.0, 33.3])
@pytest.mark.parametrize("nan_share", [0.0, 0.3, 0.95])
def test_disparity_and_depth_reductions_agree(pct: float, nan_share: float) -> None:
    rng = np.random.default_rng(int(pct * 10) + int(nan_share * 100))
    layout = region_layout(ZED_VGA, RegionsConfig())
    disp = rng.integers(-2, 64, (376, 672)).astype(np.float32)  # integers, incl. 0 and negatives
    disp[rng.random(disp.shape) < nan_share] = np.nan
    disp[:50, :50] = 0.0  # a region corner at infinity
    cfg = RegionsConfig(robust_percentile_pct=pct, min_valid_fraction=0.1, max_depth_m=30.0)
    fb = ZED_VGA.focal_baseline_px_m
    from_depth = reduce_regions(disparity_to_depth(disp, fb), layout, cfg)
    from_disp = reduce_regions_from_disparity(disp, layout, cfg, fb)
    np.testing.assert_array_equal(from_disp.depth_m, from_depth.depth_m)
    np.testing.assert_array_equal(from_disp.valid_fraction, from_depth.valid_fraction)


def test_disparity_reduction_k_th_largest() -> None:
    layout = RegionLayout(row_edges=np.array([0, 1, 2, 3]), col_edges=np.array([0, 1, 11, 12]))
    disp = np.full((3, 12), 1.0, np.float32)
    disp[1, 1:11] = [10, 9, 8, np.nan, -1, 7, 6, 5, 4, 3]  # 8 valid
    cfg = RegionsConfig(robust_percentile_pct=25.0, min_valid_fraction=0.5, max_depth_m=100.0)
    res = reduce_regions_from_disparity(disp, layout, cfg, 42.0)  # k = 2 -> 9 px
    assert res.depth_m[REGION_INDEX["center"]] == pytest.approx(42.0 / 9.0)
    assert res.valid_fraction[REGION_INDEX["center"]] == 0.8
