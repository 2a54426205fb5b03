"""End to end on rendered stereo pairs with ground truth: region depths and decisions."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import CompanionConfig, apply_patch, parse_config
from companion.backends import make_pipeline
from companion.core.estimator import CpuRegionEstimator
from companion.core.regions import reduce_regions
from companion.sim.render import Box, Pose, Scene, StereoRenderer
from companion.core.types import REGION_INDEX, DecisionKind
from companion.errors import BackendError
from peers.fakes import FaultingEstimator

W, H = 672, 376
ALT_M = 1.5
POSE = Pose.at(0.0, 0.0, ALT_M)


def _render(scene: Scene, seed: int = 1):
    cfg = CompanionConfig()
    pipeline = make_pipeline(cfg, W, H)
    renderer = StereoRenderer(pipeline.geometry, scene, seed=seed)
    result = renderer.render(POSE)
    frame = result.side_by_side()
    return cfg, pipeline, frame, result.depth_m


def _wall(distance_m: float, east_from_m: float = -20.0, east_to_m: float = 20.0, height_m: float = 12.0) -> Box:
    """A thick wall whose near face is ``distance_m`` north of the origin."""
    width = east_to_m - east_from_m
    return Box.on_ground(distance_m + 0.5, 0.5 * (east_from_m + east_to_m), (1.0, width, height_m))


@pytest.mark.parametrize("distance_m", [1.0, 1.5, 2.0, 2.5, 3.0])
def test_region_depths_within_5_percent_of_truth(distance_m: float) -> None:
    cfg, pipeline, frame, true_depth = _render(Scene(obstacles=(_wall(distance_m),)))
    result = pipeline.process(frame, timestamp_s=0.0)
    truth = reduce_regions(true_depth, pipeline.estimator.layout, cfg.regions).depth_m
    got = result.refined.depth_m
    assert np.all(np.isfinite(got)), result.refined.as_dict()
    np.testing.assert_allclose(got, truth, rtol=0.05)
    # and the centre sees the wall itself
    assert got[REGION_INDEX["center"]] == pytest.approx(distance_m, rel=0.05)


def test_reference_backend_agrees_with_truth_too() -> None:
    scene = Scene(obstacles=(_wall(1.5),))
    cfg = apply_patch(CompanionConfig(), {"stereo": {"backend": "reference"}})
    estimator = CpuRegionEstimator(cfg, W, H)
    renderer = StereoRenderer(estimator.geometry, scene, seed=2)
    rendered = renderer.render(POSE)
    est = estimator.estimate(rendered.side_by_side())
    truth = reduce_regions(rendered.depth_m, estimator.layout, cfg.regions).depth_m
    np.testing.assert_allclose(est.regions.depth_m, truth, rtol=0.05)


def test_box_ahead_with_the_right_side_free_turns_right() -> None:
    # A box at 1 m covering the centre and everything to its left; open space on the right.
    box = Box.on_ground(1.0 + 0.5, -2.0, (1.0, 4.3, 6.0))  # east -4.15 .. +0.15
    _, pipeline, frame, _ = _render(Scene(obstacles=(box,)))
    result = pipeline.process(frame, timestamp_s=0.0)
    d = result.decision
    assert d.kind is DecisionKind.AVOID, (d, result.refined.as_dict())
    assert d.yaw > 0.3


def test_box_ahead_with_the_left_side_free_turns_left() -> None:
    box = Box.on_ground(1.0 + 0.5, 2.0, (1.0, 4.3, 6.0))
    _, pipeline, frame, _ = _render(Scene(obstacles=(box,)))
    d = pipeline.process(frame, timestamp_s=0.0).decision
    assert d.kind is DecisionKind.AVOID and d.yaw < -0.3, d


def test_nothing_within_3_m_flies_straight() -> None:
    far_box = Box.on_ground(12.0, 0.0, (1.0, 2.0, 2.0))
    _, pipeline, frame, _ = _render(Scene(obstacles=(far_box,)))
    result = pipeline.process(frame, timestamp_s=0.0)
    d = result.decision
    assert d.kind is DecisionKind.CLEAR, (d, result.refined.as_dict())
    assert d.yaw == pytest.approx(0.0, abs=1e-6) and d.pitch == pytest.approx(0.0, abs=1e-6)


def test_a_wall_brakes() -> None:
    _, pipeline, frame, _ = _render(Scene(obstacles=(_wall(1.0),)))
    d = pipeline.process(frame, timestamp_s=0.0).decision
    assert d.kind is DecisionKind.BRAKE, d


def test_low_obstacle_ahead_climbs() -> None:
    # A low wall at 1 m whose top is below the camera: the centre and down regions are near, the
    # up region sees far space.
    low = Box.on_ground(1.0 + 0.5, 0.0, (1.0, 30.0, ALT_M + 0.1))
    _, pipeline, frame, _ = _render(Scene(obstacles=(low,)))
    result = pipeline.process(frame, timestamp_s=0.0)
    assert result.decision.pitch > 0.3, (result.decision, result.refined.as_dict())


def test_textureless_view_is_unknown_and_treated_as_near() -> None:
    _, pipeline, frame, _ = _render(Scene(obstacles=(_wall(2.0),)))
    flat = np.full_like(frame, 128)
    result = pipeline.process(flat, timestamp_s=0.0)
    assert np.all(np.isnan(result.refined.depth_m))
    assert result.decision.kind is DecisionKind.BRAKE


def test_reconfigure_changes_the_next_decision_without_rebuilding_the_estimator() -> None:
    scene = Scene(obstacles=(_wall(2.0, east_from_m=-20.0, east_to_m=0.6),))
    cfg, pipeline, frame, _ = _render(scene)
    before = pipeline.process(frame, timestamp_s=0.0).decision
    estimator = pipeline.estimator
    # Widen 'near' so that 2 m is fully near: the decision must change.
    patch = {"controller": {"input_terms": {"near": {"shape": "left_shoulder", "params_m": [2.5, 4.0]},
                                            "far": {"shape": "right_shoulder", "params_m": [2.5, 4.0]}}}}
    changed = pipeline.reconfigure(apply_patch(cfg, patch))
    after = pipeline.process(frame, timestamp_s=0.1).decision
    assert changed == ["controller"]
    assert pipeline.estimator is estimator
    assert (before.kind, round(before.yaw, 3)) != (after.kind, round(after.yaw, 3))


def test_the_pipeline_flies_the_auto_map_options_resolved_on_every_config_it_gets() -> None:
    """The loader resolves planner.block_erode_px "auto" for the backend (the reference SGM: 1 px) and
    the pipeline flies it, on the first config and on every reconfigure; a config that only differs in
    the controller changes only the controller."""
    cfg = parse_config({"stereo": {"backend": "reference", "matcher": "sgm"}})
    pipeline = make_pipeline(cfg, W, H)
    assert pipeline.config.planner.block_erode_px == 1
    cfg = apply_patch(cfg, {"controller": {"defuzzification": "bisector"}})
    assert pipeline.reconfigure(cfg) == ["controller"]
    assert pipeline.config.planner.block_erode_px == 1
    assert pipeline.reconfigure(apply_patch(cfg, {"planner": {"block_erode_px": 0}})) == ["planner"]
    assert pipeline.config.planner.block_erode_px == 0


def test_reconfigure_of_stereo_rebuilds_the_estimator() -> None:
    cfg, pipeline, frame, _ = _render(Scene(obstacles=(_wall(2.0),)))
    old = pipeline.estimator
    changed = pipeline.reconfigure(apply_patch(cfg, {"stereo": {"num_disparities": 96}}))
    assert changed == ["stereo"] and pipeline.estimator is not old
    assert np.all(np.isfinite(pipeline.process(frame, timestamp_s=0.0).refined.depth_m))


def test_wrong_frame_size_is_a_frame_error() -> None:
    from companion.errors import FrameError

    _, pipeline, frame, _ = _render(Scene(obstacles=(_wall(2.0),)))
    with pytest.raises(FrameError, match="differs from the configured"):
        pipeline.process(frame[:, 2:-2], timestamp_s=0.0)
    with pytest.raises(FrameError):
        pipeline.process(frame[:, :-1], timestamp_s=0.0)  # odd side-by-side width


def test_every_frame_carries_its_blocks_for_the_local_map() -> None:
    """The local planner's map input: each ``planner.block_px`` block's nearest disparity (px, NaN
    none), a copy the estimator does not reuse for the next frame; a wall 1 m ahead reads its
    disparity there, and a live change of the block size applies on the next frame."""
    cfg, pipeline, frame, _ = _render(Scene(obstacles=(_wall(1.0),)))
    first = pipeline.process(frame, timestamp_s=0.0)
    b = cfg.planner.block_px
    assert first.near_blocks is not None and first.near_blocks.dtype == np.float32
    assert first.near_blocks.shape == (-(-H // b), -(-W // b))
    assert first.geometry is pipeline.geometry
    wall_d = pipeline.geometry.focal_baseline_px_m / 1.0  # the wall 1 m ahead fills the view
    measured = first.near_blocks[np.isfinite(first.near_blocks)]
    assert measured.size > 0 and np.median(measured) == pytest.approx(wall_d, rel=0.15)
    second = pipeline.process(frame, timestamp_s=0.1)
    assert not np.shares_memory(first.near_blocks, second.near_blocks)
    assert pipeline.reconfigure(apply_patch(cfg, {"planner": {"block_px": 8}})) == ["planner"]
    assert pipeline.process(frame, timestamp_s=0.2).near_blocks.shape == (-(-H // 8), -(-W // 8))


def test_a_gpu_fault_that_loses_the_device_loses_one_frame_then_the_cpu_engine_matches() -> None:
    """A sticky CUDA fault costs the frame it struck; from the next frame on the CPU engine of the same
    census + SGM matches, and every later rebuild (a live stereo change) builds the CPU engine too,
    not the configured backend (the StereoBM here stands in for a configured GPU)."""
    cfg, pipeline, frame, _ = _render(Scene(obstacles=(_wall(2.0),)))
    cfg = apply_patch(cfg, {"stereo": {"backend": "opencv-bm"}})
    faulty = FaultingEstimator(CpuRegionEstimator(cfg, W, H), good_frames=1, device_lost=True)
    pipeline = make_pipeline(cfg, W, H, estimator=faulty)
    assert pipeline.process(frame, timestamp_s=0.0).refined.depth_m.size == 9
    with pytest.raises(BackendError, match="illegal memory access"):
        pipeline.process(frame, timestamp_s=0.1)
    assert pipeline.device_lost is not None and "illegal memory access" in pipeline.device_lost
    assert faulty.closed and pipeline.estimator.name == "cpu-sgm"
    centre = pipeline.process(frame, timestamp_s=0.2).refined.depth_m[REGION_INDEX["center"]]
    assert centre == pytest.approx(2.0, rel=0.05)
    assert pipeline.reconfigure(apply_patch(cfg, {"stereo": {"num_disparities": 96}})) == ["stereo"]
    assert pipeline.estimator.name == "cpu-sgm"
    assert pipeline.process(frame, timestamp_s=0.3).refined.depth_m[REGION_INDEX["center"]] == pytest.approx(2.0, rel=0.05)


def test_a_gpu_error_that_leaves_the_device_usable_loses_only_its_frame() -> None:
    cfg, _, frame, _ = _render(Scene(obstacles=(_wall(2.0),)))
    faulty = FaultingEstimator(CpuRegionEstimator(cfg, W, H), good_frames=0, device_lost=False)
    pipeline = make_pipeline(cfg, W, H, estimator=faulty)
    with pytest.raises(BackendError):
        pipeline.process(frame, timestamp_s=0.0)
    assert pipeline.estimator is faulty and pipeline.device_lost is None and not faulty.closed
