"""Flat calibration targets seen through real (distorted, unrectified) cameras.

:class:`~companion.sim.render.renderer.StereoRenderer` draws *rectified* pairs of an ideal rig, which is
what the pipeline sees after rectification. Calibrating a rig needs the step before: each eye with its
own camera matrix and lens distortion, the right eye rotated and shifted by any ``(R, T)``. This module
draws that: a flat target (a printed board: a texture of known size) at a given pose, seen by a camera
``(K, D, image size)``. It is exact up to the texture sampling: every pixel's ray is undistorted with
OpenCV's own model (``cv2.undistortPoints`` iterated to convergence), intersected with the board's
plane, and the texture is sampled there; ``supersample`` rays per pixel side are averaged, so the
board's edges are anti-aliased the way a lens and a sensor would blur them. Deterministic (no noise
unless asked, and then from the given generator).

Frames (OpenCV's): the camera frame is x right, y down, z forward, metres. The target frame has its
origin at the texture's top-left corner, x along the texture's columns, y along its rows, z into the
board; a point ``X_t`` on the board is ``X_c = R_ct @ X_t + t_ct`` in the camera frame. The right eye
of a rig with ``X_r = R @ X_l + T`` sees the board at ``(R @ R_ct, R @ t_ct + T)``
(:func:`right_eye_pose`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = [
    "PlanarTarget",
    "TargetCamera",
    "board_pose",
    "calibration_poses",
    "charuco_target",
    "chessboard_target",
    "right_eye_pose",
]


@dataclass(frozen=True, eq=False)
class PlanarTarget:
    """A flat, textured rectangle: a printed calibration board (or any printed texture).

    Attributes:
        texture: uint8 ``(h, w)`` grey image printed on the board, read-only.
        texel_m: the side of one texture pixel on the board, metres (> 0); the board is
            ``w * texel_m`` by ``h * texel_m``.
        corners_m: float64 ``(N, 3)`` the board's reference points in the target frame (chessboard:
            its inner corners in OpenCV's row-major order; ChArUco: ``board.getChessboardCorners()``),
            metres; the ground truth a detector should find.
        board: the ``cv2.aruco.CharucoBoard`` a ChArUco target was drawn from, else None.
    """

    texture: np.ndarray
    texel_m: float
    corners_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    board: object | None = None

    def __post_init__(self) -> None:
        tex = np.asarray(self.texture)
        if tex.dtype != np.uint8 or tex.ndim != 2 or min(tex.shape) < 2:
            raise ValueError(f"texture must be uint8 (h, w) grey, got {tex.dtype} {tex.shape}")
        if not (self.texel_m > 0 and math.isfinite(self.texel_m)):
            raise ValueError(f"texel_m must be > 0, got {self.texel_m}")
        tex = tex.copy()
        tex.setflags(write=False)
        object.__setattr__(self, "texture", tex)
        corners = np.asarray(self.corners_m, dtype=np.float64).reshape(-1, 3).copy()
        corners.setflags(write=False)
        object.__setattr__(self, "corners_m", corners)

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the board, metres."""
        h, w = self.texture.shape
        return (w * self.texel_m, h * self.texel_m)

    @property
    def centre_m(self) -> np.ndarray:
        """float64 ``(3,)`` the board's centre in the target frame, metres."""
        w, h = self.size_m
        return np.array([0.5 * w, 0.5 * h, 0.0])


def chessboard_target(
    inner_cols: int, inner_rows: int, square_m: float, *, texels_per_square: int = 40, margin_squares: float = 1.0
) -> PlanarTarget:
    """A chessboard with ``inner_cols x inner_rows`` inner corners (OpenCV's pattern size), squares of
    ``square_m`` metres, and a white margin of ``margin_squares`` squares around it.

    The top-left square is black. ``corners_m`` lists the inner corners row by row from the top-left
    one, x along the columns, as ``cv2.findChessboardCorners`` orders them on an upright board.
    """
    if inner_cols < 2 or inner_rows < 2:
        raise ValueError(f"a chessboard needs at least 2x2 inner corners, got {inner_cols}x{inner_rows}")
    n = int(texels_per_square)
    margin = int(round(margin_squares * n))
    cols, rows = inner_cols + 1, inner_rows + 1
    yy, xx = np.mgrid[0 : rows * n, 0 : cols * n]
    squares = ((yy // n + xx // n) % 2).astype(np.uint8) * 255  # (0, 0) black
    texture = np.full((rows * n + 2 * margin, cols * n + 2 * margin), 255, np.uint8)
    texture[margin : margin + rows * n, margin : margin + cols * n] = squares
    texel = square_m / n
    j, i = np.mgrid[0:inner_rows, 0:inner_cols]
    corners = np.stack(
        [(margin + (i.ravel() + 1) * n) * texel, (margin + (j.ravel() + 1) * n) * texel, np.zeros(i.size)], axis=1
    )
    return PlanarTarget(texture, texel, corners)


def charuco_target(
    squares_x: int,
    squares_y: int,
    square_m: float,
    marker_m: float,
    dictionary: str = "DICT_5X5_100",
    *,
    texels_per_square: int = 60,
    margin_squares: float = 0.5,
) -> PlanarTarget:
    """A ChArUco board (``cv2.aruco``) of ``squares_x x squares_y`` squares; ``corners_m`` are its
    chessboard corners by id (``board.getChessboardCorners()``), shifted by the margin."""
    aruco = cv2.aruco
    board = aruco.CharucoBoard(
        (squares_x, squares_y), square_m, marker_m, aruco.getPredefinedDictionary(getattr(aruco, dictionary))
    )
    n = int(texels_per_square)
    margin = int(round(margin_squares * n))
    image = board.generateImage((squares_x * n + 2 * margin, squares_y * n + 2 * margin), marginSize=margin)
    texel = square_m / n
    corners = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3) + [margin * texel, margin * texel, 0.0]
    return PlanarTarget(np.ascontiguousarray(image), texel, corners, board=board)


def board_pose(
    target: PlanarTarget,
    distance_m: float,
    *,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
    offset_m: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """A pose ``(R_ct, t_ct)`` that puts the board's centre ``distance_m`` in front of the camera
    (plus ``offset_m`` right and down), upright and facing it, then turned by yaw (about the board's
    vertical), pitch (about its horizontal) and roll (about the optical axis), degrees.

    Returns:
        ``R_ct`` float64 ``(3, 3)`` and ``t_ct`` float64 ``(3,)`` (metres): ``X_c = R_ct X_t + t_ct``.
    """
    y, p, r = (math.radians(v) for v in (yaw_deg, pitch_deg, roll_deg))
    ry = np.array([[math.cos(y), 0.0, math.sin(y)], [0.0, 1.0, 0.0], [-math.sin(y), 0.0, math.cos(y)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), -math.sin(p)], [0.0, math.sin(p), math.cos(p)]])
    rz = np.array([[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]])
    rot = rz @ rx @ ry
    centre_c = np.array([offset_m[0], offset_m[1], distance_m], dtype=np.float64)
    t = centre_c - rot @ target.centre_m
    return rot, t


def right_eye_pose(
    R_ct: np.ndarray, t_ct: np.ndarray, R: np.ndarray, T: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The board's pose in the right eye of a rig with ``X_r = R X_l + T`` (OpenCV's stereo R, T)."""
    R = np.asarray(R, dtype=np.float64)
    return R @ R_ct, R @ np.asarray(t_ct, dtype=np.float64).reshape(3) + np.asarray(T, dtype=np.float64).reshape(3)


def _undistort(pts: np.ndarray, K: np.ndarray, D: np.ndarray, criteria: tuple) -> np.ndarray:
    """Normalised undistorted coordinates of pixel points, iterated to ``criteria`` (OpenCV 4:
    ``undistortPointsIter``; OpenCV 5: ``undistortPoints`` takes the criteria itself)."""
    iterative = getattr(cv2, "undistortPointsIter", None)
    if iterative is not None:
        return iterative(pts, K, D, None, None, criteria)
    return cv2.undistortPoints(pts, K, D, criteria=criteria)


class TargetCamera:
    """One raw camera (an eye): OpenCV's pinhole model with distortion.

    The undistorted ray of every (sub)pixel is computed once, here; each :meth:`render` is then a
    ray-plane intersection and a texture lookup.

    Args:
        K: float ``(3, 3)`` camera matrix, pixels.
        D: distortion coefficients, as OpenCV takes them (4, 5, 8, 12 or 14).
        image_size: ``(width, height)``, pixels.
        supersample: rays per pixel side (their mean is the pixel), >= 1.
    """

    def __init__(self, K: np.ndarray, D: np.ndarray, image_size: tuple[int, int], supersample: int = 3) -> None:
        self.K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        self.D = np.asarray(D, dtype=np.float64).reshape(-1)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.supersample = int(supersample)
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        w, h = self.image_size
        s = self.supersample
        # Exact rays at every pixel centre, one pixel beyond the image on each side...
        uu, vv = np.meshgrid(np.arange(-1, w + 1, dtype=np.float64), np.arange(-1, h + 1, dtype=np.float64))
        pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-11)
        norm = _undistort(pts, self.K, self.D, criteria).reshape(h + 2, w + 2, 2)
        # ...then the sub-pixel samples between them by linear interpolation (the ray field is smooth):
        # cv2.resize by s samples the source at (i + 0.5) / s - 0.5, the sub-pixel offsets wanted.
        if s > 1:
            norm = cv2.resize(norm, ((w + 2) * s, (h + 2) * s), interpolation=cv2.INTER_LINEAR)[s:-s, s:-s]
        else:
            norm = norm[1:-1, 1:-1]
        self._rays_x = np.ascontiguousarray(norm[..., 0], dtype=np.float32)  # (h*s, w*s), ray = (x, y, 1)
        self._rays_y = np.ascontiguousarray(norm[..., 1], dtype=np.float32)

    def render(
        self,
        target: PlanarTarget,
        R_ct: np.ndarray,
        t_ct: np.ndarray,
        *,
        background: int = 90,
        blur_px: float = 0.0,
        noise_std: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """The camera's grey image of ``target`` at pose ``(R_ct, t_ct)``.

        Args:
            target: the board.
            R_ct, t_ct: the board's pose in this camera (``X_c = R_ct X_t + t_ct``), metres.
            background: grey level where the board is not seen.
            blur_px: Gaussian blur after sampling (optics), pixels (0 = none).
            noise_std: additive Gaussian noise, grey levels (needs ``rng``).

        Returns:
            uint8 ``(H, W)``.
        """
        R_ct = np.asarray(R_ct, dtype=np.float64).reshape(3, 3)
        t_ct = np.asarray(t_ct, dtype=np.float64).reshape(3)
        # In the target frame, the ray lambda*r from the camera centre is R^T (lambda r - t); its
        # z is 0 on the board: lambda = (R^T t)_z / (R^T r)_z.
        rt = R_ct.T
        origin_t = -rt @ t_ct  # the camera centre in the target frame
        f32 = np.float32
        # Ray directions in the target frame: rt @ (x, y, 1), one component at a time (float32).
        def comp(k: int) -> np.ndarray:
            out = self._rays_x * f32(rt[k, 0])
            out += self._rays_y * f32(rt[k, 1])
            out += f32(rt[k, 2])
            return out

        dz = comp(2)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = f32(-origin_t[2]) / dz
        seen = np.isfinite(lam) & (lam > 0)
        inv_texel = 1.0 / target.texel_m
        # Texel centres are at (i + 0.5) * texel_m: texel coordinate = metres / texel_m - 0.5.
        map_x = comp(0)
        map_x *= lam
        map_x += f32(origin_t[0])
        map_x *= f32(inv_texel)
        map_x -= f32(0.5)
        map_y = comp(1)
        map_y *= lam
        map_y += f32(origin_t[1])
        map_y *= f32(inv_texel)
        map_y -= f32(0.5)
        map_x[~seen] = -10.0
        map_y[~seen] = -10.0
        tex = target.texture
        fine = cv2.remap(
            tex.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT, borderValue=float(background),
        )
        # Pixels half inside the board blend with the background: the border counts as background.
        s = self.supersample
        w, h = self.image_size
        img = fine.reshape(h, s, w, s).mean(axis=(1, 3))
        if blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_px)
        if noise_std > 0:
            if rng is None:
                raise ValueError("noise_std > 0 needs an rng (numpy Generator)")
            img = img + rng.standard_normal(img.shape) * noise_std
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def project(self, target: PlanarTarget, R_ct: np.ndarray, t_ct: np.ndarray) -> np.ndarray:
        """Where the board's reference points fall in this camera: float64 ``(N, 2)`` pixels (the
        ground truth for a detector), with OpenCV's ``projectPoints``."""
        rvec, _ = cv2.Rodrigues(np.asarray(R_ct, dtype=np.float64))
        pts, _ = cv2.projectPoints(target.corners_m, rvec, np.asarray(t_ct, dtype=np.float64), self.K, self.D)
        return pts.reshape(-1, 2)


def calibration_poses(
    target: PlanarTarget,
    K: np.ndarray,
    image_size: tuple[int, int],
    n: int,
    *,
    R: np.ndarray | None = None,
    T: np.ndarray | None = None,
    K_right: np.ndarray | None = None,
    distance_m: tuple[float, float] = (0.5, 1.2),
    max_tilt_deg: float = 35.0,
    max_roll_deg: float = 20.0,
    seed: int = 0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` board poses a careful person would show a camera: the board's centre over a 3x3 grid of
    the image first (then anywhere), at distances in ``distance_m``, tilted up to ``max_tilt_deg``,
    rolled up to ``max_roll_deg``, each wholly inside the image (both eyes' when ``R, T`` are given).
    Deterministic in ``seed``.

    Returns:
        ``[(R_ct, t_ct), ...]`` poses in the (left) camera.
    """
    rng = np.random.default_rng([seed, 0xCA1B])
    w, h = image_size
    K = np.asarray(K, dtype=np.float64)
    cams = [(np.eye(3), np.zeros(3), K)]
    if R is not None and T is not None:
        cams.append((np.asarray(R, dtype=np.float64), np.asarray(T, dtype=np.float64).reshape(3), np.asarray(K_right if K_right is not None else K, dtype=np.float64)))
    # What must be inside the image: the corners and the squares around them (a detector needs the
    # outer squares, not the whole white margin), else the whole board.
    if target.corners_m.shape[0] >= 2:
        c = target.corners_m
        square = float(np.linalg.norm(c[1] - c[0]))
        x0, y0 = c[:, :2].min(axis=0) - 1.3 * square
        x1, y1 = c[:, :2].max(axis=0) + 1.3 * square
    else:
        (x0, y0), (x1, y1) = (0.0, 0.0), target.size_m
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
    bw, bh = x1 - x0, y1 - y0
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    tries = attempt = 0
    while len(poses) < n and tries < 200 * n:
        tries += 1
        k = len(poses)
        z = rng.uniform(*distance_m)
        # Where the board's centre can go at this distance (the board wholly inside, upright).
        half_u = 0.5 * bw * K[0, 0] / z + 0.03 * w
        half_v = 0.5 * bh * K[1, 1] / z + 0.03 * h
        lo_u, hi_u = half_u, w - 1 - half_u
        lo_v, hi_v = half_v, h - 1 - half_v
        if lo_u > hi_u or lo_v > hi_v:
            continue  # too near for the board to fit: another distance
        if k < 9:  # the 3x3 grid of the places it can go, first; pulled in while a tilt sticks out
            pull = max(0.0, 1.0 - 0.04 * attempt)
            gx, gy = 0.5 + pull * ((k % 3) / 2.0 - 0.5), 0.5 + pull * ((k // 3) / 2.0 - 0.5)
        else:
            gx, gy = rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0)
        u = lo_u + gx * (hi_u - lo_u) + rng.uniform(-0.05, 0.05) * w
        v = lo_v + gy * (hi_v - lo_v) + rng.uniform(-0.05, 0.05) * h
        off = ((u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z)
        tilt = [rng.uniform(-max_tilt_deg, max_tilt_deg) for _ in range(2)]
        rot, t = board_pose(target, z, yaw_deg=tilt[0], pitch_deg=tilt[1], roll_deg=rng.uniform(-max_roll_deg, max_roll_deg), offset_m=off)
        inside = True
        for rc, tc, kc in cams:
            pc = (rc @ (outline @ rot.T + t).T).T + tc
            if np.any(pc[:, 2] <= 0.05):
                inside = False
                break
            uv = (pc[:, :2] / pc[:, 2:3]) * [kc[0, 0], kc[1, 1]] + [kc[0, 2], kc[1, 2]]
            margin = 0.03 * w
            if uv[:, 0].min() < margin or uv[:, 1].min() < margin or uv[:, 0].max() > w - 1 - margin or uv[:, 1].max() > h - 1 - margin:
                inside = False
                break
        if inside:
            poses.append((rot, t))
            attempt = 0
        else:
            attempt += 1
    if len(poses) < n:
        raise ValueError(f"could not place {n} boards inside the image (placed {len(poses)}); a smaller board or farther")
    return poses
