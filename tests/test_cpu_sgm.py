"""The compiled CPU census + SGM engine (``stereo.backend = "cpu-sgm"``) equals the NumPy reference bit for
bit: disparities, region depths and OBSTACLE_DISTANCE, on the pairs the reference's and the GPU kernels'
tests use (odd sizes, odd and wide disparity counts, flat patches with tied sums, both path sets, every
post-processing switch); and ``auto`` picks it only where it keeps the camera's rate.

The kernels compile once, into pytest's cache folder (images are small, so the reference is quick).
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from stereo_pairs import shifted_pair

from companion import backends
from companion.config import CompanionConfig
from companion.core.disparity import sgm as S
from companion.errors import BackendError, FrameError

pytest.importorskip("numba")


@pytest.fixture(scope="module", autouse=True)
def _numba_cache() -> None:
    """The kernels bound to the session's cache folder (``numba_cache_dir`` in conftest: pytest's own,
    so they compile once per checkout), never the user's."""
    from companion.cpu import load_kernels

    load_kernels()


def _matcher(w: int, h: int, d: int, **kw):
    from companion.cpu import CpuSgmMatcher

    return CpuSgmMatcher(w, h, d, **kw)


def _assert_equal(left: np.ndarray, right: np.ndarray, d: int, **params) -> None:
    h, w = left.shape
    got = _matcher(w, h, d, **params).compute_fixed(left, right)
    np.testing.assert_array_equal(got, S.sgm_match(left, right, d, **params))


@pytest.mark.parametrize(
    ("D", "p1", "p2", "paths", "u", "lr", "median"),
    [
        (6, 10, 120, 4, 10, 1, True),
        (8, 3, 193, 8, 0, 0, False),  # largest P2: path costs reach 255
        (5, 192, 193, 8, 25, -1, True),
        (16, 7, 40, 4, 5, 2, True),  # D wider than the image
        (2, 0, 1, 4, 0, 0, True),  # the fewest disparities, P1 = 0
    ],
)
def test_equals_the_reference_on_the_literal_rules_pairs(D: int, p1: int, p2: int, paths: int, u: int, lr: int, median: bool) -> None:
    left, right = shifted_pair(9, 14, 2, seed=D + p1)
    left[2:6, 4:9] = 90  # a flat patch: equal sums, ties to the largest d
    right[2:6, 2:7] = 90
    _assert_equal(left, right, D, p1=p1, p2=p2, paths=paths, uniqueness_ratio_pct=u, lr_max_diff_px=lr, median=median)


@pytest.mark.parametrize(
    ("w", "h", "d", "paths", "p1", "p2", "u", "lr", "median"),
    [
        (40, 18, 32, 8, 10, 120, 10, 1, True),
        (48, 12, 128, 4, 8, 80, 0, 0, False),  # D far wider than the image, u = 0, strict LR
        (56, 16, 48, 4, 192, 193, 5, -1, True),  # costs up to 255, no LR
        (24, 70, 16, 4, 10, 120, 10, 1, True),  # taller than wide
        (37, 23, 17, 8, 10, 120, 10, 3, True),  # odd size and an odd disparity count
        (1, 1, 4, 4, 10, 120, 10, 1, True),  # one pixel
        (97, 5, 33, 4, 10, 120, 50, 1, True),
    ],
)
def test_equals_the_reference_on_the_gpu_kernels_pairs(
    w: int, h: int, d: int, paths: int, p1: int, p2: int, u: int, lr: int, median: bool
) -> None:
    rng = np.random.default_rng([w, d, paths])
    left = rng.integers(0, 256, (h, w), dtype=np.uint8)
    right = np.roll(left, -int(rng.integers(3, 12)), axis=1)
    right = np.clip(right.astype(int) + rng.integers(-3, 4, right.shape), 0, 255).astype(np.uint8)
    left[h // 4 : h // 2, w // 3 : w // 2] = 90  # a flat patch: equal sums everywhere
    right[h // 4 : h // 2, w // 3 : w // 2] = 90
    _assert_equal(left, right, d, p1=p1, p2=p2, paths=paths, uniqueness_ratio_pct=u, lr_max_diff_px=lr, median=median)


@pytest.mark.parametrize(("window", "rng_px", "paths"), [(100, 2, 4), (12, 0, 8), (5000, 1, 4)])
def test_equals_the_reference_with_peak_removal(window: int, rng_px: int, paths: int) -> None:
    """Rule 10's peak removal (OpenCV's filterSpeckles in the engine) on a pair with a plain patch under
    noise, at both scales (the near-range check's coarse pair removes its own peaks)."""
    rng = np.random.default_rng([window, paths])
    w, h = 120, 64
    left = rng.integers(0, 256, (h, w), dtype=np.uint8)
    right = np.roll(left, -6, axis=1)
    plain = (slice(10, 54), slice(40, 110))
    left[plain] = 120 + rng.integers(-2, 3, left[plain].shape)
    right[plain] = 120 + rng.integers(-2, 3, right[plain].shape)
    params = dict(p1=10, p2=120, paths=paths, speckle_window_px=window, speckle_range_px=rng_px)
    _assert_equal(left, right, 24, **params)
    m = _matcher(w, h, 24, **params)
    fixed = m.compute_fixed(left, right)
    np.testing.assert_array_equal(m.compute(left, right), S.fixed_to_float(fixed))
    assert (fixed != S.sgm_match(left, right, 24, p1=10, p2=120, paths=paths)).any()


def test_flat_and_saturated_images_equal_the_reference() -> None:
    flat = np.full((12, 30), 128, np.uint8)
    _assert_equal(flat, flat, 16, p1=10, p2=120)
    black, white = np.zeros((12, 30), np.uint8), np.full((12, 30), 255, np.uint8)
    _assert_equal(black, white, 16, p1=10, p2=120, paths=8)


def test_one_matcher_matches_frame_after_frame_into_the_callers_buffer() -> None:
    m = _matcher(90, 40, 16, p1=10, p2=120)
    out = np.empty((40, 90), np.float32)
    for seed, shift in ((2, 5), (3, 9)):
        left, right = shifted_pair(40, 90, shift, seed=seed)
        assert m.compute(left, right, out=out) is out
        np.testing.assert_array_equal(out, S.fixed_to_float(S.sgm_match(left, right, 16, p1=10, p2=120)))


def test_a_frame_allocates_nothing_large() -> None:
    left, right = shifted_pair(120, 200, 7, seed=5)
    m = _matcher(200, 120, 32, p1=10, p2=120)
    out = np.empty((120, 200), np.float32)
    m.compute(left, right, out=out)
    tracemalloc.start()
    try:
        m.compute(left, right, out=out)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16_384  # the image alone is 24 kB, the cost volume 768 kB


def test_one_thread_and_all_threads_agree() -> None:
    left, right = shifted_pair(50, 80, 6, seed=7)
    a = _matcher(80, 50, 16, p1=10, p2=120, threads=1).compute_fixed(left, right)
    b = _matcher(80, 50, 16, p1=10, p2=120, threads=0).compute_fixed(left, right)
    np.testing.assert_array_equal(a, b)


def test_a_frame_of_another_size_or_type_is_refused() -> None:
    m = _matcher(30, 20, 16, p1=10, p2=120)
    with pytest.raises(FrameError, match="built for 30x20"):
        m.compute(np.zeros((20, 31), np.uint8), np.zeros((20, 31), np.uint8))
    with pytest.raises(FrameError, match="uint8"):
        m.compute(np.zeros((20, 30), np.float32), np.zeros((20, 30), np.float32))
    with pytest.raises(ValueError, match="P1"):
        _matcher(30, 20, 16, p1=20, p2=10)


def _cfg(**stereo) -> CompanionConfig:
    return CompanionConfig.model_validate({"stereo": {"num_disparities": 32, **stereo}})


def test_the_estimator_equals_the_reference_estimator_regions_and_obstacle_distance() -> None:
    """Same rectification, region reduction and OBSTACLE_DISTANCE as the other CPU estimators."""
    from companion.bench.common import BenchSize, rendered_frames

    w, h = 160, 96
    _, frames = rendered_frames(BenchSize(w, h, 32), 2, seed=3)
    cfg = _cfg(backend="cpu-sgm", cpu_threads=2)
    cfg = cfg.model_copy(update={"obstacle_distance": cfg.obstacle_distance.model_copy(update={"send": "on"})})
    ref_cfg = cfg.model_copy(update={"stereo": cfg.stereo.model_copy(update={"backend": "reference"})})
    est = backends.make_estimator(cfg, w, h)
    ref = backends.make_estimator(ref_cfg, w, h)
    assert est.name == "cpu-sgm"
    for frame in frames:
        a = est.estimate(frame, want_disparity=True, near_block_px=8)
        b = ref.estimate(frame, want_disparity=True, near_block_px=8)
        np.testing.assert_array_equal(a.disparity, b.disparity)
        np.testing.assert_array_equal(a.regions.depth_m, b.regions.depth_m)
        np.testing.assert_array_equal(a.regions.valid_fraction, b.regions.valid_fraction)
        np.testing.assert_array_equal(a.near_blocks, b.near_blocks)
        assert a.obstacle is not None and b.obstacle is not None
        np.testing.assert_array_equal(a.obstacle.distances_cm, b.obstacle.distances_cm)
        assert np.isfinite(a.regions.depth_m).any()


def _shared_data(name: str) -> Path:
    """``shared/data/<name>`` beside the checkout or a folder above it (as in tests/test_eval.py)."""
    root = Path(__file__).resolve().parents[1]
    for parent in root.parents:
        if (parent / "shared" / "data" / name).is_dir():
            return parent / "shared" / "data" / name
    return root.parent / "shared" / "data" / name


@pytest.mark.slow
@pytest.mark.skipif(not (_shared_data("aloe") / "aloeGT.png").is_file(), reason="no shared Aloe pair")
def test_aloe_at_half_size_equals_the_reference() -> None:
    from companion.core.evaluation import load_middlebury, rescale

    pair = rescale(load_middlebury(_shared_data("aloe")), 0.5)
    _assert_equal(pair.left, pair.right, 112, p1=10, p2=120, speckle_window_px=100, speckle_range_px=2)


def test_the_backend_makes_the_dense_map_and_refuses_the_core_factory() -> None:
    from companion.core.disparity import make_cpu_matcher

    got = CompanionConfig.model_validate({"stereo": {"backend": "cpu-sgm"}})
    assert got.planner.block_erode_px == 1
    with pytest.raises(BackendError, match="cpu-sgm"):
        make_cpu_matcher(_cfg(backend="cpu-sgm").stereo)


@pytest.mark.parametrize(
    ("cores", "threads", "fps", "keeps"),
    [
        (2, 0, 30.0, False),  # 672x376x64 at 30 fps: 485 M px·disparities per second for 2 cores
        (8, 0, 15.0, False),  # its paths run in two halves: more cores do not count
        (2, 0, 7.5, True),
        (2, 1, 7.5, False),  # cpu_threads caps the cores it may use
        (1, 0, 5.0, True),
    ],
)
def test_auto_picks_cpu_sgm_where_it_keeps_the_camera_rate(
    monkeypatch: pytest.MonkeyPatch, cores: int, threads: int, fps: float, keeps: bool
) -> None:
    cfg = CompanionConfig.model_validate(
        {"stereo": {"cpu_threads": threads, "num_disparities": 64}, "camera": {"width_px": 672, "height_px": 376, "fps_hz": fps}}
    )
    import companion.config as config

    assert config.cpu_sgm_keeps_rate(cfg, cores) is keeps
    monkeypatch.setattr(config, "cuda_available", lambda: False)
    monkeypatch.setattr(config, "cpu_cores", lambda: cores)
    assert backends.resolve_backend(cfg) == ("cpu-sgm" if keeps else "opencv-bm")
    never = cfg.model_copy(update={"stereo": cfg.stereo.model_copy(update={"cpu_sgm_cells_per_core_s": 0.0})})
    assert backends.resolve_backend(never) == "opencv-bm"
    explicit = cfg.model_copy(update={"stereo": cfg.stereo.model_copy(update={"backend": "opencv-bm"})})
    assert backends.resolve_backend(explicit) == "opencv-bm"


def test_an_unwritable_cache_folder_is_one_line_naming_it(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import numba

    from companion.cpu import load_kernels

    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocker / "numba"))
    with pytest.raises(BackendError, match="cache folder .*NUMBA_CACHE_DIR"):
        load_kernels()
