"""The flat-target renderer (companion/sim/render/target.py): exact rays through OpenCV's distortion
model, boards where their pose puts them, deterministic images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib_data import generic_rig
from companion.core.calibrate import BoardSpec, detect_board
from companion.sim.render.target import (
    PlanarTarget,
    TargetCamera,
    board_pose,
    calibration_poses,
    chessboard_target,
    right_eye_pose,
)


@pytest.fixture(scope="module")
def camera() -> TargetCamera:
    rig = generic_rig()
    return TargetCamera(rig.K1, rig.D1, rig.image_size, supersample=2)


def test_every_ray_projects_back_to_its_sample(camera: TargetCamera) -> None:
    rays = np.stack([camera._rays_x[::37, ::41].ravel(), camera._rays_y[::37, ::41].ravel()], axis=1)
    pts, _ = cv2.projectPoints(np.hstack([rays, np.ones((len(rays), 1))]).astype(np.float64), np.zeros(3), np.zeros(3),
                               camera.K, camera.D)
    rows, cols = np.mgrid[0 : camera._rays_x.shape[0] : 37, 0 : camera._rays_x.shape[1] : 41]
    s = camera.supersample
    expected = np.stack([(cols.ravel() + 0.5) / s - 0.5, (rows.ravel() + 0.5) / s - 0.5], axis=1)
    assert np.abs(pts.reshape(-1, 2) - expected).max() < 2e-3  # pixels (float32 rays, interpolated)


def test_a_rendered_chessboard_is_found_where_its_pose_puts_it(camera: TargetCamera) -> None:
    target = chessboard_target(9, 6, 0.04)
    rot, t = board_pose(target, 0.7, yaw_deg=20.0, pitch_deg=-15.0, roll_deg=5.0, offset_m=(0.05, -0.02))
    image = camera.render(target, rot, t, blur_px=0.5)
    assert np.array_equal(image, camera.render(target, rot, t, blur_px=0.5))  # deterministic
    found = detect_board(image, BoardSpec.parse("chessboard:9x6:0.04"))
    assert found is not None
    truth = camera.project(target, rot, t)
    err = np.linalg.norm(found.image_points - truth, axis=1)
    if err.max() > 1.0:  # the detector may start at the other end (a half turn)
        err = np.linalg.norm(found.image_points[::-1] - truth, axis=1)
    assert err.max() < 0.15 and np.sqrt(np.mean(err**2)) < 0.08


def test_right_eye_pose_and_calibration_poses_stay_in_both_images() -> None:
    rig = generic_rig()
    target = chessboard_target(9, 6, 0.04)
    poses = calibration_poses(target, rig.K1, rig.image_size, 10, R=rig.R, T=rig.T, K_right=rig.K2, seed=1)
    assert len(poses) == 10
    corner = target.corners_m[0]
    for rot, t in poses:
        rr, tr = right_eye_pose(rot, t, rig.R, rig.T)
        # The same board point, through either eye's pose: X_r = R X_l + T.
        np.testing.assert_allclose(rr @ corner + tr, rig.R @ (rot @ corner + t) + rig.T, atol=1e-12)
        for K, D, (r, tt) in ((rig.K1, rig.D1, (rot, t)), (rig.K2, rig.D2, (rr, tr))):
            uv, _ = cv2.projectPoints(target.corners_m, cv2.Rodrigues(r)[0], tt, K, D)
            uv = uv.reshape(-1, 2)
            assert (uv >= 0).all() and (uv[:, 0] < rig.image_size[0]).all() and (uv[:, 1] < rig.image_size[1]).all()


def test_target_arguments_are_checked() -> None:
    with pytest.raises(ValueError, match="uint8"):
        PlanarTarget(np.zeros((4, 4), np.float32), 0.01)
    with pytest.raises(ValueError, match="texel_m"):
        PlanarTarget(np.zeros((4, 4), np.uint8), 0.0)
    with pytest.raises(ValueError, match="2x2 inner corners"):
        chessboard_target(1, 6, 0.04)
