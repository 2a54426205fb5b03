"""Synthetic stereo renderer: exact depth, consistent eyes, clipping, texture, conventions, ground truth."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from companion.core.geometry import StereoGeometry
from companion.sim.render import (
    Box,
    Photometry,
    Pillar,
    Pose,
    RenderResult,
    Scene,
    StereoRenderer,
    TextureBank,
    corridor_scene,
)

GEO = StereoGeometry.ideal(672, 376, hfov_deg=87.0, baseline_m=0.12)
FB = GEO.focal_baseline_px_m
ALT = 1.5


def wall_scene(distance_m: float, yaw_rad: float = 0.0, extra: tuple = ()) -> Scene:
    """A 40 m wide, 20 m tall wall whose near face is ``distance_m`` north of the origin."""
    wall = Box((distance_m + 0.5, 0.0, -ALT), (1.0, 40.0, 20.0), yaw_rad)
    return Scene((wall, *extra))


#: Textures for seed 0, shared by most tests (generating them is most of a first frame's cost).
SHARED_TEXTURES = TextureBank(0, 1024, pad=512)


def render(scene: Scene, pose: Pose, seed: int = 0) -> RenderResult:
    textures = SHARED_TEXTURES if seed == 0 else None
    return StereoRenderer(GEO, scene, seed=seed, textures=textures).render(pose)


def grey(img: np.ndarray) -> np.ndarray:
    return img[:, :, 0].astype(np.float32)


def rays_world(pose: Pose) -> np.ndarray:
    """Unit-z camera rays of every pixel centre, rotated to NED: float64 (H, W, 3)."""
    u = (np.arange(GEO.width_px) - GEO.cx_px) / GEO.focal_px
    v = (np.arange(GEO.height_px) - GEO.cy_px) / GEO.focal_px
    uu, vv = np.meshgrid(u, v)
    r_cam = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    return r_cam @ pose.ned_from_camera().T


def analytic_plane_depth(pose: Pose, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Depth (camera z) where each pixel's ray meets the plane through ``point`` with ``normal``."""
    rays = rays_world(pose)
    origin = np.asarray(pose.position_ned_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (normal @ (point - origin)) / (rays @ normal)


# ---------------------------------------------------------------- depth


@pytest.mark.parametrize("distance_m", [0.7, 1.7, 2.5])
def test_fronto_parallel_wall_depth_is_exact(distance_m: float) -> None:
    res = render(wall_scene(distance_m), Pose.at(0.0, 0.0, ALT))
    assert res.depth_m.dtype == np.float32 and res.depth_m.shape == (GEO.height_px, GEO.width_px)
    np.testing.assert_allclose(res.depth_m, distance_m, rtol=1e-4)


def test_yawed_wall_depth_matches_analytic_plane() -> None:
    yaw = math.radians(35.0)
    pose = Pose.at(0.0, 0.0, ALT, yaw_rad=0.1, pitch_rad=0.05, roll_rad=-0.04)
    res = render(wall_scene(3.0, yaw_rad=yaw), pose)
    normal = np.array([-math.cos(yaw), -math.sin(yaw), 0.0])  # the wall's near face, towards us
    point = np.array([3.0 + 0.5, 0.0, -ALT]) + 0.5 * normal
    expected = analytic_plane_depth(pose, normal, point)
    hit = rays_world(pose) * expected[..., None] + np.asarray(pose.position_ned_m)
    # Pixels that see the near face (in front, above the ground), away from the face's edges.
    ok = (expected > 0) & (expected < 8.0) & (hit[..., 2] < -0.05)
    ok = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(res.depth_m[ok], expected[ok], rtol=1e-4)


def test_ground_depth_matches_analytic_with_pitch_and_roll() -> None:
    pose = Pose.at(5.0, -3.0, 2.0, yaw_rad=0.7, pitch_rad=-0.35, roll_rad=0.15)
    res = render(Scene(), pose)
    expected = analytic_plane_depth(pose, np.array([0.0, 0.0, -1.0]), np.zeros(3))
    hit = rays_world(pose) * expected[..., None] + np.asarray(pose.position_ned_m)
    ok = (expected > 0) & (np.abs(hit[..., :2]).max(axis=-1) < 60.0)  # well inside the world box
    ok = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(res.depth_m[ok], expected[ok], rtol=1e-4)


def test_every_pixel_sees_something_inside_the_world() -> None:
    res = render(corridor_scene(seed=3), Pose.at(10.0, 0.5, 1.5, yaw_rad=0.4, pitch_rad=0.3))
    assert np.all(np.isfinite(res.depth_m)) and res.depth_m.min() > 0.0


# ---------------------------------------------------------------- stereo consistency


def test_integer_disparity_right_eye_is_left_shifted() -> None:
    """At Z = f*B/20 the right image is the left one shifted by exactly 20 px."""
    res = render(wall_scene(FB / 20.0), Pose.at(0.0, 0.0, ALT))
    left, right = grey(res.left_bgr), grey(res.right_bgr)
    diff = np.abs(left[:, 20:] - right[:, :-20])
    assert diff.mean() < 0.05 and diff.max() <= 2.0
    assert np.abs(left[:, 21:] - right[:, :-21]).mean() > 5.0  # and not at 21 px


def test_right_eye_is_the_left_eye_of_a_pose_one_baseline_to_the_right() -> None:
    """Whole-pipeline consistency (clipping, LOD, texture tiles, z-test) on a cluttered scene."""
    r = StereoRenderer(GEO, corridor_scene(seed=3), seed=0, textures=SHARED_TEXTURES)
    rng = np.random.default_rng(0)
    for _ in range(3):
        pose = Pose.at(
            rng.uniform(2.0, 60.0), rng.uniform(-2.0, 2.0), rng.uniform(0.3, 3.0),
            yaw_rad=rng.uniform(-1.0, 1.0), pitch_rad=rng.uniform(-0.4, 0.4), roll_rad=rng.uniform(-0.3, 0.3),
        )
        shifted = np.asarray(pose.position_ned_m) + pose.ned_from_camera()[:, 0] * GEO.baseline_m
        pose_r = Pose(tuple(shifted), pose.yaw_rad, pose.pitch_rad, pose.roll_rad)
        diff = np.abs(grey(r.render(pose).right_bgr) - grey(r.render(pose_r).left_bgr))
        # identical but for a few silhouette pixels where vertex rounding differs
        assert diff.mean() < 0.02 and (diff > 2).mean() < 5e-4


def _global_disparity(left: np.ndarray, right: np.ndarray, rows: slice, cols: slice) -> float:
    """One disparity for a region: best integer shift in [0, 64) by SSD, refined to 0.01 px by
    resampling the left image (bicubic) at sub-pixel shifts."""
    target = right[rows, cols]
    ssd = [np.mean((left[rows, cols.start + d : cols.stop + d] - target) ** 2) for d in range(64)]
    d0 = int(np.argmin(ssd))
    ys, xs = np.mgrid[rows, cols].astype(np.float32)
    shifts = np.arange(d0 - 1.0, d0 + 1.0, 0.01)
    costs = [
        np.mean((cv2.remap(left, xs + np.float32(d), ys, cv2.INTER_CUBIC) - target) ** 2) for d in shifts
    ]
    return float(shifts[int(np.argmin(costs))])


@pytest.mark.parametrize("distance_m", [1.3, 1.75, 4.1, 9.3])
def test_fronto_parallel_disparity_is_fb_over_z(distance_m: float) -> None:
    res = render(wall_scene(distance_m), Pose.at(0.0, 0.0, ALT))
    rows = slice(140, 236)  # around the horizon: wall pixels even where the ground shows below
    assert np.allclose(res.depth_m[rows, 60:612], distance_m, rtol=1e-4)
    d = _global_disparity(grey(res.left_bgr), grey(res.right_bgr), rows, slice(80, 560))
    assert d == pytest.approx(FB / distance_m, abs=0.05)


def _subpixel_match(
    left: np.ndarray, right: np.ndarray, u: int, v: int, d_guess: float, half: int = 7
) -> float:
    """Disparity at (u, v): ZNCC over a (2*half+1)^2 window, integer search near d_guess, parabola fit."""
    patch = left[v - half : v + half + 1, u - half : u + half + 1]
    lo, hi = int(math.floor(d_guess)) - 3, int(math.ceil(d_guess)) + 3
    scores = []
    for d in range(lo, hi + 1):
        cand = right[v - half : v + half + 1, u - d - half : u - d + half + 1]
        scores.append(cv2.matchTemplate(cand, patch, cv2.TM_CCOEFF_NORMED)[0, 0])
    s = np.asarray(scores)
    k = int(np.argmax(s[1:-1])) + 1
    denom = s[k - 1] - 2 * s[k] + s[k + 1]
    return lo + k + (0.5 * (s[k - 1] - s[k + 1]) / denom if denom != 0 else 0.0)


def test_slanted_wall_local_disparity_matches_depth() -> None:
    """Patch matching on a wall at 40 deg recovers f*B/Z of the ground-truth depth, pixel by pixel."""
    res = render(wall_scene(2.5, yaw_rad=math.radians(40.0)), Pose.at(0.0, 0.0, ALT))
    left, right = grey(res.left_bgr), grey(res.right_bgr)
    errors = []
    for v in range(120, 260, 20):
        for u in range(120, 640, 40):
            z = float(res.depth_m[v, u])
            d_true = FB / z
            # skip where the window or its match leaves the wall face
            if not np.all(np.abs(res.depth_m[v - 8 : v + 9, u - 8 : u + 9] - z) < 0.2 * z):
                continue
            errors.append(_subpixel_match(left, right, u, v, d_true) - d_true)
    errors_arr = np.asarray(errors)
    assert errors_arr.size > 40
    assert np.median(np.abs(errors_arr)) < 0.15
    assert np.percentile(np.abs(errors_arr), 90) < 0.25


# ---------------------------------------------------------------- visibility and clipping


def test_box_in_front_of_wall_occludes_it() -> None:
    box = Box((2.0 + 0.25, 0.0, -ALT), (0.5, 1.0, 1.0))  # near face at 2.0 m, 1 m wide and tall
    res = render(wall_scene(5.0, extra=(box,)), Pose.at(0.0, 0.0, ALT))
    # the box spans f*0.5/2 = 88 px either side of the centre at 2 m
    centre = res.depth_m[int(GEO.cy_px) - 60 : int(GEO.cy_px) + 60, int(GEO.cx_px) - 60 : int(GEO.cx_px) + 60]
    np.testing.assert_allclose(centre, 2.0, rtol=1e-4)
    np.testing.assert_allclose(res.depth_m[150:220, 20:60], 5.0, rtol=1e-4)
    np.testing.assert_allclose(res.depth_m[150:220, 612:652], 5.0, rtol=1e-4)


def test_pillar_depth_and_silhouette() -> None:
    pillar = Pillar.on_ground(3.0, 0.0, radius_m=0.3, height_m=3.0, sides=16)  # a face looks south
    res = render(Scene((pillar,)), Pose.at(0.0, 0.0, ALT))
    cu, cv = int(GEO.cx_px), int(GEO.cy_px)
    assert res.depth_m[cv, cu] == pytest.approx(2.7, rel=1e-4)
    # silhouette: the extreme vertical edges as seen from the camera
    ang = (np.arange(16) + 0.5) * 2 * math.pi / 16
    r_vertex = 0.3 / math.cos(math.pi / 16)
    slope = (r_vertex * np.sin(ang)) / (3.0 + r_vertex * np.cos(ang))
    width_px = GEO.focal_px * (slope.max() - slope.min())
    on_pillar = np.flatnonzero(res.depth_m[cv] < 3.5)
    assert on_pillar.size == pytest.approx(width_px, abs=2.0)


def test_objects_behind_the_camera_are_not_drawn() -> None:
    pose = Pose.at(0.0, 0.0, ALT)
    base = render(wall_scene(4.0), pose)
    behind = (Box((-1.0, 0.0, -ALT), (0.5, 3.0, 3.0)), Pillar((-0.5, 0.3, -ALT), 0.2, 3.0))
    with_behind = render(wall_scene(4.0, extra=behind), pose)
    np.testing.assert_array_equal(base.depth_m, with_behind.depth_m)
    np.testing.assert_array_equal(base.left_bgr, with_behind.left_bgr)
    np.testing.assert_array_equal(base.right_bgr, with_behind.right_bgr)


def test_camera_five_centimetres_from_a_wall() -> None:
    res = render(wall_scene(0.05), Pose.at(0.0, 0.0, ALT))
    np.testing.assert_allclose(res.depth_m, 0.05, rtol=1e-4)
    assert np.isfinite(res.depth_m).all()
    assert grey(res.left_bgr).std() > 3.0 and grey(res.right_bgr).std() > 3.0  # textured, not blank


def test_faces_crossing_the_near_plane_are_clipped() -> None:
    """Grazing view along a wall 3 cm away, and the camera inside a box: no garbage, exact depth."""
    scene = Scene((Box.on_ground(20.0, 3.15, (40.0, 0.3, 4.0)),))  # inner face at east = +3.0
    pose = Pose.at(20.0, 2.97, 1.2, yaw_rad=math.radians(60.0))
    res = render(scene, pose)
    assert np.isfinite(res.depth_m).all() and res.depth_m.min() > 0.0
    expected = analytic_plane_depth(pose, np.array([0.0, -1.0, 0.0]), np.array([0.0, 3.0, 0.0]))
    hit = rays_world(pose) * expected[..., None] + np.asarray(pose.position_ned_m)
    on_wall = (expected > 0) & (hit[..., 2] < -0.05) & (hit[..., 2] > -3.95) & (expected < 3.0)
    on_wall = cv2.erode(on_wall.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert on_wall.mean() > 0.3
    np.testing.assert_allclose(res.depth_m[on_wall], expected[on_wall], rtol=1e-4)

    inside = Box((3.0, 0.0, -ALT), (2.0, 2.0, 2.0))
    pose_in = Pose.at(3.2, 0.1, ALT, yaw_rad=0.3)
    a = render(wall_scene(6.0), pose_in)
    b = render(wall_scene(6.0, extra=(inside,)), pose_in)  # inside a box: its faces are back faces
    np.testing.assert_array_equal(a.depth_m, b.depth_m)


# ---------------------------------------------------------------- texture


@pytest.mark.parametrize("distance_m", [1.0, 2.0, 3.0])
def test_texture_is_rich_at_typical_distances(distance_m: float) -> None:
    res = render(wall_scene(distance_m), Pose.at(0.0, 0.0, ALT))
    rows = slice(140, 236)
    for img in (res.left_bgr, res.right_bgr):
        g = grey(img)[rows]
        assert np.abs(np.diff(g, axis=1)).mean() >= 5.0


def test_ground_and_sky_are_textured() -> None:
    res = render(Scene(), Pose.at(0.0, 0.0, ALT))
    g = grey(res.left_bgr)
    sky = g[:120]  # above the horizon: the backdrop
    ground = g[280:]
    assert np.abs(np.diff(sky, axis=1)).mean() >= 2.0
    assert np.abs(np.diff(ground, axis=1)).mean() >= 5.0


def test_same_seed_same_images_other_seed_other_texture() -> None:
    scene = corridor_scene(seed=2)
    pose = Pose.at(6.0, 0.3, 1.4, yaw_rad=0.2)
    a = render(scene, pose, seed=5)
    b = render(scene, pose, seed=5)
    c = render(scene, pose, seed=6)
    np.testing.assert_array_equal(a.left_bgr, b.left_bgr)
    np.testing.assert_array_equal(a.right_bgr, b.right_bgr)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    np.testing.assert_array_equal(a.depth_m, c.depth_m)  # geometry does not depend on the seed
    assert np.abs(grey(a.left_bgr) - grey(c.left_bgr)).mean() > 10.0


def test_shared_texture_bank_gives_the_same_images() -> None:
    scene = corridor_scene(seed=2)
    pose = Pose.at(6.0, 0.3, 1.4, yaw_rad=0.2)
    own = StereoRenderer(GEO, scene, seed=0).render(pose)
    shared = StereoRenderer(GEO, scene, seed=0, textures=SHARED_TEXTURES).render(pose)
    np.testing.assert_array_equal(own.left_bgr, shared.left_bgr)
    np.testing.assert_array_equal(own.right_bgr, shared.right_bgr)


def test_renderer_is_repeatable_across_frames() -> None:
    r = StereoRenderer(GEO, corridor_scene(seed=2), seed=1)
    p1, p2 = Pose.at(6.0, 0.3, 1.4), Pose.at(30.0, -1.0, 2.0, yaw_rad=1.0)
    first = r.render(p1)
    r.render(p2)
    again = r.render(p1)
    np.testing.assert_array_equal(first.left_bgr, again.left_bgr)
    np.testing.assert_array_equal(first.depth_m, again.depth_m)


# ---------------------------------------------------------------- pose conventions


def _marker_centroid(pose: Pose) -> tuple[float, float]:
    """Image centroid (u, v) of a small box 4 m north of the origin at 1.5 m altitude."""
    marker = Box((4.0, 0.0, -ALT), (0.3, 0.3, 0.3))
    res = render(Scene((marker,), ground=False), pose)  # no ground: only the marker is near
    vs, us = np.nonzero(res.depth_m < 5.0)
    assert us.size > 20
    return float(us.mean()), float(vs.mean())


def test_pose_conventions_move_the_image_the_right_way() -> None:
    u0, v0 = _marker_centroid(Pose.at(0.0, 0.0, ALT))
    assert u0 == pytest.approx(GEO.cx_px, abs=1.0) and v0 == pytest.approx(GEO.cy_px, abs=1.0)
    u, v = _marker_centroid(Pose.at(0.0, 0.0, ALT, yaw_rad=0.2))  # yaw right
    assert u < u0 - 50 and v == pytest.approx(v0, abs=3.0)
    u, v = _marker_centroid(Pose.at(0.0, 0.5, ALT))  # step east (right): f * 0.5 / 4 = 44 px
    assert u < u0 - 35
    u, v = _marker_centroid(Pose.at(0.0, 0.0, ALT + 0.5))  # climb
    assert v > v0 + 30
    u, v = _marker_centroid(Pose.at(0.0, 0.0, ALT, pitch_rad=0.2))  # nose up
    assert v > v0 + 50
    # roll right (right wing down): the camera rolls clockwise, the world appears to turn
    # counter-clockwise, so a point right of centre moves up in the image
    right_marker = Box((4.0, 1.0, -ALT), (0.3, 0.3, 0.3))
    for roll, sign in ((0.0, 0), (0.2, -1)):
        res = render(Scene((right_marker,), ground=False), Pose.at(0.0, 0.0, ALT, roll_rad=roll))
        vs, _ = np.nonzero(res.depth_m < 5.0)
        if sign == 0:
            v_level = vs.mean()
        else:
            assert vs.mean() < v_level - 10


def test_climbing_moves_the_ground_down() -> None:
    low = render(Scene(), Pose.at(0.0, 0.0, 1.0))
    high = render(Scene(), Pose.at(0.0, 0.0, 3.0))
    col = int(GEO.cx_px)
    # the ground 6 m ahead: its image row grows with altitude (v = cy + f*h/6)
    for res, h in ((low, 1.0), (high, 3.0)):
        row = int(round(GEO.cy_px + GEO.focal_px * h / 6.0))
        assert res.depth_m[row, col] == pytest.approx(6.0, rel=0.01)


def test_camera_offset_and_eye_positions() -> None:
    r = StereoRenderer(GEO, Scene(), camera_offset_frd_m=(0.2, 0.0, -0.1))
    pose = Pose.at(1.0, 2.0, 3.0, yaw_rad=math.pi / 2)
    left, right = r.eye_positions_ned_m(pose)
    np.testing.assert_allclose(left, [1.0, 2.2, -3.1], atol=1e-12)  # forward is east
    np.testing.assert_allclose(right - left, [-0.12, 0.0, 0.0], atol=1e-12)  # right is south


# ---------------------------------------------------------------- outputs and photometry


def test_side_by_side_matches_render_and_reuses_out() -> None:
    r = StereoRenderer(GEO, corridor_scene(seed=4), seed=3)
    pose = Pose.at(5.0, 0.0, 1.5)
    res = r.render(pose)
    out = np.zeros((GEO.height_px, 2 * GEO.width_px, 3), np.uint8)
    depth = np.zeros((GEO.height_px, GEO.width_px), np.float32)
    frame = r.render_side_by_side(pose, out=out, depth_out=depth)
    assert frame is out and frame.dtype == np.uint8
    np.testing.assert_array_equal(frame, res.side_by_side())
    np.testing.assert_array_equal(depth, res.depth_m)
    assert np.array_equal(res.left_bgr[..., 0], res.left_bgr[..., 2])  # grey replicated in BGR
    with pytest.raises(ValueError, match="out must be"):
        r.render_side_by_side(pose, out=np.zeros((10, 10, 3), np.uint8))


def test_photometry_gain_and_noise() -> None:
    r = StereoRenderer(GEO, wall_scene(2.0), seed=0)
    pose = Pose.at(0.0, 0.0, ALT)
    clean = r.render(pose)
    dark = r.render(pose, right=Photometry(gain=0.5))
    np.testing.assert_array_equal(dark.left_bgr, clean.left_bgr)
    np.testing.assert_allclose(grey(dark.right_bgr), np.rint(grey(clean.right_bgr) * 0.5), atol=0.0)
    n1 = r.render(pose, left=Photometry(noise_std=4.0), rng=np.random.default_rng(7))
    n2 = r.render(pose, left=Photometry(noise_std=4.0), rng=np.random.default_rng(7))
    np.testing.assert_array_equal(n1.left_bgr, n2.left_bgr)
    resid = grey(n1.left_bgr) - grey(clean.left_bgr)
    assert 3.0 < resid.std() < 5.0
    np.testing.assert_array_equal(n1.right_bgr, clean.right_bgr)
    with pytest.raises(ValueError, match="rng"):
        r.render(pose, left=Photometry(noise_std=1.0))


# ---------------------------------------------------------------- ground truth distances


def test_box_distance_matches_analytic() -> None:
    box = Box((10.0, 5.0, -1.0), (2.0, 4.0, 2.0), yaw_rad=math.pi / 2)  # length now along east
    pts = np.array(
        [
            [10.0, 5.0, -1.0],  # centre: 1 m from the nearest faces (x +-1 after yaw, z +-1)
            [10.0, 5.0 + 1.0 + 3.0, -1.0],  # 3 m east of the east face
            [10.0 + 2.0 + 1.5, 5.0, -1.0],  # 1.5 m north of the north face (half width 2)
            [10.0 + 2.0 + 3.0, 5.0 + 1.0 + 4.0, -1.0],  # off a vertical edge: hypot(3, 4)
            [10.0 + 2.0 + 2.0, 5.0 + 1.0 + 2.0, -2.0 - 1.0],  # off a corner: sqrt(4+4+1)
        ]
    )
    np.testing.assert_allclose(box.signed_distance_m(pts), [-1.0, 3.0, 1.5, 5.0, 3.0], atol=1e-12)


def test_pillar_distance_matches_analytic() -> None:
    p = Pillar((0.0, 0.0, -2.0), radius_m=0.5, height_m=4.0, sides=8)
    r_vertex = 0.5 / math.cos(math.pi / 8)
    pts = np.array(
        [
            [3.0, 0.0, -2.0],  # along a face normal
            [0.0, -2.0, -1.0],  # along another face normal
            [3.0 * math.cos(math.pi / 8), 3.0 * math.sin(math.pi / 8), -2.0],  # towards a vertical edge
            [0.0, 0.0, -2.0],  # on the axis, mid-height: 0.5 to the faces
            [0.0, 0.0, -6.0],  # 2 m above the top
            [0.2, 0.0, -0.1],  # inside, 0.1 above the bottom
            [1.5, 0.0, -5.0],  # above and beside: hypot(1.0, 1.0)
        ]
    )
    expected = [2.5, 1.5, 3.0 - r_vertex, -0.5, 2.0, -0.1, math.sqrt(2.0)]
    np.testing.assert_allclose(p.signed_distance_m(pts), expected, atol=1e-12)


def test_scene_distance_to_obstacles() -> None:
    scene = Scene(
        (Box.on_ground(10.0, 0.0, (2.0, 2.0, 2.0)), Pillar.on_ground(0.0, 5.0, 0.5, 3.0, sides=12)),
        ceiling_altitude_m=4.0,
    )
    assert scene.distance_to_obstacles_m([5.0, 0.0, -1.0]) == pytest.approx(4.0)
    assert scene.distance_to_obstacles_m([0.0, 2.0, -1.0]) == pytest.approx(2.5)
    many = scene.distance_to_obstacles_m(np.array([[5.0, 0.0, -1.0], [0.0, 2.0, -1.0], [0.0, 0.0, -0.5]]))
    assert isinstance(many, np.ndarray) and many.shape == (3,)
    assert scene.distance_to_obstacles_m([0.0, 0.0, -0.5], include_ground=True) == pytest.approx(0.5)
    assert scene.distance_to_obstacles_m([0.0, 0.0, -3.5], include_ground=True) == pytest.approx(0.5)
    assert Scene().distance_to_obstacles_m([0.0, 0.0, -1.0]) == math.inf


def test_invalid_inputs_are_rejected() -> None:
    with pytest.raises(ValueError):
        Box((0, 0, 0), (1.0, 0.0, 1.0))
    with pytest.raises(ValueError):
        Pillar((0, 0, 0), 0.5, 1.0, sides=2)
    with pytest.raises(ValueError):
        Pose((0.0, math.nan, 0.0))
    with pytest.raises(ValueError):
        Scene(ceiling_altitude_m=-1.0)
    with pytest.raises(ValueError):
        Photometry(gain=-1.0)
