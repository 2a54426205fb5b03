"""Sample captures from known rigs, rendered with the project's own renderers: chessboard views of a
generic stereo camera, a flat target at measured distances, a side-by-side frame with its calibration.

What a camera would have captured for the calibration commands and ``companion process``: the tests use
it, and ``tools/gen-samples.py`` writes the small set the repository ships in ``samples/`` (so that the
README's and docs/first-flight.md's commands run in a fresh checkout). Deterministic.
"""


from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.core.geometry import StereoGeometry
from companion.sim.render import Box, Pose, Scene, StereoRenderer
from companion.sim.render.target import TargetCamera, calibration_poses, chessboard_target, right_eye_pose

#: The board the views show: 9x6 inner corners, 40 mm squares.
BOARD = "chessboard:9x6:0.04"


@dataclass(frozen=True)
class Rig:
    """A raw stereo rig (what a calibration should recover)."""

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int]


def generic_rig() -> Rig:
    """A generic USB stereo camera: 640x400 eyes, ~78° HFOV, 6 cm baseline, unequal eyes, lens
    distortion, a slight rotation between them."""
    K1 = np.array([[400.0, 0.0, 321.5], [0.0, 401.0, 197.0], [0.0, 0.0, 1.0]])
    K2 = np.array([[398.0, 0.0, 316.0], [0.0, 398.5, 203.0], [0.0, 0.0, 1.0]])
    D1 = np.array([-0.11, 0.025, 4e-4, -3e-4, 0.0])
    D2 = np.array([-0.10, 0.020, -2e-4, 3e-4, 0.0])
    R = cv2.Rodrigues(np.array([0.008, -0.012, 0.005]))[0]
    T = np.array([-0.06, 0.0008, 0.0012])
    return Rig(K1, D1, K2, D2, R, T, (640, 400))


def write_stereo_views(folder: Path, rig: Rig, n: int = 12, seed: int = 0, layout: str = "sbs") -> Path:
    """``n`` views of the 9x6 chessboard (40 mm) seen by ``rig``, as side-by-side PNGs (``sbs``) or
    ``left/`` and ``right/`` files (``pair``), named ``view_000.png`` ... as ``--live`` saves them.
    Returns ``folder``."""
    target = chessboard_target(9, 6, 0.04, texels_per_square=32)
    w, h = rig.image_size
    left_cam = TargetCamera(rig.K1, rig.D1, rig.image_size, supersample=2)
    right_cam = TargetCamera(rig.K2, rig.D2, rig.image_size, supersample=2)
    poses = calibration_poses(
        target, rig.K1, rig.image_size, n, R=rig.R, T=rig.T, K_right=rig.K2, distance_m=(0.3, 0.6), max_tilt_deg=25.0, max_roll_deg=8.0, seed=seed
    )
    folder.mkdir(parents=True, exist_ok=True)
    for i, (rot, t) in enumerate(poses):
        left = left_cam.render(target, rot, t, blur_px=0.5)
        rr, tr = right_eye_pose(rot, t, rig.R, rig.T)
        right = right_cam.render(target, rr, tr, blur_px=0.5)
        if layout == "sbs":
            cv2.imwrite(str(folder / f"view_{i:03d}.png"), np.concatenate([left, right], axis=1))
        else:
            (folder / "left").mkdir(exist_ok=True)
            (folder / "right").mkdir(exist_ok=True)
            cv2.imwrite(str(folder / "left" / f"view_{i:03d}.png"), left)
            cv2.imwrite(str(folder / "right" / f"view_{i:03d}.png"), right)
    return folder


#: The simulated ZED's rig (the sim camera's: VGA, 90° HFOV, 12 cm): what the LUT captures are rendered with.
LUT_GEOMETRY = StereoGeometry.ideal(672, 376, hfov_deg=90.0, baseline_m=0.12)


def write_lut_captures(folder: Path, distances_m: tuple[float, ...] = (1.0, 1.5, 2.0, 3.0, 4.0), seed: int = 0) -> Path:
    """A flat textured target (a 4 m x 3 m board) square to the camera at each distance, rendered with
    :data:`LUT_GEOMETRY`, as side-by-side PNGs, and ``distances.csv`` beside them. Returns the CSV."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    # One target (its face at 8 m north), the camera stepped back from it.
    wall_m = 8.0
    scene = Scene(obstacles=(Box.on_ground(wall_m + 0.05, 0.0, (0.1, 4.0, 3.0)),), ground=True)
    renderer = StereoRenderer(LUT_GEOMETRY, scene, seed=seed)
    for k, d in enumerate(distances_m):
        frame = renderer.render_side_by_side(Pose.at(wall_m - d, 0.0, 1.5))
        name = f"target_{k:02d}.png"
        cv2.imwrite(str(folder / name), frame)
        rows.append((name, f"{d:g}"))
    path = folder / "distances.csv"
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["file", "true_distance_m"])
        w.writerows(rows)
    return path


def write_rig_lut_captures(
    folder: Path, rig: Rig, distances_m: tuple[float, ...] = (1.0, 1.5, 2.0, 3.0, 4.0), seed: int = 0, ext: str = "png"
) -> Path:
    """A flat target printed with a random multi-scale texture (3 m x 2 m), square to ``rig`` at each
    distance (from the left camera), seen by the rig's raw (distorted, unrectified) eyes, as
    side-by-side PNGs named as ``calibrate lut --live`` saves them, and ``distances.csv``. Returns the CSV."""
    from companion.sim.render.target import PlanarTarget, board_pose
    from companion.sim.render.texture import noise_field

    rng = np.random.default_rng([seed, 0x1A7])
    texture = np.clip(noise_field(rng, 1024) * 45.0 + 128.0, 0, 255).astype(np.uint8)
    target = PlanarTarget(np.ascontiguousarray(texture[:683, :]), 3.0 / 1024)
    left_cam = TargetCamera(rig.K1, rig.D1, rig.image_size, supersample=2)
    right_cam = TargetCamera(rig.K2, rig.D2, rig.image_size, supersample=2)
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, d in enumerate(distances_m):
        rot, t = board_pose(target, d)
        left = left_cam.render(target, rot, t, blur_px=0.5)
        rr, tr = right_eye_pose(rot, t, rig.R, rig.T)
        right = right_cam.render(target, rr, tr, blur_px=0.5)
        name = f"d{k:02d}_{d:g}m_00.{ext}"
        _write_image(folder / name, cv2.cvtColor(np.concatenate([left, right], axis=1), cv2.COLOR_GRAY2BGR))
        rows.append((name, f"{d:g}"))
    path = folder / "distances.csv"
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["file", "true_distance_m"])
        w.writerows(rows)
    return path


#: JPEG quality of the shipped samples (textured captures as PNG weigh up to 1 MB each).
SAMPLE_JPEG_QUALITY = 90


def _write_image(path: Path, image: np.ndarray) -> None:
    params = [cv2.IMWRITE_JPEG_QUALITY, SAMPLE_JPEG_QUALITY] if path.suffix.lower() in (".jpg", ".jpeg") else []
    if not cv2.imwrite(str(path), image, params):
        raise OSError(f"{path}: cannot write the image")


def write_calibration(path: Path, rig: Rig) -> Path:
    """``rig``'s true calibration in the project's format (docs/calibration.md). Returns ``path``."""
    from companion.core.calibration import StereoCalibration
    from companion.core.calibration_files import save_calibration

    calib = StereoCalibration(rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T, rig.image_size, source="samples")
    return save_calibration(calib, path, {"made_by": "the rendered generic rig (companion.sim.render.samples)"})


def write_obstacle_frame(path: Path, rig: Rig, distance_m: float = 1.2, seed: int = 0) -> Path:
    """One side-by-side frame of ``rig``'s raw eyes: a textured board (1.2 m x 0.9 m) ``distance_m``
    ahead of the left camera, in front of a textured wall 6 m away: an obstacle in the centre, clear
    round it. Returns ``path``."""
    from companion.sim.render.target import PlanarTarget, board_pose
    from companion.sim.render.texture import noise_field

    rng = np.random.default_rng([seed, 0xF8A])
    left_cam = TargetCamera(rig.K1, rig.D1, rig.image_size, supersample=2)
    right_cam = TargetCamera(rig.K2, rig.D2, rig.image_size, supersample=2)
    eyes = []
    wall_tex = np.clip(noise_field(rng, 1024) * 45.0 + 128.0, 0, 255).astype(np.uint8)
    wall = PlanarTarget(np.ascontiguousarray(wall_tex[:768, :]), 12.0 / 1024)
    board_tex = np.clip(noise_field(rng, 512) * 50.0 + 110.0, 0, 255).astype(np.uint8)
    board = PlanarTarget(np.ascontiguousarray(board_tex[:384, :]), 1.2 / 512)
    for cam, right in ((left_cam, False), (right_cam, True)):
        images = []
        for target, d in ((wall, 6.0), (board, distance_m)):
            rot, t = board_pose(target, d)
            if right:
                rot, t = right_eye_pose(rot, t, rig.R, rig.T)
            images.append(cam.render(target, rot, t, blur_px=0.5))
        far, near = images
        # the board covers the wall where it is (the renderer draws outside a target as 0)
        eyes.append(np.where(near > 0, near, far).astype(np.uint8))
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_image(path, cv2.cvtColor(np.concatenate(eyes, axis=1), cv2.COLOR_GRAY2BGR))
    return path


def write_samples(folder: Path) -> list[Path]:
    """The repository's sample set (each file small): ``frame.jpg`` and ``frame-calib.yaml`` (one
    side-by-side frame and its rig's calibration), ``calib_views/`` (12 chessboard views, PNG),
    ``lut_captures/`` (a flat target at 1-4 m, JPEG, and ``distances.csv``). Returns the files written."""
    rig = generic_rig()
    folder.mkdir(parents=True, exist_ok=True)
    write_obstacle_frame(folder / "frame.jpg", rig)
    write_calibration(folder / "frame-calib.yaml", rig)
    write_stereo_views(folder / "calib_views", rig)
    write_rig_lut_captures(folder / "lut_captures", rig, ext="jpg")
    return sorted(p for p in folder.rglob("*") if p.is_file())
