"""The near-range check (rule 11 of :mod:`companion.core.disparity.sgm`): a surface nearer than the rig's
range makes its regions read the nearest measurable depth, not farther, with every engine; a scene
inside the range reads exactly as without the check, and bars that fool the shrunk match are not read
near; the CPU engine and the GPU kernels (run on the CPU by the host
emulation) equal the reference bit for bit.

A wall nearer than the range cannot be matched inside ``[0, D)``: census + SGM leaves much of it
unmatched and matches the rest at a wrong disparity inside the range, so the region reads some way
behind the wall (the unsafe direction).
"""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
from stereo_pairs import shifted_pair

from companion.config import CompanionConfig
from companion.config.core import RegionsConfig
from companion.core.depth import disparity_to_depth
from companion.core.disparity import make_cpu_matcher
from companion.core.disparity import sgm as S
from companion.core.geometry import StereoGeometry
from companion.core.regions import (
    RegionLayout,
    reduce_regions,
    reduce_regions_from_disparity,
    region_layout,
)

_SGM = dict(p1=10, p2=120)


def _wall_pair(width_px: int, height_px: int, distance_m: float, kind: str) -> tuple[StereoGeometry, np.ndarray, np.ndarray]:
    """A rendered wall ``distance_m`` ahead filling the view (ZED-like rig: 87°, 12 cm; sensor noise 2
    grey levels an eye): the geometry and the grey uint8 ``(H, W)`` left and right eyes."""
    from companion.sim.render import (
        Box,
        Photometry,
        Pose,
        Scene,
        StereoRenderer,
        Surface,
    )

    geometry = StereoGeometry.ideal(width_px, height_px, hfov_deg=87.0, baseline_m=0.12)
    wall = Box((2.0 + distance_m + 0.05, 0.0, -1.5), (0.1, 6.0, 3.0), surface=Surface(kind=kind))
    renderer = StereoRenderer(geometry, Scene(obstacles=(wall,)), seed=1)
    noise = Photometry(noise_std=2.0)
    res = renderer.render(Pose.at(2.0, 0.0, 1.5), left=noise, right=noise, rng=np.random.default_rng(0))
    grey = [cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) for img in (res.left_bgr, res.right_bgr)]
    return geometry, grey[0], grey[1]


def _regions(fixed: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    layout = region_layout(geometry, RegionsConfig())
    return reduce_regions_from_disparity(S.fixed_to_float(fixed), layout, RegionsConfig(), geometry.focal_baseline_px_m).depth_m


def _nearest_m(geometry: StereoGeometry, num_disparities: int) -> float:
    return float(np.float32(geometry.focal_baseline_px_m) / np.float32(num_disparities - 1))


# ---------------------------------------------------------------------------------------------------------
# the rule


def test_the_coarse_pair_is_the_rounded_mean_of_each_block() -> None:
    img = np.arange(8 * 12, dtype=np.uint8).reshape(8, 12)
    img[:4, :4] = np.arange(16).reshape(4, 4)  # mean 7.5: rounds up to 8
    out = S.shrink(img)
    assert out.shape == (2, 3) and out.dtype == np.uint8
    assert out[0, 0] == 8
    assert out[1, 2] == (img[4:8, 8:12].astype(int).sum() + 8) // 16


def test_a_pair_beyond_the_range_reads_the_nearest_measurable_disparity() -> None:
    left, right = shifted_pair(64, 120, 24, seed=1)  # 24 px: beyond 16 disparities, within the coarse 2 x 16
    plain = S.sgm_match(left, right, 16, near_range=False, **_SGM)
    checked = S.sgm_match(left, right, 16, **_SGM)
    interior = np.s_[8:-8, 40:-8]  # away from the borders and the unmatched left band
    assert (plain[interior] < 0).mean() > 0.3  # much of it: no match the full-size matcher can stand behind
    # every pixel the full-size matcher left invalid reads the nearest measurable disparity
    assert (checked[interior][plain[interior] < 0] == 16 * 15).all()
    # and a valid full-size match is never overridden
    changed = checked != plain
    assert (plain[changed] < 0).all() and (checked[changed] == 16 * 15).all()


def test_a_pair_inside_the_range_is_left_as_it_was() -> None:
    left, right = shifted_pair(64, 120, 6, seed=2)
    np.testing.assert_array_equal(S.sgm_match(left, right, 16, **_SGM), S.sgm_match(left, right, 16, near_range=False, **_SGM))


@pytest.mark.parametrize(("h", "w", "d"), [(27, 120, 16), (64, 35, 16), (64, 120, 3)])
def test_no_check_where_the_coarse_pair_is_smaller_than_the_census_window(h: int, w: int, d: int) -> None:
    assert S.near_range_shape(h, w, d) is None
    left, right = shifted_pair(h, w, 20, seed=3)
    np.testing.assert_array_equal(S.sgm_match(left, right, d, **_SGM), S.sgm_match(left, right, d, near_range=False, **_SGM))


# ---------------------------------------------------------------------------------------------------------
# rendered walls, every engine


@pytest.mark.parametrize("kind", ["textured", "plain"])
@pytest.mark.parametrize("distance_m", [0.3, 0.5])
def test_a_wall_nearer_than_the_range_reads_near_not_far(kind: str, distance_m: float) -> None:
    """336x188 px, 32 disparities: nothing nearer than 0.69 m is measurable. Without the check the
    regions read up to 0.9 m (a wall at 0.3 m); with it each reads 0.69 m."""
    geometry, left, right = _wall_pair(336, 188, distance_m, kind)
    nearest = _nearest_m(geometry, 32)
    without = _regions(S.sgm_match(left, right, 32, near_range=False, **_SGM), geometry)
    assert (without > nearest).any()  # the failure the check is for
    np.testing.assert_array_equal(_regions(S.sgm_match(left, right, 32, **_SGM), geometry), np.full(9, nearest))


@pytest.mark.parametrize("kind", ["textured", "plain"])
def test_a_wall_inside_the_range_reads_as_before(kind: str) -> None:
    geometry, left, right = _wall_pair(336, 188, 1.5, kind)
    with_check = S.sgm_match(left, right, 32, **_SGM)
    np.testing.assert_array_equal(with_check, S.sgm_match(left, right, 32, near_range=False, **_SGM))
    assert (_regions(with_check, geometry) > 1.3).all()


def test_the_benchmark_corridor_reads_as_before() -> None:
    """Obstacles 1.2 m and farther on a textured corridor: the coarse match finds nothing beyond the
    range, so no pixel changes (no new phantom)."""
    from companion.bench.common import BenchSize, rendered_frames
    from companion.core.stereo import split_frame, to_grey

    _, frames = rendered_frames(BenchSize(336, 188, 32), 3, seed=0)
    for frame in frames:
        left, right = (to_grey(e) for e in split_frame(frame, 336, 188))
        np.testing.assert_array_equal(
            S.sgm_match(left, right, 32, **_SGM), S.sgm_match(left, right, 32, near_range=False, **_SGM)
        )


@pytest.mark.parametrize(("period_m", "distance_m"), [(0.04, 3.5), (0.06, 2.0), (0.1, 2.0), (0.1, 3.5), (0.2, 3.5)])
def test_bars_inside_the_range_are_not_read_near(period_m: float, distance_m: float) -> None:
    """Opaque bars (a radiator's fins) in front of a wall: shrunk 4 times, the bars' period is a few
    pixels and the coarse match locks onto a wrong repeat beyond the range in patches. The full-size
    matcher matches the bars there, and the check never overrides a valid full-size match: no region
    reads near."""
    from companion.sim.render import (
        Box,
        Photometry,
        Pose,
        Scene,
        StereoRenderer,
        Surface,
    )

    geometry = StereoGeometry.ideal(336, 188, hfov_deg=87.0, baseline_m=0.12)
    bars = Surface(kind="bars", bar_period_m=period_m, bar_width_m=period_m / 4, see_through=False)
    scene = Scene(obstacles=(Box((2.05 + distance_m, 0.0, -1.5), (0.1, 6.0, 3.0), surface=bars),
                             Box((5.0 + distance_m, 0.0, -1.5), (0.1, 8.0, 4.0))))
    noise = Photometry(noise_std=2.0)
    res = StereoRenderer(geometry, scene, seed=1).render(Pose.at(2.0, 0.0, 1.5), left=noise, right=noise,
                                                         rng=np.random.default_rng(0))
    left, right = (cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) for img in (res.left_bgr, res.right_bgr))
    with_check = _regions(S.sgm_match(left, right, 32, **_SGM), geometry)
    without = _regions(S.sgm_match(left, right, 32, near_range=False, **_SGM), geometry)
    assert (with_check >= 0.95 * without).all(), (with_check, without)


@pytest.mark.parametrize("backend", ["opencv-bm", "opencv-sgbm"])
def test_the_opencv_matchers_do_not_read_a_too_near_wall_far(backend: str) -> None:
    """StereoBM leaves the wall unmatched (unknown, which counts as near); StereoSGBM reads it within
    a few tens of centimetres of the nearest measurable depth. Neither reads it farther than 1 m."""
    geometry, left, right = _wall_pair(336, 188, 0.3, "plain")
    cfg = CompanionConfig.model_validate({"stereo": {"backend": backend, "num_disparities": 32}})
    disp = make_cpu_matcher(cfg.stereo).compute(left, right)
    layout = region_layout(geometry, RegionsConfig())
    depth = reduce_regions(disparity_to_depth(disp, geometry.focal_baseline_px_m), layout, RegionsConfig()).depth_m
    assert all(np.isnan(z) or z < 1.0 for z in depth), depth


# ---------------------------------------------------------------------------------------------------------
# the CPU engine


@pytest.fixture(scope="module")
def _numba_cache() -> None:
    """The kernels bound to the session's cache folder (``numba_cache_dir`` in conftest): nothing in
    the user's cache."""
    pytest.importorskip("numba")
    from companion.cpu import load_kernels

    load_kernels()


@pytest.mark.usefixtures("_numba_cache")
@pytest.mark.parametrize(
    ("h", "w", "shift", "d", "paths", "u", "lr", "median"),
    [
        (64, 120, 24, 16, 4, 10, 1, True),
        (37, 41, 13, 8, 8, 10, 1, True),  # odd sizes: the last coarse row and column serve the remainder
        (40, 90, 50, 32, 4, 0, -1, False),  # beyond even the coarse range: whatever it finds
        (30, 47, 11, 7, 8, 25, 0, True),  # an odd disparity count: 3 coarse disparities
    ],
)
def test_the_cpu_engine_equals_the_reference(h: int, w: int, shift: int, d: int, paths: int, u: int, lr: int, median: bool) -> None:
    from companion.cpu import CpuSgmMatcher

    left, right = shifted_pair(h, w, shift, seed=shift)
    params = dict(p1=10, p2=120, paths=paths, uniqueness_ratio_pct=u, lr_max_diff_px=lr, median=median)
    reference = S.sgm_match(left, right, d, **params)
    assert (reference != S.sgm_match(left, right, d, near_range=False, **params)).any() or shift > 2 * d
    m = CpuSgmMatcher(w, h, d, **params)
    np.testing.assert_array_equal(m.compute_fixed(left, right), reference)
    np.testing.assert_array_equal(m.compute(left, right), S.fixed_to_float(reference))


@pytest.mark.usefixtures("_numba_cache")
def test_the_cpu_engine_reads_a_too_near_wall_near() -> None:
    from companion.cpu import CpuSgmMatcher

    geometry, left, right = _wall_pair(336, 188, 0.3, "plain")
    got = CpuSgmMatcher(336, 188, 32, **_SGM).compute_fixed(left, right)
    np.testing.assert_array_equal(got, S.sgm_match(left, right, 32, **_SGM))
    np.testing.assert_array_equal(_regions(got, geometry), np.full(9, _nearest_m(geometry, 32)))


# ---------------------------------------------------------------------------------------------------------
# the GPU kernels on the CPU

_needs_gxx = pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++ to compile the kernels for the CPU")


def _host_run(left: np.ndarray, right: np.ndarray, d: int, fb: float, layout: RegionLayout | None = None,
              **params) -> dict[str, np.ndarray]:
    from companion.gpu.hostemu import HostSgmKernels

    h, w = left.shape
    if layout is None:
        rows_e, cols_e = [0, h // 3, 2 * h // 3, h], [0, w // 3, 2 * w // 3, w]
    else:
        rows_e, cols_e = [int(e) for e in layout.row_edges], [int(e) for e in layout.col_edges]
    kernels = HostSgmKernels(w, h, d, params.get("paths", 4), rows_e, cols_e)
    out = kernels.run(left, right, params["p1"], params["p2"], params.get("uniqueness_ratio_pct", 10),
                      params.get("lr_max_diff_px", 1), params.get("median", True), fb=fb)
    out["layout_rows"], out["layout_cols"] = np.array(rows_e), np.array(cols_e)
    return out


@pytest.mark.slow
@_needs_gxx
@pytest.mark.parametrize(
    ("h", "w", "shift", "d", "paths", "u", "lr", "median"),
    [
        (36, 64, 24, 16, 4, 10, 1, True),
        (30, 41, 13, 8, 8, 25, 0, False),  # odd sizes, 8 paths, strict left-right check, no median
    ],
)
def test_the_gpu_kernels_equal_the_reference(h: int, w: int, shift: int, d: int, paths: int, u: int, lr: int, median: bool) -> None:
    left, right = shifted_pair(h, w, shift, seed=shift)
    params = dict(p1=10, p2=120, paths=paths, uniqueness_ratio_pct=u, lr_max_diff_px=lr, median=median)
    out = _host_run(left, right, d, 50.0, **params)
    np.testing.assert_array_equal(out["coarse_left"], S.shrink(left))
    np.testing.assert_array_equal(out["coarse_right"], S.shrink(right))
    hc, wc, dc = S.near_range_shape(h, w, d)
    coarse = S.sgm_match(S.shrink(left), S.shrink(right), dc, near_range=False, **params)
    np.testing.assert_array_equal(out["coarse_disparity"], coarse)
    reference = S.sgm_match(left, right, d, **params)
    assert (reference != S.sgm_match(left, right, d, near_range=False, **params)).any()
    np.testing.assert_array_equal(out["disparity"], reference)
    expected = reduce_regions_from_disparity(
        S.fixed_to_float(reference), RegionLayout(out["layout_rows"], out["layout_cols"]), RegionsConfig(), 50.0
    )
    np.testing.assert_array_equal(out["regions"][:9], expected.depth_m)
    np.testing.assert_array_equal(out["regions"][9:], expected.valid_fraction)


@pytest.mark.slow
@_needs_gxx
def test_the_gpu_kernels_read_a_too_near_wall_near() -> None:
    """128x72 px, 16 disparities: nothing nearer than 0.54 m is measurable; a plain wall at 0.3 m."""
    geometry, left, right = _wall_pair(128, 72, 0.3, "plain")
    out = _host_run(left, right, 16, geometry.focal_baseline_px_m, region_layout(geometry, RegionsConfig()), **_SGM)
    reference = S.sgm_match(left, right, 16, **_SGM)
    np.testing.assert_array_equal(out["disparity"], reference)
    nearest = _nearest_m(geometry, 16)
    assert (_regions(S.sgm_match(left, right, 16, near_range=False, **_SGM), geometry) > nearest).any()
    layout = RegionLayout(out["layout_rows"], out["layout_cols"])
    expected = reduce_regions_from_disparity(S.fixed_to_float(reference), layout, RegionsConfig(), geometry.focal_baseline_px_m)
    np.testing.assert_array_equal(out["regions"][:9], expected.depth_m)
    np.testing.assert_array_equal(out["regions"][:9], np.full(9, nearest))


# ---------------------------------------------------------------------------------------------------------
# a real pair: Middlebury's Aloe (the shared copy, where present)


def _shared_data(name: str):
    """``shared/data/<name>`` beside the checkout or a folder above it (as in tests/test_eval.py)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for parent in root.parents:
        if (parent / "shared" / "data" / name).is_dir():
            return parent / "shared" / "data" / name
    return root.parent / "shared" / "data" / name


_needs_aloe = pytest.mark.skipif(not (_shared_data("aloe") / "aloeGT.png").is_file(), reason="no shared Aloe pair")


@pytest.mark.slow
@_needs_aloe
@pytest.mark.usefixtures("_numba_cache")
def test_aloe_with_too_few_disparities_reads_its_near_leaves_near() -> None:
    """Aloe at full size has disparities up to 211 px; with 64 the plant's leaves are nearer than the
    range. Without the check two upper regions read farther than the nearest measurable depth (the
    leaves matched a wrong, smaller disparity); with it every region whose true depth is nearer than the
    range reads the nearest measurable depth (the leaves the full-size matcher left unmatched)."""
    from companion.core.evaluation import load_middlebury
    from companion.cpu import CpuSgmMatcher

    pair = load_middlebury(_shared_data("aloe"))
    h, w = pair.left.shape
    layout = RegionLayout(np.array([0, h // 3, 2 * h // 3, h]), np.array([0, w // 3, 2 * w // 3, w]))
    fb = 100.0  # any f·B: the regions are compared in the same units
    cfg = RegionsConfig()
    nearest = float(np.float32(fb) / np.float32(63))
    truth = reduce_regions_from_disparity(np.where(pair.disparity > 0, pair.disparity, np.nan).astype(np.float32),
                                          layout, cfg, fb).depth_m
    too_near = truth < nearest
    assert too_near.sum() >= 6
    read = {}
    for near_range in (False, True):
        fixed = CpuSgmMatcher(w, h, 64, near_range=near_range, **_SGM).compute_fixed(pair.left, pair.right)
        read[near_range] = reduce_regions_from_disparity(S.fixed_to_float(fixed), layout, cfg, fb).depth_m
    assert (read[False][too_near] > 1.05 * nearest).any()
    np.testing.assert_array_equal(read[True][too_near], np.full(too_near.sum(), nearest))


@pytest.mark.slow
@_needs_aloe
def test_aloe_inside_the_range_reads_exactly_as_without_the_check() -> None:
    """Aloe at half size with 112 disparities: every surface inside the range, no pixel changes."""
    from companion.core.evaluation import load_middlebury, rescale

    pair = rescale(load_middlebury(_shared_data("aloe")), 0.5)
    np.testing.assert_array_equal(
        S.sgm_match(pair.left, pair.right, 112, **_SGM), S.sgm_match(pair.left, pair.right, 112, near_range=False, **_SGM)
    )


# ---------------------------------------------------------------------------------------------------------
# the estimators: the whole frame, the region depths the controller sees


def _ideal_cfg(backend: str, num_disparities: int) -> CompanionConfig:
    """The rendered rig as the ideal one (frames already rectified): 87°, 12 cm."""
    return CompanionConfig.model_validate({
        "stereo": {"backend": backend, "num_disparities": num_disparities},
        "calibration": {"ideal_hfov_deg": 87.0, "ideal_baseline_m": 0.12},
        "gpu": {"disparity_preview_downsample": 0},
    })


def _gpu_present() -> bool:
    from companion.backends import cuda_available

    return cuda_available()


@pytest.mark.parametrize(
    "backend",
    [
        "cpu-sgm",
        pytest.param("cupy", marks=[pytest.mark.gpu, pytest.mark.skipif(not _gpu_present(), reason="needs CuPy and a CUDA device")]),
    ],
)
def test_the_estimators_read_a_too_near_wall_as_the_reference(backend: str, request: pytest.FixtureRequest) -> None:
    """A plain wall 0.3 m ahead, 336x188 px with 32 disparities: the backend's estimator gives the
    reference estimator's disparity and region depths, each region the nearest measurable depth."""
    from companion.backends import make_estimator

    if backend == "cpu-sgm":
        request.getfixturevalue("_numba_cache")
    geometry, left, right = _wall_pair(336, 188, 0.3, "plain")
    frame = np.ascontiguousarray(np.hstack([left, right]))
    est = make_estimator(_ideal_cfg(backend, 32), 336, 188)
    ref = make_estimator(_ideal_cfg("reference", 32), 336, 188)
    assert est.name == backend
    a, b = est.estimate(frame, want_disparity=True), ref.estimate(frame, want_disparity=True)
    np.testing.assert_array_equal(a.disparity, b.disparity)
    np.testing.assert_array_equal(a.regions.depth_m, b.regions.depth_m)
    np.testing.assert_array_equal(a.regions.valid_fraction, b.regions.valid_fraction)
    assert est.geometry.focal_baseline_px_m == pytest.approx(geometry.focal_baseline_px_m)
    np.testing.assert_array_equal(a.regions.depth_m, np.full(9, _nearest_m(est.geometry, 32)))
