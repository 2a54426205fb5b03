"""The obstacle memory and the out-of-view guard (companion.core.memory)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import CompanionConfig, parse_config
from companion.config.core import CommandConfig, MemoryConfig
from companion.core.command import setpoint_for
from companion.core.geometry import StereoGeometry
from companion.core.memory import (
    CLEAR_WINDOW_BLOCKS,
    LONGEST_COUNTED_FRAME_S,
    BlockMax,
    FarView,
    Gap,
    NearCells,
    ObstacleMemory,
    ViewLimits,
    apply_guard,
    block_max,
    camera_points_to_ned,
    view_limits,
    window_max,
)
from companion.core.pose import Pose
from companion.core.types import ZERO_SETPOINT, Decision, DecisionKind

GEOM = StereoGeometry(width_px=128, height_px=64, focal_px=100.0, cx_px=63.5, cy_px=31.5, baseline_m=0.12)
CFG = MemoryConfig(grid_rows=2, grid_cols=4, block_px=4, robust_percentile_pct=0.0, min_valid_fraction=0.1)
VIEW = ViewLimits(left_rad=math.radians(32.0), right_rad=math.radians(44.0), min_range_m=0.19)


def test_view_limits_leave_out_the_columns_block_matching_cannot_search() -> None:
    v = view_limits(GEOM, 16)
    assert v.left_rad == pytest.approx(math.atan((63.5 - 15) / 100.0))  # 15 columns never matched
    assert v.right_rad == pytest.approx(math.atan(63.5 / 100.0))
    assert v.min_range_m == pytest.approx(100.0 * 0.12 / 15)
    assert view_limits(GEOM, 80).left_rad == 0.0  # nothing matched left of the principal point


def test_block_max_is_the_nan_aware_maximum_of_each_block_partial_edges_included() -> None:
    rng = np.random.default_rng(0)
    d = rng.uniform(1, 60, (10, 13)).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = np.nan
    d[0:4, 0:4] = np.nan  # a block with no valid pixel
    got = block_max(d, 4)
    assert got.shape == (3, 4)
    for r in range(3):
        for c in range(4):
            blk = d[4 * r : 4 * r + 4, 4 * c : 4 * c + 4]
            want = np.nanmax(blk) if np.any(np.isfinite(blk)) else np.nan
            assert np.array_equal(got[r, c], np.float32(want), equal_nan=True)
    assert np.array_equal(block_max(d, 1), d, equal_nan=True)


def test_block_max_reuses_its_buffers_and_checks_the_shape() -> None:
    bm = BlockMax((8, 8), 4)
    a = bm(np.ones((8, 8), np.float32))
    b = bm(np.full((8, 8), 2.0, np.float32))
    assert a is b and float(b[0, 0]) == 2.0
    with pytest.raises(ValueError, match="must be"):
        bm(np.ones((8, 9), np.float32))


def test_eroded_blocks_drop_a_lone_spike_and_a_smeared_edge_but_keep_a_wide_surface() -> None:
    """``erode_px`` = 1: a pixel counts only where its row neighbours are as near (NaN the smallest),
    so a one-pixel spike and a one-pixel fringe smeared into the next block give no block their
    depth; a 6 px post still does, and a 2 px one, narrower than the erosion's 3 px, is lost."""
    d = np.full((4, 24), 5.0, np.float32)
    d[:, 2] = 30.0  # a spike in block 0 (columns 0-3)
    d[:, 12:18] = 20.0  # a post over blocks 3 and 4 (columns 12-17)
    d[:, 11] = 20.0  # its fringe, smeared into block 2
    d[1, 21] = np.nan  # an invalid pixel: its row neighbours become invalid; the block keeps its other rows
    np.testing.assert_array_equal(block_max(d, 4)[0], [30.0, 5.0, 20.0, 20.0, 20.0, 5.0])
    np.testing.assert_array_equal(block_max(d, 4, erode_px=1)[0], [5.0, 5.0, 5.0, 20.0, 20.0, 5.0])
    d[:, 11:18] = 5.0
    d[:, 12:14] = 20.0  # a 2 px post
    np.testing.assert_array_equal(block_max(d, 4, erode_px=1)[0], [5.0, 5.0, 5.0, 5.0, 5.0, 5.0])
    bm = BlockMax((4, 24), 4, erode_px=1)
    assert bm(d) is bm(d) and bm.erode_px == 1
    with pytest.raises(ValueError, match="erode_px"):
        BlockMax((4, 24), 4, erode_px=-1)


def test_the_memory_gets_eroded_blocks_from_the_cpu_estimator_when_configured() -> None:
    """``memory.block_erode_px`` reaches the estimator: its ``near_blocks`` are those of the eroded
    disparity, and a reload that changes only the memory section changes them on the next frame."""
    from companion.backends import make_estimator
    from companion.core.pipeline import Pipeline

    cfg = parse_config({"stereo": {"backend": "reference"}})
    w, h = 96, 48
    rng = np.random.default_rng(5)
    left = rng.integers(0, 256, (h, w), dtype=np.uint8)
    right = np.roll(left, -6, axis=1)
    frame = np.ascontiguousarray(np.hstack([left, right]))
    seen: list[tuple[np.ndarray, np.ndarray, int]] = []
    pipe = Pipeline(cfg, w, h, make_estimator=make_estimator)
    inner = pipe.estimator

    class _Spy:
        geometry, layout, name = inner.geometry, inner.layout, inner.name

        def estimate(self, frame, want_disparity=False, near_block_px=0, near_erode_px=0):  # type: ignore[no-untyped-def]
            res = inner.estimate(frame, want_disparity=True, near_block_px=near_block_px, near_erode_px=near_erode_px)
            seen.append((res.disparity, res.near_blocks.copy(), near_erode_px))
            return res

    pipe.estimator = _Spy()  # type: ignore[assignment]
    pipe.process(frame, 0.0)
    disp, blocks, k = seen[-1]
    # "auto" is resolved where the config loads: the reference's semi-global map erodes by one pixel.
    assert k == cfg.memory.block_erode_px == 1 and np.array_equal(blocks, block_max(disp, 4, 1), equal_nan=True)
    pipe.reconfigure(parse_config({"stereo": {"backend": "reference"}, "memory": {"block_erode_px": 2}}))
    pipe.process(frame, 0.1)
    disp, blocks, k = seen[-1]
    assert k == 2 and np.array_equal(blocks, block_max(disp, 4, 2), equal_nan=True)


def blocks_with(disparity_px: float | None, rows: slice = slice(6, 10), cols: slice = slice(26, 30)) -> np.ndarray:
    """A 16 x 32 block image (128 x 64 eye at 4 px): far background (1 px) and one near patch."""
    b = np.full((16, 32), 1.0, np.float32)
    if disparity_px is not None:
        b[rows, cols] = disparity_px
    return b


def test_near_cells_need_confirming_frames_and_put_the_point_on_the_ray_it_was_seen_along() -> None:
    cells = NearCells(CFG, GEOM, (16, 32))
    d = GEOM.focal_baseline_px_m / 12.0  # 12 px: 1.0 m
    assert cells.points(blocks_with(12.0)).shape == (0, 3)  # not yet confirmed (3 frames)
    assert cells.points(blocks_with(12.0)).shape == (0, 3)
    pts = cells.points(blocks_with(12.0))
    assert len(pts) >= 1
    z = pts[:, 2]
    assert z == pytest.approx(np.full(len(z), d))
    # The patch spans blocks 26-29 (pixels 104-119): the point is on one of those blocks' rays.
    x_px = pts[:, 0] / z * GEOM.focal_px + GEOM.cx_px
    assert np.all((x_px >= 104) & (x_px < 120))
    assert np.all(np.abs(x_px - ((np.round((x_px + 0.5) / 4 - 0.5) + 0.5) * 4 - 0.5)) < 1e-9)  # a block centre


def test_a_false_match_lasting_one_frame_is_not_remembered() -> None:
    cells = NearCells(CFG, GEOM, (16, 32))
    for b in (blocks_with(None), blocks_with(12.0), blocks_with(None), blocks_with(None)):
        assert cells.points(b).shape == (0, 3)


def test_only_cells_nearer_than_max_depth_and_valid_enough_give_points() -> None:
    cells = NearCells(CFG.model_copy(update={"max_depth_m": 0.5, "map_depth_m": 0.5}), GEOM, (16, 32))
    for _ in range(3):
        pts = cells.points(blocks_with(12.0))  # 1.0 m: beyond 0.5 m
    assert pts.shape == (0, 3)
    # The map's depth (for the detour layer) reaches farther than the guard's.
    mapping = NearCells(CFG.model_copy(update={"max_depth_m": 0.5, "map_depth_m": 2.0}), GEOM, (16, 32))
    for _ in range(3):
        pts = mapping.points(blocks_with(12.0))
    assert pts.shape[0] > 0 and np.all(pts[:, 2] > 0.5)
    sparse = NearCells(CFG.model_copy(update={"min_valid_fraction": 0.5}), GEOM, (16, 32))
    b = np.full((16, 32), np.nan, np.float32)
    b[7, 27] = 40.0  # one valid block of 64 in its cell
    for _ in range(3):
        pts = sparse.points(b)
    assert pts.shape == (0, 3)


def test_camera_points_to_ned_follows_the_pose() -> None:
    pose = Pose((1.0, 2.0, -1.5), math.pi / 2)  # facing east
    p = camera_points_to_ned(np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]]), pose)
    assert p[0] == pytest.approx([1.0, 4.0, -1.5])  # 2 m ahead = 2 m east
    assert p[1] == pytest.approx([0.0, 2.0, -1.5])  # 1 m right of east = 1 m south


def test_memory_refreshes_a_cube_seen_again_forgets_after_duration_and_keeps_at_most_max_points() -> None:
    mem = ObstacleMemory(max_points=3)
    mem.add(np.array([[1.0, 0.0, -1.5]]), 0.0, 10.0)
    mem.add(np.array([[1.01, 0.01, -1.49]]), 5.0, 10.0)  # the same 5 cm cube: refreshed, not added
    assert len(mem) == 1
    mem.add(np.array([[3.0, 0.0, -1.5], [np.nan, 0.0, 0.0]]), 14.0, 10.0)  # NaN row dropped
    assert len(mem) == 2  # the first, refreshed at 5 s, is 9 s old
    mem.add(np.empty((0, 3)), 15.5, 10.0)
    assert len(mem) == 1  # now 10.5 s old: forgotten
    mem.add(np.array([[5.0, 0, 0], [6.0, 0, 0], [7.0, 0, 0]]), 16.0, 10.0)
    assert len(mem) == 3
    mem.reset()
    assert len(mem) == 0


def guard_cfg(**kw: float) -> MemoryConfig:
    return MemoryConfig().model_copy(update=kw)


@pytest.mark.parametrize(
    ("point", "yaw", "expect"),
    [
        ((0.0, -0.4, -1.5), 0.0, (0.4, 0.0, -1.0)),  # 0.4 m left, out of view: guards
        ((0.3, -0.3, -1.5), 0.0, (math.hypot(0.3, 0.3), math.sqrt(0.5), -math.sqrt(0.5))),  # 45° left: unmatched
        ((0.3, 0.3, -1.5), 0.0, (math.hypot(0.3, 0.3), math.sqrt(0.5), math.sqrt(0.5))),  # 45° right: past 44°
        ((0.4, 0.3, -1.5), 0.0, None),  # 37° right: matched, the live view's
        ((0.4, 0.0, -1.5), math.pi / 2, (0.4, 0.0, -1.0)),  # facing east, 0.4 m north is on the left
        ((-0.4, 0.0, -1.5), 0.0, (0.4, -1.0, 0.0)),  # behind
        ((0.4, 0.1, -1.5), 0.0, None),  # ahead, in view and beyond the rig's nearest depth: the live view's
        ((0.15, 0.0, -1.5), 0.0, (0.15, 1.0, 0.0)),  # ahead but nearer than the rig sees (0.19 m): guards
        ((0.0, -0.7, -1.5), 0.0, None),  # beyond guard_distance_m
        ((0.0, -0.4, -0.5), 0.0, None),  # 1 m above: outside the height band
    ],
)
def test_guard_picks_out_of_view_points_near_the_vehicle(point, yaw, expect) -> None:
    mem = ObstacleMemory()
    mem.add(np.array([point]), 0.0, 30.0)
    g = mem.guard(np.array([0.0, 0.0, -1.5]), yaw, 1.0, guard_cfg(), VIEW)
    if expect is None:
        assert g is None
    else:
        assert g is not None and g.shape == (1, 4)
        assert g[0, :3] == pytest.approx(expect, abs=1e-9)
        assert g[0, 3] == 0.0  # added without trust kept: it stops motion toward it, never pushes


def test_only_trusted_points_push_untrusted_ones_only_stop_the_motion_toward_them() -> None:
    """A point seen for a moment from one place may be a false match in the air; its push would move
    the vehicle sideways into what the camera does not see (kinematic forest-2 with StereoBM: a
    false point beside the vehicle pushed it into a pillar out of view). A point seen from two places
    0.6 m apart (more than memory.push_baseline_m) pushes."""
    cfg = guard_cfg()
    vehicle = np.array([0.0, 0.0, -1.5])
    left_point = np.array([[0.0, -0.4, -1.5]])
    once = ObstacleMemory()
    once.add(left_point, 0.0, 30.0, viewpoint_ned_m=np.array([-1.5, 0.0, -1.5]), cfg=cfg)
    g = once.guard(vehicle, 0.0, 1.0, cfg, VIEW)
    assert g is not None and g.shape == (1, 4) and g[0, 3] == 0.0
    assert apply_guard(0.0, 0.0, g, cfg) == (0.0, 0.0)  # no push
    assert apply_guard(0.0, -0.3, g, cfg) == pytest.approx((0.0, 0.0))  # but no sliding into it
    twice = ObstacleMemory()
    twice.add(left_point, 0.0, 30.0, viewpoint_ned_m=np.array([-1.5, 0.0, -1.5]), cfg=cfg)
    twice.add(left_point, 0.5, 30.0, viewpoint_ned_m=np.array([-0.9, 0.0, -1.5]), cfg=cfg)
    g = twice.guard(vehicle, 0.0, 1.0, cfg, VIEW)
    assert g is not None and g.shape == (1, 4) and g[0, 3] == 1.0
    f, r = apply_guard(0.0, 0.0, g, cfg)
    assert (f, r) == pytest.approx((0.0, cfg.guard_gain_per_s * (cfg.guard_distance_m - 0.4)))


def test_a_point_that_only_persists_from_one_place_is_trusted_but_never_pushes() -> None:
    """Persistence is what a false match that moves with the vehicle has too; only a point seen from
    two places moves the vehicle sideways (PX4 SITL r5 office-3: StereoBM's alias on a fence, trusted
    by persistence, pushed the vehicle into the right wall). It still stops the motion toward it."""
    cfg = guard_cfg()
    vehicle = np.array([0.0, 0.0, -1.5])
    left_point = np.array([[0.0, -0.4, -1.5]])
    mem = ObstacleMemory()
    for k in range(10):
        mem.add(left_point, 0.1 * k, 30.0, viewpoint_ned_m=np.array([-1.0, 0.0, -1.5]), cfg=cfg)
    assert mem.trusted(left_point, cfg)[0]  # for the map and the path ahead
    assert not mem.may_push(left_point, cfg)[0]
    g = mem.guard(vehicle, 0.0, 1.0, cfg, VIEW)
    assert g is not None and g.shape == (1, 4) and g[0, 3] == 0.0
    assert apply_guard(0.0, 0.0, g, cfg) == (0.0, 0.0)
    assert apply_guard(0.0, -0.3, g, cfg) == pytest.approx((0.0, 0.0))


def test_a_false_match_that_follows_the_vehicle_never_pushes_where_a_real_point_does() -> None:
    """A fence's alias (or a smudge on the lens) sits at the same place in the view wherever the
    vehicle goes: seen from two places ``push_baseline_m`` (0.5 m) apart it lands 0.5 m apart, never
    in one 0.3 m cube, however long the vehicle wanders; it persists, so it is trusted, but it never
    pushes. A real point lands in its cube from everywhere."""
    cfg = guard_cfg()
    mem = ObstacleMemory()
    real = np.array([[2.0, -0.6, -1.5]])
    rng = np.random.default_rng(3)
    east = 0.0
    for k in range(300):  # 30 s, wandering sideways over 1 m at up to 0.5 m/s
        east = float(np.clip(east + rng.uniform(-0.05, 0.05), -0.5, 0.5))
        here = np.array([1.0, east, -1.5])
        phantom = here + [0.25, -0.35, 0.0]  # 0.43 m ahead-left, wherever the vehicle is
        mem.add(np.vstack([phantom, real]), 0.1 * k, 30.0, viewpoint_ned_m=here, cfg=cfg)
    pts, _ = mem.points(30.0, cfg)
    phantoms = pts[np.abs(pts[:, 0] - 1.25) < 1e-6]
    assert len(phantoms) > 5 and mem.trusted(phantoms, cfg).any()
    assert not mem.may_push(phantoms, cfg).any()
    assert mem.may_push(real, cfg)[0]


def test_guard_keeps_the_nearest_trusted_point_of_a_sector_beside_a_nearer_untrusted_one() -> None:
    cfg = guard_cfg()
    mem = ObstacleMemory()
    real = np.array([[0.0, -0.5, -1.5]])
    for t, north in ((0.0, -1.5), (0.5, -0.9)):
        mem.add(real, t, 30.0, viewpoint_ned_m=np.array([north, 0.0, -1.5]), cfg=cfg)
    mem.add(np.array([[0.0, -0.2, -1.5]]), 0.9, 30.0, viewpoint_ned_m=np.array([-0.5, 0.0, -1.5]), cfg=cfg)
    g = mem.guard(np.array([0.0, 0.0, -1.5]), 0.0, 1.0, cfg, VIEW)
    assert g is not None
    assert sorted((round(float(d), 6), float(push)) for d, _, _, push in g) == [(0.2, 0.0), (0.5, 1.0)]


def test_guard_forgets_old_points_and_keeps_the_nearest_per_sector() -> None:
    mem = ObstacleMemory()
    mem.add(np.array([[0.0, -0.5, -1.5], [0.0, -0.3, -1.5], [0.0, 0.45, -1.5]]), 0.0, 30.0)
    g = mem.guard(np.zeros(3) + [0, 0, -1.5], 0.0, 1.0, guard_cfg(), VIEW)
    assert sorted(np.round(g[:, 0], 6).tolist()) == [0.3, 0.45]  # left: the nearer of two; right
    assert mem.guard(np.array([0.0, 0.0, -1.5]), 0.0, 40.0, guard_cfg(), VIEW) is None
    assert mem.guard(np.array([np.nan, 0.0, -1.5]), 0.0, 1.0, guard_cfg(), VIEW) is None


def test_apply_guard_removes_motion_toward_the_point_and_pushes_away_capped() -> None:
    cfg = guard_cfg(guard_distance_m=0.6, guard_gain_per_s=1.5, max_guard_speed_m_s=0.5, keep_out_m=0.35)
    left = np.array([[0.4, 0.0, -1.0]])  # 0.4 m to the left
    f, r = apply_guard(0.0, -0.3, left, cfg)  # sliding left, into it
    assert (f, r) == pytest.approx((0.0, 1.5 * 0.2))  # the leftward 0.3 removed, pushed right 0.3
    f, r = apply_guard(0.7, -0.3, left, cfg)  # forward and left: it lies 0.4·0.92 = 0.37 m off the path
    assert (f, r) == pytest.approx((0.7, -0.3 + 0.3))  # beside the path: only the push
    ahead_left = np.array([[0.4, math.sqrt(0.5), -math.sqrt(0.5)]])  # 45° ahead-left, 0.28 m off the path
    f, r = apply_guard(0.7, 0.0, ahead_left, cfg)
    toward = 0.7 * math.sqrt(0.5)
    assert (f, r) == pytest.approx((0.7 - toward * math.sqrt(0.5) - 0.3 * math.sqrt(0.5), toward * math.sqrt(0.5) + 0.3 * math.sqrt(0.5)))
    f, r = apply_guard(0.0, 0.0, np.array([[0.1, 0.0, -1.0]]), cfg)
    assert (f, r) == pytest.approx((0.0, 0.5))  # 0.75 capped at 0.5
    f, r = apply_guard(0.0, 0.2, left, cfg)
    assert r == pytest.approx(0.2 + 0.3)  # already moving away: kept, plus the push
    assert apply_guard(0.7, -0.3, None, cfg) == (0.7, -0.3)
    only_stop = cfg.model_copy(update={"guard_gain_per_s": 0.0})
    assert apply_guard(0.0, -0.3, left, only_stop) == pytest.approx((0.0, 0.0))


def test_a_damped_push_drops_by_the_speed_already_moving_away_never_below_zero() -> None:
    cfg = guard_cfg(guard_distance_m=0.6, guard_gain_per_s=3.0, max_guard_speed_m_s=0.8, guard_damping_fraction=1.0)
    left = np.array([[0.4, 0.0, -1.0]])  # 0.4 m to the left: a push of 3·0.2 = 0.6 m/s to the right
    assert apply_guard(0.0, 0.0, left, cfg, (0.0, 0.0)) == pytest.approx((0.0, 0.6))
    assert apply_guard(0.0, 0.0, left, cfg, (0.0, 0.25)) == pytest.approx((0.0, 0.35))  # moving away at 0.25
    assert apply_guard(0.0, 0.0, left, cfg, (0.0, 0.9)) == pytest.approx((0.0, 0.0))  # away faster: no push
    assert apply_guard(0.0, 0.0, left, cfg, (0.5, 0.0)) == pytest.approx((0.0, 0.6))  # along it: undamped
    assert apply_guard(0.0, 0.0, left, cfg) == pytest.approx((0.0, 0.6))  # velocity unknown: undamped
    # Between a wall 0.4 m left and a box 0.4 m right, moving right at 0.3 m/s: the wall's push drops
    # to 0.3, the box's stays 0.6 and its lean adds 0.5·0.3, so the command brakes the swing at 0.45
    # m/s where undamped only the lean's 0.15 does.
    both = np.array([[0.4, 0.0, -1.0], [0.4, 0.0, 1.0]])
    assert apply_guard(0.0, 0.0, both, cfg, (0.0, 0.3)) == pytest.approx((0.0, -0.45))
    undamped = cfg.model_copy(update={"guard_damping_fraction": 0.0})
    assert apply_guard(0.0, 0.0, both, undamped, (0.0, 0.3)) == pytest.approx((0.0, -0.15))


def test_apply_guard_leans_against_a_motion_that_still_closes_on_a_point_on_the_actual_path() -> None:
    """PX4 follows a setpoint ~0.85 s late: a command already turned away still leaves the vehicle
    closing on what it was flying at; the command then moves away at counter_velocity_fraction times
    the closing speed, capped at max_guard_speed_m_s."""
    cfg = guard_cfg(
        guard_distance_m=0.6, guard_gain_per_s=0.0, max_guard_speed_m_s=0.5, keep_out_m=0.35, counter_velocity_fraction=1.0
    )
    left = np.array([[0.4, 0.0, -1.0]])  # 0.4 m to the left
    # Commanded straight on (the point is beside that path), but still sliding left at 0.3 m/s.
    assert apply_guard(0.7, 0.0, left, cfg, (0.0, -0.3)) == pytest.approx((0.7, 0.3))
    # Moving mostly forward: 0.4 m to the left lies off the actual path, nothing to lean against.
    assert apply_guard(0.7, 0.0, left, cfg, (0.7, -0.1)) == pytest.approx((0.7, 0.0))
    # Already moving away, or no velocity known: only the commanded path counts.
    assert apply_guard(0.7, 0.0, left, cfg, (0.0, 0.3)) == pytest.approx((0.7, 0.0))
    assert apply_guard(0.7, 0.0, left, cfg, None) == pytest.approx((0.7, 0.0))
    assert apply_guard(0.7, 0.0, left, cfg, (math.nan, -0.3)) == pytest.approx((0.7, 0.0))
    # A command already moving away faster than the counter is kept; a fast closing speed is capped,
    # and so are the lean and the push together.
    assert apply_guard(0.0, 0.45, left, cfg, (0.0, -0.3)) == pytest.approx((0.0, 0.45))
    assert apply_guard(0.0, 0.0, left, cfg, (0.0, -0.9)) == pytest.approx((0.0, 0.5))
    pushing = cfg.model_copy(update={"guard_gain_per_s": 1.5})  # push 0.3 m/s at 0.4 m
    assert apply_guard(0.7, 0.0, left, pushing, (0.0, -0.3)) == pytest.approx((0.7, 0.5))
    half = cfg.model_copy(update={"counter_velocity_fraction": 0.5})
    off = cfg.model_copy(update={"counter_velocity_fraction": 0.0})
    # A point 45° ahead-left, 0.5 m: just beside the commanded path (0.354 m off it), straight on the
    # path actually flown. The command's motion toward it is removed, then the lean added.
    ahead_left = np.array([[0.5, math.sqrt(0.5), -math.sqrt(0.5)]])
    assert apply_guard(0.7, 0.0, ahead_left, cfg) == pytest.approx((0.7, 0.0))
    assert apply_guard(0.7, 0.0, ahead_left, off, (0.3, -0.3)) == pytest.approx((0.35, 0.35))
    lean = 0.5 * 0.3 * math.sqrt(2.0)
    assert apply_guard(0.7, 0.0, ahead_left, half, (0.3, -0.3)) == pytest.approx(
        (0.35 - lean * math.sqrt(0.5), 0.35 + lean * math.sqrt(0.5))
    )
    assert apply_guard(0.0, -0.2, left, half, (0.0, -0.3)) == pytest.approx((0.0, 0.15))
    assert apply_guard(0.0, -0.2, left, off, (0.0, -0.3)) == pytest.approx((0.0, 0.0))


def test_setpoint_for_hands_the_actual_velocity_to_the_guard() -> None:
    cmd = CompanionConfig().command
    cfg = guard_cfg(guard_gain_per_s=0.0, counter_velocity_fraction=1.0)
    left = np.array([[0.4, 0.0, -1.0]])
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    sp = setpoint_for(clear, 0.0, cmd, guard_m=left, guard_cfg=cfg, velocity_body_m_s=(0.0, -0.3))
    assert sp.right_m_s == pytest.approx(0.3) and sp.forward_m_s == pytest.approx(cmd.cruise_speed_m_s)
    assert setpoint_for(clear, 0.0, cmd, guard_m=left, guard_cfg=cfg).right_m_s == 0.0


def test_setpoint_for_guards_every_fresh_decision_but_never_a_stale_one() -> None:
    cmd = CompanionConfig().command
    cfg = guard_cfg()
    left = np.array([[0.3, 0.0, -1.0]])
    brake = Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "wall")
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    sp = setpoint_for(brake, 0.0, cmd, guard_m=left, guard_cfg=cfg)
    assert sp.right_m_s == pytest.approx(0.45) and sp.forward_m_s == 0.0
    sp = setpoint_for(clear, 0.0, cmd, guard_m=left, guard_cfg=cfg)
    assert sp.forward_m_s == pytest.approx(cmd.cruise_speed_m_s) and sp.right_m_s == pytest.approx(0.45)
    assert setpoint_for(clear, cmd.stale_frame_timeout_s + 0.1, cmd, guard_m=left, guard_cfg=cfg) == ZERO_SETPOINT
    assert setpoint_for(None, 0.0, cmd, guard_m=left, guard_cfg=cfg) == ZERO_SETPOINT


def test_memory_config_is_validated() -> None:
    from companion.errors import ConfigError

    with pytest.raises(ConfigError, match="confirm_frames"):
        parse_config({"memory": {"confirm_frames": 2}})
    with pytest.raises(ConfigError, match="guard_distance_m"):
        parse_config({"memory": {"guard_distance_m": 0.0}})
    with pytest.raises(ConfigError, match="envelope.memory_may_be_off"):  # off only where the envelope allows
        parse_config({"memory": {"duration_s": 0.0}})
    allowed = {"memory": {"duration_s": 0.0}, "envelope": {"memory_may_be_off": True}}
    assert parse_config(allowed).memory.duration_s == 0.0


def test_sides_near_tells_which_side_has_a_remembered_point_within_hold_clear_m() -> None:
    mem = ObstacleMemory()
    cfg = guard_cfg(hold_clear_m=1.0)
    here = np.array([0.0, 0.0, -1.5])
    assert mem.sides_near(here, 0.0, 1.0, cfg) == (False, False)
    mem.add(np.array([[-0.3, -0.6, -1.5]]), 0.0, 30.0)  # left and 0.3 m behind, 0.67 m
    assert mem.sides_near(here, 0.0, 1.0, cfg) == (True, False)
    assert mem.sides_near(here, math.pi, 1.0, cfg) == (False, True)  # facing south it is on the right
    # Farther behind than keep_out_m: turning or sliding toward it does not close on it.
    assert mem.sides_near(here, 0.0, 1.0, cfg.model_copy(update={"keep_out_m": 0.25})) == (False, False)
    assert mem.sides_near(here, 0.0, 1.0, cfg.model_copy(update={"hold_clear_m": 0.5})) == (False, False)
    assert mem.sides_near(here, 0.0, 40.0, cfg) == (False, False)  # forgotten
    assert mem.sides_near(np.array([np.nan, 0, 0]), 0.0, 1.0, cfg) is None


def test_course_hold_neither_turns_nor_slides_toward_a_remembered_side() -> None:
    # No taper of the sideways step while the aim lies off the nose: that is another rule's test.
    cmd = CompanionConfig().command.model_copy(
        update={"hold_resume_delay_s": 0.0, "line_hold_lateral_max_aim_error_deg": 180.0}
    )
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    kw = {"heading_error_rad": -0.3, "line_offset_m": -0.5, "clear_for_s": 5.0}  # the course lies left
    free = setpoint_for(clear, 0.0, cmd, **kw)
    assert free.yaw_rate_deg_s < 0.0 and free.right_m_s < 0.0
    blocked = setpoint_for(clear, 0.0, cmd, remembered_sides=(True, False), **kw)
    assert blocked.yaw_rate_deg_s == 0.0 and blocked.right_m_s == 0.0
    assert setpoint_for(clear, 0.0, cmd, remembered_sides=(False, True), **kw) == free


def test_clear_below_looks_for_remembered_points_under_the_way_down() -> None:
    """Climbed over a 1.3 m cabinet to 2.0 m (engaged at 1.5 m): its top, remembered, lies below
    the vehicle until it has flown keep_out_m (its radius and a margin) past it."""
    mem = ObstacleMemory()
    cfg = MemoryConfig(keep_out_m=0.35, height_band_m=0.4)
    down_to = -1.5
    assert mem.clear_below(np.array([0.0, 0.0, -2.0]), 0.0, cfg, down_to) is True  # empty memory
    # The cabinet's top, 1.3 m high, seen once from 4 m: far and untrusted, it counts all the same.
    mem.add(np.array([[0.0, 0.0, -1.3]]), 0.0, 30.0, ranges_m=np.array([4.0]))
    assert mem.clear_below(np.array([0.1, 0.0, -2.0]), 1.0, cfg, down_to) is False  # over it
    assert mem.clear_below(np.array([0.3, 0.0, -2.0]), 1.0, cfg, down_to) is False  # still over its edge
    assert mem.clear_below(np.array([0.5, 0.0, -2.0]), 1.0, cfg, down_to) is True  # flown past it
    # Beside it (0.9 m: a wall beside the vehicle, not under it): the guard's business, not the descent's.
    assert mem.clear_below(np.array([0.0, -0.9, -2.0]), 1.0, cfg, down_to) is True
    # More than the band below the altitude to descend to: the descent never comes that close.
    assert mem.clear_below(np.array([0.1, 0.0, -2.0]), 1.0, cfg, -1.8) is True
    # Above the vehicle: not on the way down.
    assert mem.clear_below(np.array([0.1, 0.0, -0.5]), 1.0, cfg, 0.0) is True
    assert mem.clear_below(np.array([0.1, 0.0, -2.0]), 40.0, cfg, down_to) is True  # forgotten
    assert mem.clear_below(np.array([np.nan, 0.0, -2.0]), 1.0, cfg, down_to) is None
    assert mem.clear_below(np.array([0.5, 0.0, -2.0]), 1.0, cfg, math.nan) is None


def test_the_descent_back_to_the_engagement_altitude_waits_only_for_what_is_remembered_below() -> None:
    """An office never gives 1.5 m of straight, clear flight; a descent over nothing remembered need
    not wait for it, and the down region must still read clear. (A climb back up waits for nothing
    but what was overhead: test_sim_goal_seeking.)"""
    cmd = CommandConfig(altitude_hold_gain_per_s=0.5, hold_resume_delay_s=1.5, hold_resume_distance_m=1.5,
                        hold_clear_depth_m=2.25)
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    kw = {"altitude_error_m": -0.5, "clear_for_s": 0.2, "clear_for_m": 0.1}  # 0.5 m above, just cleared
    assert setpoint_for(clear, 0.1, cmd, **kw).down_m_s == 0.0
    assert setpoint_for(clear, 0.1, cmd, below_clear=False, **kw).down_m_s == 0.0
    assert setpoint_for(clear, 0.1, cmd, below_clear=True, **kw).down_m_s == pytest.approx(0.25)
    assert setpoint_for(clear, 0.1, cmd, below_clear=True, region_depths_m=np.full(9, 1.0), **kw).down_m_s == 0.0
    up = {**kw, "altitude_error_m": 0.5}  # below the engagement altitude: the climb back does not wait
    assert setpoint_for(clear, 0.1, cmd, below_clear=True, **up).down_m_s == pytest.approx(-0.25)
    assert setpoint_for(clear, 0.1, cmd, since_up_near_m=0.5, **up).down_m_s == 0.0  # unless under something

def test_steering_round_something_the_vehicle_still_returns_to_its_altitude() -> None:
    """With command.altitude_hold_on_avoid, on an AVOID decision (an office's walls: the CLEAR wait
    never ends) the altitude hold acts where it does not fight the controller: a climb back while
    the decision does not descend, a descent over nothing remembered below while it does not climb;
    the vertical regions and what was overhead still stop it. A BRAKE's holds are its own."""
    off = CommandConfig(altitude_hold_gain_per_s=0.5, hold_resume_delay_s=1.5, hold_resume_distance_m=1.5,
                        hold_clear_depth_m=2.25)
    cmd = off.model_copy(update={"altitude_hold_on_avoid": True})
    level = Decision(DecisionKind.AVOID, 0.3, 0.0, 0.5, "avoid")
    above = {"altitude_error_m": -0.5}  # 0.5 m above the engagement altitude
    below = {"altitude_error_m": 0.5}
    # Off by default: an AVOID decision's vertical speed is the controller's alone.
    assert setpoint_for(level, 0.1, off, below_clear=True, **above).down_m_s == 0.0
    assert setpoint_for(level, 0.1, off, **below).down_m_s == 0.0
    assert setpoint_for(level, 0.1, cmd, below_clear=True, **above).down_m_s == pytest.approx(0.25)
    assert setpoint_for(level, 0.1, cmd, below_clear=False, **above).down_m_s == 0.0
    assert setpoint_for(level, 0.1, cmd, **above).down_m_s == 0.0  # below unknown: no descent
    assert setpoint_for(level, 0.1, cmd, below_clear=True, region_depths_m=np.full(9, 1.0), **above).down_m_s == 0.0
    assert setpoint_for(level, 0.1, cmd, **below).down_m_s == pytest.approx(-0.25)
    assert setpoint_for(level, 0.1, cmd, since_up_near_m=0.5, **below).down_m_s == 0.0
    own = 0.5 * cmd.max_vertical_speed_m_s  # the controller's half-rate climb or descent, m/s
    climbing = Decision(DecisionKind.AVOID, 0.0, 0.5, 0.5, "over")
    assert setpoint_for(climbing, 0.1, cmd, below_clear=True, **above).down_m_s == pytest.approx(-own)
    assert setpoint_for(climbing, 0.1, cmd, **below).down_m_s == pytest.approx(-own - 0.5 * 0.25)
    descending = Decision(DecisionKind.AVOID, 0.0, -0.5, 0.5, "under")
    assert setpoint_for(descending, 0.1, cmd, **below).down_m_s == pytest.approx(own)
    assert setpoint_for(descending, 0.1, cmd, below_clear=True, **above).down_m_s == pytest.approx(own + 0.5 * 0.25)
    brake = Decision(DecisionKind.BRAKE, 0.0, 0.0, 0.0, "brake")
    assert setpoint_for(brake, 0.1, cmd, below_clear=True, **above).down_m_s == 0.0


def test_a_gap_is_the_middle_and_width_between_the_nearest_points_left_and_right() -> None:
    """A 1.2 m doorway 1 m ahead whose middle lies 0.3 m right: its jambs bound the gap, not the wall
    beyond them; a wide gap, one side only, points beyond the lookahead or centering off: no gap."""
    from companion.core.memory import find_gap

    cfg = MemoryConfig(gap_centering_gain_per_s=1.0)  # the default, pinned
    right = np.concatenate([np.linspace(-2.0, -0.3, 18), np.linspace(0.9, 2.5, 17)])  # wall, door -0.3..0.9
    fwd = np.full_like(right, 1.0)
    gap = find_gap(fwd, right, cfg)
    assert gap is not None
    assert gap.offset_m == pytest.approx(0.3) and gap.width_m == pytest.approx(1.2)
    assert find_gap(fwd[right < 0], right[right < 0], cfg) is None  # one side only
    wide = cfg.model_copy(update={"gap_max_width_m": 1.1})
    assert find_gap(fwd, right, wide) is None
    assert find_gap(fwd + cfg.gap_lookahead_m, right, cfg) is None  # beyond the lookahead
    assert find_gap(fwd - 1.0 - cfg.keep_out_m - 0.01, right, cfg) is None  # passed, behind
    off = cfg.model_copy(update={"gap_centering_gain_per_s": 0.0})
    assert find_gap(fwd, right, off) is None


def test_hold_inputs_find_a_doorway_from_the_memory() -> None:
    """The remembered jambs of a door 1 m ahead (beyond hold_clear_m and the guard) give the gap."""
    mem = ObstacleMemory()
    cfg = MemoryConfig(gap_centering_gain_per_s=1.0)  # the default, pinned
    wall = np.array([[1.0, e, -1.5] for e in np.arange(-2.0, 2.51, 0.05) if not -0.3 < e < 0.9])
    here = np.array([0.0, 0.0, -1.5])
    mem.add(wall, 0.0, 30.0, viewpoint_ned_m=here + [-0.5, 0.0, 0.0], cfg=cfg)
    # Seen from one place once: not trusted, so no gap (a false point made a false gap, run 22).
    assert mem.hold_inputs(here, 0.0, 0.1, cfg, VIEW).gap is None
    mem.add(wall, 0.1, 30.0, viewpoint_ned_m=here, cfg=cfg)  # seen again from 0.5 m on: trusted
    got = mem.hold_inputs(here, 0.0, 0.5, cfg, VIEW)
    assert got.guard_m is None and got.sides == (False, False)  # beyond the guard and hold_clear_m
    assert got.gap is not None
    assert got.gap.offset_m == pytest.approx(0.3, abs=0.03) and got.gap.width_m == pytest.approx(1.2, abs=0.06)
    # Facing south the same door lies behind: no gap.
    assert mem.hold_inputs(here, math.pi, 0.5, cfg, VIEW).gap is None


def test_a_clear_decision_slides_toward_the_middle_of_a_gap_instead_of_the_line() -> None:
    cfg = MemoryConfig(gap_centering_gain_per_s=1.0)  # the default, pinned
    cmd = CompanionConfig().command.model_copy(update={"hold_resume_delay_s": 0.0})
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    kw = {"heading_error_rad": 0.0, "line_offset_m": -0.5, "clear_for_s": 5.0, "guard_cfg": cfg}  # line left
    assert setpoint_for(clear, 0.0, cmd, **kw).right_m_s < 0.0
    sp = setpoint_for(clear, 0.0, cmd, gap=Gap(0.1, 1.5), **kw)  # the gap's middle 0.1 m right
    assert sp.right_m_s == pytest.approx(cfg.gap_centering_gain_per_s * 0.1)
    far = setpoint_for(clear, 0.0, cmd, gap=Gap(2.0, 1.5), **kw)
    assert far.right_m_s == pytest.approx(cfg.max_gap_centering_speed_m_s)
    # At once, without course hold's wait; scaled down while the decision turns.
    waiting = setpoint_for(clear, 0.0, cmd, gap=Gap(0.1, 1.5), **{**kw, "clear_for_s": 0.0, "heading_clear_for_s": 0.0})
    assert waiting.right_m_s == pytest.approx(sp.right_m_s)
    turning = Decision(DecisionKind.CLEAR, 0.5, 0.0, 1.0, "clear")
    assert setpoint_for(turning, 0.0, cmd, gap=Gap(0.1, 1.5), **kw).right_m_s == pytest.approx(0.5 * sp.right_m_s)
    # Only on CLEAR: an avoiding decision keeps its own (no sideways) velocity.
    avoid = Decision(DecisionKind.AVOID, 0.3, 0.0, 0.5, "avoid")
    assert setpoint_for(avoid, 0.0, cmd, gap=Gap(0.1, 1.5), **kw).right_m_s == 0.0
    # Off: the line hold's sideways step stays.
    off = {**kw, "guard_cfg": MemoryConfig(gap_centering_gain_per_s=0.0)}
    assert setpoint_for(clear, 0.0, cmd, gap=Gap(0.1, 1.5), **off) == setpoint_for(clear, 0.0, cmd, **off)


def test_off_the_middle_of_a_gap_the_vehicle_lines_up_before_it_flies_on() -> None:
    """PX4 SITL doorway-2 (2026-11-26): a 1.3 m door, the vehicle 0.5 m off its middle 0.9 m short of
    it, CLEAR at the full 0.7 m/s while gap centering slid it at 0.18 m/s (PX4 ~0.85 s late): it hit
    the jamb. Off the middle by more than half the width less gap_pass_clearance_m, the forward
    speed falls to 0 over gap_lineup_ramp_m; the slide goes on; a narrowed gap keeps a small band."""
    from companion.core.command import gap_lineup_fraction

    cfg = MemoryConfig(gap_centering_gain_per_s=1.0)  # the default, pinned
    assert (cfg.gap_pass_clearance_m, cfg.gap_lineup_ramp_m, cfg.gap_lineup_min_slack_m) == (0.35, 0.1, 0.05)
    # A 1.3 m door: lined up within 0.65 - 0.35 = 0.3 m of its middle; stopped from 0.4 m off.
    assert gap_lineup_fraction(Gap(0.3, 1.3), cfg) == 1.0
    assert gap_lineup_fraction(Gap(-0.35, 1.3), cfg) == pytest.approx(0.5)
    assert gap_lineup_fraction(Gap(0.5, 1.3), cfg) == 0.0
    # A gap the map has narrowed below twice the clearance still lets a centred vehicle through.
    assert gap_lineup_fraction(Gap(0.04, 0.5), cfg) == 1.0
    assert gap_lineup_fraction(Gap(0.2, 0.5), cfg) == 0.0
    assert gap_lineup_fraction(Gap(0.5, 1.3), cfg.model_copy(update={"gap_pass_clearance_m": 0.0})) == 1.0

    cmd = CompanionConfig().command.model_copy(update={"hold_resume_delay_s": 0.0})
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    kw = {"heading_error_rad": 0.0, "line_offset_m": 0.0, "clear_for_s": 5.0, "guard_cfg": cfg}
    off_middle = setpoint_for(clear, 0.0, cmd, gap=Gap(-0.5, 1.3), **kw)  # the middle 0.5 m left
    assert off_middle.forward_m_s == 0.0
    assert off_middle.right_m_s == pytest.approx(-cfg.max_gap_centering_speed_m_s)  # still sliding to it
    lined_up = setpoint_for(clear, 0.0, cmd, gap=Gap(-0.1, 1.3), **kw)
    assert lined_up.forward_m_s == pytest.approx(cmd.cruise_speed_m_s)
    assert lined_up.right_m_s == pytest.approx(-0.1)
    # Centering off: neither the slide nor the line-up.
    off = {**kw, "guard_cfg": MemoryConfig(gap_centering_gain_per_s=0.0)}
    assert setpoint_for(clear, 0.0, cmd, gap=Gap(-0.5, 1.3), **off) == setpoint_for(clear, 0.0, cmd, **off)


def test_what_lies_in_the_path_slows_the_vehicle_enough_to_stop_short_of_it() -> None:
    """PX4 SITL side-4 and doorway-2 (2026-11-26): CLEAR at 0.7 m/s into a corner the right region read
    at 0.4-0.9 m; the centre region, a fixed angle wide, did not hold it. With path_slow_time_s the
    nearest trusted point within path_half_width_m of the centre line caps the forward speed at
    (distance - path_stop_m) / path_slow_time_s; points beside the path, behind, or seen past do not."""
    from companion.core.command import path_speed_limit_m_s
    from companion.core.memory import path_ahead_m

    cfg = MemoryConfig(path_slow_time_s=1.0)  # off by default
    assert MemoryConfig().path_slow_time_s == 0.0 and path_ahead_m(np.array([1.0]), np.array([0.0]), MemoryConfig()) is None
    assert (cfg.path_stop_m, cfg.path_half_width_m, cfg.path_range_m) == (0.2, 0.3, 2.0)
    # A corner 0.9 m ahead, 0.18 m right: it comes within 0.3 m after 0.9 - sqrt(0.3² - 0.18²) = 0.66 m.
    fwd = np.array([0.9, 0.6, -0.3, 1.5, 0.05])
    right = np.array([0.18, 0.35, 0.0, -0.1, -0.29])  # in the path / beside it / behind / in the path / abreast
    assert path_ahead_m(fwd[:4], right[:4], cfg) == pytest.approx(0.66)
    assert path_ahead_m(fwd[1:3], right[1:3], cfg) is None  # a wall alongside, 0.35 m off: not in the way
    assert path_ahead_m(fwd, right, cfg) == 0.0  # 0.29 m off and just ahead: as near as it may come
    assert path_speed_limit_m_s(0.66, cfg) == pytest.approx(0.46)
    assert path_speed_limit_m_s(0.1, cfg) == 0.0 and math.isinf(path_speed_limit_m_s(None, cfg))
    assert math.isinf(path_speed_limit_m_s(0.66, MemoryConfig()))

    cmd = CompanionConfig().command
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    avoid = Decision(DecisionKind.AVOID, 0.3, 0.0, 1.0, "avoid")
    for d in (clear, avoid):
        assert setpoint_for(d, 0.0, cmd, guard_cfg=cfg, path_ahead_m=0.66).forward_m_s == pytest.approx(0.46)
        assert setpoint_for(d, 0.0, cmd, guard_cfg=cfg, path_ahead_m=2.0).forward_m_s == pytest.approx(cmd.cruise_speed_m_s)
    # From the memory: a trusted corner 0.9 m ahead, 0.18 m right of the centre line.
    mem = ObstacleMemory()
    here = np.array([0.0, 0.0, -1.5])
    corner = np.array([[0.9, 0.18, -1.5]])
    for k in range(2):
        mem.add(corner, 0.1 * k, 30.0, ranges_m=np.array([1.0]), viewpoint_ned_m=here + [0.0, 0.5 * k, 0.0], cfg=cfg)
    got = mem.hold_inputs(here, 0.0, 0.2, cfg, VIEW)
    assert got.ahead_m == pytest.approx(0.66, abs=0.05)
    assert mem.hold_inputs(here, 0.0, 0.2, MemoryConfig(), VIEW).ahead_m is None  # off
    assert mem.hold_inputs(here, math.pi / 2, 0.2, cfg, VIEW).ahead_m is None  # facing east: beside, not ahead
    for _ in range(cfg.map_clear_after_frames):  # the camera sees past it: not in the way now
        mem.see_through(_far_view(6.0), Pose(tuple(here), 0.0), 0.2, cfg)
    assert mem.hold_inputs(here, 0.0, 0.2, cfg, VIEW).ahead_m is None


def _sides(left_m: float, right_m: float) -> np.ndarray:
    """Region depths (float ``(9,)`` metres) that are far everywhere but the left and right regions."""
    from companion.core.types import REGION_INDEX

    d = np.full(9, 10.0)
    d[REGION_INDEX["left"]], d[REGION_INDEX["right"]] = left_m, right_m
    return d


def test_side_room_shrinks_with_the_depth_a_side_region_reads_and_is_none_where_unknown() -> None:
    """Only the side that is not the deeper one is limited. In the kinematic suite with 0.14 m/s of
    drift, limiting both sides made four dead ends collide (as banning every near side had): in a
    dead end both sides read near, and the push away from the wall the vehicle drifts toward is what
    keeps it off that wall."""
    from companion.core.command import side_room_m_s

    cmd = CompanionConfig().command.model_copy(update={"sideways_clear_depth_m": 1.0})  # off by default
    assert side_room_m_s(_sides(0.8, 3.0), cmd) == pytest.approx((0.3, math.inf))
    assert side_room_m_s(_sides(1.0, 0.6), cmd) == pytest.approx((math.inf, 0.1))
    assert side_room_m_s(_sides(0.45, 0.9), cmd) == (0.0, math.inf)
    # In a dead end both sides read near: the deeper one is not limited (the push away from the wall
    # the vehicle drifts toward keeps it off that wall).
    assert side_room_m_s(_sides(0.6, 0.8), cmd) == pytest.approx((0.1, math.inf))
    assert side_room_m_s(_sides(0.5, 0.37), cmd) == (math.inf, 0.0)
    assert side_room_m_s(_sides(0.7, 0.7), cmd) == (math.inf, math.inf)
    # Unknown has no room (PX4 SITL office-0: counted as 0 m against the other side, the guard
    # pushed toward a left region that read 0.37 m).
    assert side_room_m_s(_sides(math.nan, 2.0), cmd) == (0.0, math.inf)
    assert side_room_m_s(_sides(0.37, math.nan), cmd) == (0.0, 0.0)
    assert side_room_m_s(None, cmd) is None
    assert side_room_m_s(_sides(0.6, 3.0), CompanionConfig().command) is None  # off


def test_within_room_holds_the_sideways_speed_unless_it_was_already_more() -> None:
    from companion.core.memory import within_room

    assert within_room(0.5, 0.0, (0.0, 0.2)) == pytest.approx(0.2)
    assert within_room(-0.5, 0.0, (0.0, 0.2)) == 0.0
    assert within_room(0.5, 0.4, (0.0, 0.2)) == pytest.approx(0.4)  # the command had 0.4 itself
    assert within_room(-0.5, 0.0, None) == -0.5


def test_apply_guard_pushes_and_leans_toward_a_near_side_only_within_its_room() -> None:
    cfg = guard_cfg(guard_distance_m=0.6, guard_gain_per_s=1.5, max_guard_speed_m_s=0.5, counter_velocity_fraction=1.0)
    right = np.array([[0.3, 0.0, 1.0]])  # 0.3 m to the right: pushes left at 0.45 m/s
    assert apply_guard(0.7, 0.0, right, cfg) == pytest.approx((0.7, -0.45))
    assert apply_guard(0.7, 0.0, right, cfg, None, (0.0, math.inf)) == pytest.approx((0.7, 0.0))
    assert apply_guard(0.7, 0.0, right, cfg, None, (0.2, math.inf)) == pytest.approx((0.7, -0.2))
    assert apply_guard(0.7, 0.0, right, cfg, (0.0, 0.3), (0.0, math.inf)) == pytest.approx((0.7, 0.0))  # no lean
    assert apply_guard(0.7, 0.0, right, cfg, None, (math.inf, 0.0)) == pytest.approx((0.7, -0.45))
    # The motion toward the point is still removed: the room only holds the push back.
    assert apply_guard(0.0, 0.3, right, cfg, None, (0.0, math.inf)) == pytest.approx((0.0, 0.0))


def test_the_slide_past_a_remembered_point_stays_within_the_room_on_that_side() -> None:
    """PX4 SITL corridor-0: between a box on the left (remembered, its region unknown) and the
    corridor's wall on the right (its region 0.8 m), taking the forward motion off toward the box's
    point ahead on the left slid the vehicle right at 0.3-0.5 m/s, into the wall."""
    cfg = guard_cfg(guard_distance_m=0.6, guard_gain_per_s=0.0, keep_out_m=0.35)
    c = math.cos(math.radians(30.0))
    ahead_left = np.array([[0.5, c, -0.5, 1.0]])  # 0.5 m away, 30 deg left of straight ahead
    f, r = apply_guard(0.7, 0.0, ahead_left, cfg)
    assert r > 0.25 and f < 0.7  # slides right, past it
    assert apply_guard(0.7, 0.0, ahead_left, cfg, None, (0.0, 0.0)) == pytest.approx((0.0, 0.0))  # no room: stops
    f2, r2 = apply_guard(0.7, 0.0, ahead_left, cfg, None, (0.0, 0.1))
    assert r2 == pytest.approx(0.1) and 0.0 < f2 < f and f2 * c - 0.5 * r2 <= 1e-9  # slower, not toward it
    assert apply_guard(0.7, 0.0, ahead_left, cfg, None, (0.0, math.inf)) == pytest.approx((f, r))
    # The slide for the vehicle's own motion (a command off the point's line, the vehicle still
    # flying at it) is held back the same way.
    lean = guard_cfg(guard_distance_m=0.6, guard_gain_per_s=0.0, keep_out_m=0.35, counter_velocity_fraction=0.0)
    assert apply_guard(0.6, 0.35, ahead_left, lean, (0.7, 0.0))[1] > 0.5
    held = apply_guard(0.6, 0.35, ahead_left, lean, (0.7, 0.0), (0.0, 0.0))
    assert held[1] == pytest.approx(0.35) and held[0] * c - 0.5 * held[1] <= 1e-9
    # Through the whole setpoint: held with the side rule on, the slide with it off.
    cmd = CompanionConfig().command.model_copy(update={"sideways_clear_depth_m": 1.0})
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    kw = {"guard_m": ahead_left, "guard_cfg": cfg, "region_depths_m": _sides(math.nan, 0.8)}
    assert setpoint_for(clear, 0.0, cmd, **kw).right_m_s == pytest.approx(0.3)
    off = cmd.model_copy(update={"sideways_clear_depth_m": 0.0})
    assert setpoint_for(clear, 0.0, off, **kw).right_m_s > 0.25


def test_a_remembered_wall_does_not_push_the_vehicle_into_what_the_camera_sees_on_the_other_side() -> None:
    """PX4 SITL corridor-8: passing a box close to the wall on the right, PX4's estimate 0.5-0.7 m
    off; the guard pushed away from the remembered wall at 0.5 m/s, into the box's corner that the
    left regions read at 0.9 -> 0.5 m. The camera's reading of that side now limits the push."""
    cmd = CompanionConfig().command.model_copy(update={"sideways_clear_depth_m": 1.0})  # off by default
    mem = MemoryConfig(gap_centering_gain_per_s=1.0)
    clear = Decision(DecisionKind.CLEAR, 0.0, 0.0, 1.0, "clear")
    wall = np.array([[0.2, 0.0, 1.0]])  # remembered 0.2 m to the right, beside the vehicle (out of view)
    kw = {"guard_m": wall, "guard_cfg": mem}
    assert setpoint_for(clear, 0.0, cmd, region_depths_m=_sides(3.0, 3.0), **kw).right_m_s < -0.3  # pushed left
    corner = setpoint_for(clear, 0.0, cmd, region_depths_m=_sides(0.6, 3.0), **kw)
    assert corner.right_m_s == pytest.approx(-0.1) and corner.forward_m_s == pytest.approx(cmd.cruise_speed_m_s)
    assert setpoint_for(clear, 0.0, cmd, region_depths_m=_sides(0.5, 3.0), **kw).right_m_s == pytest.approx(0.0)
    # Gap centering toward the nearer side is held back too; toward the farther side it acts.
    gap = {"guard_cfg": mem, "gap": Gap(-0.2, 1.5)}
    assert setpoint_for(clear, 0.0, cmd, region_depths_m=_sides(3.0, 3.0), **gap).right_m_s == pytest.approx(-0.2)
    assert setpoint_for(clear, 0.0, cmd, region_depths_m=_sides(0.6, 3.0), **gap).right_m_s == pytest.approx(-0.1)
    assert setpoint_for(clear, 0.0, cmd, region_depths_m=_sides(3.0, 0.6), **gap).right_m_s == pytest.approx(-0.2)
    # Off: the push as before.
    off = cmd.model_copy(update={"sideways_clear_depth_m": 0.0})
    assert setpoint_for(clear, 0.0, off, region_depths_m=_sides(0.6, 3.0), **kw).right_m_s < -0.3


def test_ned_to_body_horizontal_rotates_by_the_heading_for_floats_and_arrays() -> None:
    from companion.core.frames import ned_to_body_horizontal

    assert ned_to_body_horizontal(0.0, 1.0, math.pi / 2) == pytest.approx((1.0, 0.0))  # facing east
    assert ned_to_body_horizontal(1.0, 0.0, math.pi / 2) == pytest.approx((0.0, -1.0))  # north is left
    f, r = ned_to_body_horizontal(np.array([1.0, 0.0]), np.array([0.0, 1.0]), 0.0)
    np.testing.assert_allclose(f, [1.0, 0.0])
    np.testing.assert_allclose(r, [0.0, 1.0])


# ------------------------------------------------------------------------------------- seeing past


def test_window_max_is_the_nearest_valid_block_round_each_measured_block() -> None:
    b = np.full((5, 7), 2.0, np.float32)
    b[2, 3] = 9.0  # one near block (a thin post)
    b[0, 0] = np.nan  # not measured
    got = window_max(b, 1)
    assert got[1:4, 2:5].min() == 9.0 and got[2, 5] == 2.0  # the post keeps its neighbours near
    assert np.isnan(got[0, 0]) and got[0, 1] == 2.0  # a block not measured is not judged
    assert window_max(np.full((2, 2), np.nan, np.float32), 2).shape == (2, 2)
    rng = np.random.default_rng(3)
    r = rng.uniform(1, 60, (9, 13)).astype(np.float32)
    r[rng.random(r.shape) < 0.3] = np.nan
    want = np.full(r.shape, np.nan, np.float32)
    for y, x in zip(*np.nonzero(r > 0)):
        want[y, x] = np.nanmax(r[max(0, y - 2) : y + 3, max(0, x - 2) : x + 3])
    assert np.array_equal(window_max(r, 2), want, equal_nan=True)  # the brute force, exactly


def _far_view(depth_m: float, shape: tuple[int, int] = (16, 32)) -> FarView:
    """A frame of GEOM whose every block measures ``depth_m`` (NaN: nothing measured)."""
    d = GEOM.focal_baseline_px_m / depth_m if math.isfinite(depth_m) else np.nan
    return FarView(np.full(shape, d, np.float32), GEOM, 4, VIEW)


SEEN = MemoryConfig(trust_min_frames=2, trust_persist_s=0.0)  # trusted from the second frame


def _remembered(points_ned: np.ndarray) -> ObstacleMemory:
    mem = ObstacleMemory()
    for k in range(2):  # trusted by persistence, from the start point
        mem.add(points_ned, 0.1 * k, SEEN.duration_s, ranges_m=np.full(len(points_ned), 2.0),
                viewpoint_ned_m=np.array([0.0, 0.0, -1.5]), cfg=SEEN)
    return mem


def test_a_point_seen_past_frame_after_frame_leaves_the_map_but_still_guards() -> None:
    """A point seen past leaves the detour layer's map but still guards: the position estimate's drift
    moves true points off their surfaces too, where they are seen past, and forgetting them outright
    added 4 collisions to the simulator's four drift suites."""
    here = np.array([0.0, 0.0, -1.5])
    mem = _remembered(np.array([[2.0, 0.0, -1.5]]))  # 2 m ahead of a vehicle facing north
    pose = Pose(tuple(here), 0.0)
    assert len(mem.map_points(here, 0.2, SEEN, 5.0)) == 1
    for k in range(SEEN.map_clear_after_frames - 1):
        assert mem.see_through(_far_view(6.0), pose, 0.2, SEEN) == 0  # the wall 6 m off: a miss
    assert len(mem.map_points(here, 0.2, SEEN, 5.0)) == 1
    assert mem.see_through(_far_view(6.0), pose, 0.2, SEEN) == 1
    assert len(mem.map_points(here, 0.2, SEEN, 5.0)) == 0  # out of the detour layer's map
    assert mem.seen_past_mask(0.2, SEEN).tolist() == [True]  # what the simulator's audit leaves out
    assert mem.seen_past_count(SEEN) == 1  # what the health message reports
    beside = np.array([2.0, -0.45, -1.5])  # the point 0.45 m to the right, out of view
    g = mem.guard(beside, 0.0, 0.2, SEEN, VIEW)
    assert g is not None and g[0, 0] == pytest.approx(0.45)  # it still guards
    mem.add(np.array([[2.0, 0.0, -1.5]]), 0.3, SEEN.duration_s, ranges_m=np.array([2.0]),
            viewpoint_ned_m=here, cfg=SEEN)
    assert len(mem.map_points(here, 0.3, SEEN, 5.0)) == 1  # seen again: back
    assert mem.seen_past_count(SEEN) == 0


def test_a_point_seen_past_long_enough_stops_guarding_with_guard_clear_after_s() -> None:
    """Kinematic office-4: a door's jamb smeared into the opening, seen past 3-15 s in a row, kept the
    vehicle in the door for 10 s. A point seen past for guard_clear_after_s in a row no longer guards,
    keeps course hold from a side or bounds a gap; seen again, it does. Never sooner; 0 turns it off
    (4 s by default)."""
    here = np.array([0.0, 0.0, -1.5])
    beside = np.array([2.0, -0.45, -1.5])  # 0.45 m left of the point, facing north: out of view
    cfg = SEEN.model_copy(update={"guard_clear_after_s": 1.0})
    mem = _remembered(np.array([[2.0, 0.0, -1.5]]))
    pose = Pose(tuple(here), 0.0)
    for k in range(10):  # 10 Hz: the first frame judged has no interval before it
        mem.see_through(_far_view(6.0), pose, 0.2 + 0.1 * k, cfg)
    assert mem.guard(beside, 0.0, 0.2, cfg, VIEW) is not None  # 0.9 s: still there
    assert mem.guard_cleared_count(cfg) == 0  # what the health message reports
    assert mem.hold_inputs(beside, 0.0, 0.2, cfg, VIEW).sides == (False, True)
    mem.see_through(_far_view(6.0), pose, 1.2, cfg)
    assert mem.guard(beside, 0.0, 0.2, cfg, VIEW) is None  # 1.0 s: not there
    assert mem.guard_cleared_count(cfg) == 1
    assert mem.hold_inputs(beside, 0.0, 0.2, cfg, VIEW).sides == (False, False)
    off = cfg.model_copy(update={"guard_clear_after_s": 0.0})
    assert mem.guard(beside, 0.0, 0.2, off, VIEW) is not None  # off (0): it guards
    assert mem.guard_cleared_count(off) == 0
    assert MemoryConfig().guard_clear_after_s == 4.0
    mem.add(np.array([[2.0, 0.0, -1.5]]), 1.3, cfg.duration_s, ranges_m=np.array([2.0]),
            viewpoint_ned_m=here, cfg=cfg)
    assert mem.guard(beside, 0.0, 1.3, cfg, VIEW) is not None  # seen again: guards again
    assert mem.guard_cleared_count(cfg) == 0


@pytest.mark.parametrize("rate_hz", [15.0, 30.0, 60.0])
def test_the_guard_forgets_after_the_same_time_at_any_camera_rate(rate_hz: float) -> None:
    """The default (4 s) was measured at the simulator's 15 Hz as 60 frames; the ZED's default 30 fps
    and 60 fps forget after the same 4 s, not after 2 s or 1 s."""
    cfg = SEEN.model_copy(update={"guard_clear_after_s": 4.0})
    here = np.array([0.0, 0.0, -1.5])
    mem = _remembered(np.array([[2.0, 0.0, -1.5]]))
    pose = Pose(tuple(here), 0.0)
    period = 1.0 / rate_hz
    n = round(4.0 * rate_hz)
    mem.see_through(_far_view(2.0), pose, 0.2, cfg)  # seen at its depth: the frame before the run
    for k in range(1, n):
        mem.see_through(_far_view(6.0), pose, 0.2 + k * period, cfg)
    assert mem.guard_cleared_count(cfg) == 0, f"{n - 1} frames at {rate_hz:g} Hz"
    mem.see_through(_far_view(6.0), pose, 0.2 + n * period, cfg)
    assert mem.guard_cleared_count(cfg) == 1, f"{n} frames at {rate_hz:g} Hz"


def test_a_camera_stall_counts_as_one_look_not_as_time_seen_past() -> None:
    """After a stall, one frame that sees past a point adds at most LONGEST_COUNTED_FRAME_S: a camera
    that stops for 5 s does not let one look clear the guard."""
    cfg = SEEN.model_copy(update={"guard_clear_after_s": 1.0})
    here = np.array([0.0, 0.0, -1.5])
    mem = _remembered(np.array([[2.0, 0.0, -1.5]]))
    pose = Pose(tuple(here), 0.0)
    mem.see_through(_far_view(2.0), pose, 0.2, cfg)
    mem.see_through(_far_view(6.0), pose, 5.2, cfg)  # 5 s later, one look past it
    assert mem.guard_cleared_count(cfg) == 0
    for k in range(1, 5):  # four more looks, 0.2 s apart: 1.0 s counted in all
        mem.see_through(_far_view(6.0), pose, 5.2 + 0.2 * k, cfg)
    assert LONGEST_COUNTED_FRAME_S == 0.2 and mem.guard_cleared_count(cfg) == 1


def test_a_point_seen_at_its_depth_starts_counting_again() -> None:
    here = np.array([0.0, 0.0, -1.5])
    mem = _remembered(np.array([[2.0, 0.0, -1.5]]))
    pose = Pose(tuple(here), 0.0)
    n = SEEN.map_clear_after_frames
    for _ in range(n - 1):
        mem.see_through(_far_view(6.0), pose, 0.2, SEEN)
    mem.see_through(_far_view(2.1), pose, 0.2, SEEN)  # there after all (within the ratio)
    for _ in range(n - 1):
        mem.see_through(_far_view(6.0), pose, 0.2, SEEN)
    assert len(mem.map_points(here, 0.2, SEEN, 5.0)) == 1  # never n misses in a row
    mem.see_through(_far_view(1.0), pose, 0.2, SEEN)  # something nearer in front: hidden, not past
    assert len(mem.map_points(here, 0.2, SEEN, 5.0)) == 1


@pytest.mark.parametrize(
    "point, far_m, why",
    [
        ((2.0, 0.0, -1.5), math.nan, "its block not measured (a plain wall)"),
        ((0.1, 0.0, -1.5), 6.0, "nearer than the rig can see"),
        ((-2.0, 0.0, -1.5), 6.0, "behind the camera"),
        ((2.0, -1.9, -1.5), 6.0, "left of the measured view"),
        ((2.0, 3.0, -1.5), 6.0, "outside the image"),
    ],
)
def test_points_the_frame_does_not_measure_are_never_cleared(point, far_m, why) -> None:
    here = np.array([0.0, 0.0, -1.5])
    mem = _remembered(np.array([point]))
    before = len(mem.map_points(here, 0.2, SEEN, 5.0))
    for _ in range(3 * SEEN.map_clear_after_frames):
        mem.see_through(_far_view(far_m), Pose(tuple(here), 0.0), 0.2, SEEN)
    assert len(mem.map_points(here, 0.2, SEEN, 5.0)) == before, why


def test_seeing_past_is_off_with_zero_frames_and_near_cells_make_the_frame_view() -> None:
    here = np.array([0.0, 0.0, -1.5])
    off = SEEN.model_copy(update={"map_clear_after_frames": 0})
    mem = _remembered(np.array([[2.0, 0.0, -1.5]]))
    for _ in range(5):
        mem.add_frame(np.empty((0, 3)), Pose(tuple(here), 0.0), 0.2, off, _far_view(6.0))
    assert len(mem.map_points(here, 0.2, off, 5.0)) == 1
    near = NearCells(CFG, GEOM, (16, 32))
    blocks = np.full((16, 32), 4.0, np.float32)
    fv = near.far_view(blocks, VIEW)
    assert fv.nearest_disparity_px.shape == (16, 32) and fv.block_px == CFG.block_px
    assert CLEAR_WINDOW_BLOCKS >= 1
    with pytest.raises(ValueError, match="must be"):
        near.far_view(np.zeros((3, 3), np.float32), VIEW)


def test_a_pose_from_telemetry_is_none_unless_both_parts_are_three_finite_numbers() -> None:
    """The supervisor and the flight replay tool read the vehicle's pose from the link's position
    (NED metres) and attitude (roll, pitch, yaw radians): missing, malformed or non-finite gives None,
    never a pose the memory would place points from."""
    pose = Pose.from_telemetry([1.0, 2.0, -1.5], (0.1, -0.2, 0.3))
    assert pose == Pose((1.0, 2.0, -1.5), 0.3, -0.2, 0.1)
    for position, attitude in (
        (None, (0.0, 0.0, 0.0)),
        ((0.0, 0.0, -1.0), None),
        ((0.0, 0.0), (0.0, 0.0, 0.0)),
        ((0.0, 0.0, float("nan")), (0.0, 0.0, 0.0)),
        ((0.0, 0.0, -1.0), (0.0, float("inf"), 0.0)),
        ("abc", (0.0, 0.0, 0.0)),
    ):
        assert Pose.from_telemetry(position, attitude) is None
