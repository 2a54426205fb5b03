"""OBSTACLE_DISTANCE from a disparity image (companion.core.obstacle): bins, units, angles, unknown,
the height band and the robust minimum, against a per-pixel 3D reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import ObstacleDistanceConfig
from companion.core.geometry import StereoGeometry
from companion.core.obstacle import (
    N_BINS,
    UNKNOWN_CM,
    bin_of_bearing,
    obstacle_layout,
    reduce_obstacle_distance,
)

GEOM = StereoGeometry.ideal(672, 376, 90.0, 0.12)
NDISP = 64
CFG = ObstacleDistanceConfig()


def _layout(**kw):
    return obstacle_layout(GEOM, NDISP, CFG.model_copy(update=kw))


def _wall(z_m: float) -> np.ndarray:
    return np.full((GEOM.height_px, GEOM.width_px), np.float32(GEOM.focal_baseline_px_m / z_m), np.float32)


def _reference(disp: np.ndarray, cfg: ObstacleDistanceConfig) -> np.ndarray:
    """Per pixel in float64: the 3D point, its bearing's bin, band membership and horizontal distance."""
    g = GEOM
    h, w = disp.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = disp.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = g.focal_baseline_px_m / d
        x = (u - g.cx_px) * z / g.focal_px
        y = (v - g.cy_px) * z / g.focal_px
    bins = bin_of_bearing(np.degrees(np.arctan((u[0] - g.cx_px) / g.focal_px)))
    bins[: NDISP - 1] = -1
    out = np.full(N_BINS, UNKNOWN_CM, np.int64)
    max_cm = int(round(cfg.max_distance_m * 100))
    min_cm = math.ceil(g.focal_baseline_px_m / (NDISP - 1) * 100)
    for j in range(N_BINS):
        cols = bins == j
        if not cols.any():
            continue
        dj = d[:, cols]
        n_valid = np.count_nonzero(dj >= 0)
        if n_valid == 0 or n_valid < cfg.min_valid_fraction * dj.size:
            continue
        band = (dj > 0) & (np.abs(y[:, cols]) <= cfg.band_half_height_m + 1e-9)
        dist = np.hypot(x[:, cols], z[:, cols])[band]
        if dist.size < cfg.min_points:
            out[j] = max_cm + 1
            continue
        k = max(1, math.ceil(cfg.robust_percentile_pct * dist.size / 100))
        r = np.sort(dist)[k - 1]
        out[j] = max_cm + 1 if r > cfg.max_distance_m else min(max_cm, max(min_cm, math.floor(r * 100)))
    return out


def test_bins_are_5_degrees_clockwise_from_the_nose() -> None:
    assert bin_of_bearing(0.0) == 0 and bin_of_bearing(2.49) == 0 and bin_of_bearing(2.5) == 1
    assert bin_of_bearing(-2.5) == 0 and bin_of_bearing(-2.51) == 71
    assert bin_of_bearing(30.0) == 6 and bin_of_bearing(-45.0) == 63


def test_a_wall_ahead_fills_the_view_and_nothing_else() -> None:
    lay = _layout()
    od = reduce_obstacle_distance(_wall(2.0), lay)
    d = od.distances_cm
    assert d.dtype == np.uint16 and d.shape == (72,)
    assert (od.increment_deg, od.angle_offset_deg, od.frame) == (5, 0.0, 12)
    # The view: 45° right (bins 0..9), the left side to atan((cx - 63)/f) ≈ 39° (bins 64..71).
    in_view = np.flatnonzero(d != UNKNOWN_CM)
    assert set(in_view) == set(range(0, 10)) | set(range(64, 72))
    assert set(in_view) == set(np.flatnonzero(lay.in_view))
    assert 199 <= d[0] <= 200  # straight ahead: the wall's 2 m
    # Sideways the same wall is farther (horizontal distance, not depth): bin 8 is at 40 ± 2.5°.
    assert d[8] == pytest.approx(200 / math.cos(math.radians(37.5)), abs=2)
    assert od.min_distance_cm == math.ceil(GEOM.focal_baseline_px_m / 63 * 100) and od.max_distance_cm == 1200
    np.testing.assert_array_equal(d, _reference(_wall(2.0), CFG))


def test_far_wall_is_no_obstacle_and_nothing_matched_is_unknown() -> None:
    lay = _layout()
    far = reduce_obstacle_distance(_wall(30.0), lay).distances_cm
    assert set(far[lay.in_view]) == {1201}
    blank = reduce_obstacle_distance(np.full((376, 672), np.nan, np.float32), lay).distances_cm
    assert set(blank) == {UNKNOWN_CM}


def test_the_height_band_ignores_the_ground_and_what_is_overhead() -> None:
    g = GEOM
    disp = np.full((g.height_px, g.width_px), np.nan, np.float32)
    z = 1.5
    rows_above = int(g.cy_px - (0.8 * g.focal_px / z))  # 0.8 m above the camera and higher
    disp[:rows_above] = g.focal_baseline_px_m / z
    disp[rows_above:] = g.focal_baseline_px_m / 30.0  # far away elsewhere
    lay = _layout(band_half_height_m=0.4)
    d = reduce_obstacle_distance(disp, lay).distances_cm
    assert set(d[lay.in_view]) == {1201}
    lay_tall = _layout(band_half_height_m=3.0)
    assert reduce_obstacle_distance(disp, lay_tall).distances_cm[0] < 200


def test_a_post_to_the_right_lands_in_its_bin_and_one_speck_is_not_an_obstacle() -> None:
    g = GEOM
    disp = np.full((g.height_px, g.width_px), np.float32(g.focal_baseline_px_m / 30.0), np.float32)
    u = int(round(g.cx_px + g.focal_px * math.tan(math.radians(30.0))))
    disp[:, u - 2 : u + 3] = g.focal_baseline_px_m / 1.0  # a post 1 m deep at 30° right
    disp[180, 300] = g.focal_baseline_px_m / 0.5  # one false match ahead
    lay = _layout()
    d = reduce_obstacle_distance(disp, lay).distances_cm
    assert 112 <= d[6] <= 116  # 1 m depth at 30°: 1.155 m horizontal
    others = [j for j in np.flatnonzero(lay.in_view) if j != 6]
    assert set(d[others]) == {1201}
    np.testing.assert_array_equal(d, _reference(disp, CFG))


def test_matches_the_per_pixel_reference_on_noisy_scenes() -> None:
    rng = np.random.default_rng(7)
    g = GEOM
    for trial in range(4):
        z = rng.uniform(0.4, 15.0, size=(g.height_px, g.width_px))
        disp = (g.focal_baseline_px_m / z).astype(np.float32)
        disp[rng.random(disp.shape) < 0.3] = np.nan
        disp[rng.random(disp.shape) < 0.01] = 0.0
        cfg = CFG.model_copy(update={"robust_percentile_pct": [0.0, 2.0, 10.0, 2.0][trial], "min_points": 5})
        got = reduce_obstacle_distance(disp, obstacle_layout(g, NDISP, cfg)).distances_cm.astype(np.int64)
        ref = _reference(disp, cfg)
        # The band edge and float32 rounding may move one pixel in or out of a bin: 1 cm at most here.
        assert np.max(np.abs(got - ref)) <= 1, (got, ref)


def test_wrong_size_is_refused() -> None:
    with pytest.raises(ValueError, match="does not match"):
        reduce_obstacle_distance(np.zeros((10, 10), np.float32), _layout())
