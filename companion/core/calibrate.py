"""Stereo calibration from views of a chessboard or ChArUco board (``companion calibrate stereo``).

Pure: arrays in, a :class:`~companion.core.calibration.StereoCalibration` and a report out; reading
folders and cameras is the caller's business (:mod:`companion.calib`).

The steps:

1. :func:`detect_board` finds the board in one eye's grey image: a chessboard with OpenCV's classic
   detector refined by ``cornerSubPix`` (the sector-based detector as a fallback), a ChArUco board
   with ``cv2.aruco.CharucoDetector``.
2. :func:`pair_views` keeps the views whose board is seen by both eyes, with the same corners in the
   same order (a chessboard's 180° ambiguity is resolved here; ChArUco corners are matched by id).
3. :func:`calibrate_stereo` calibrates each eye (``cv2.calibrateCamera``), then both together
   (``cv2.stereoCalibrate`` from those), and measures what a user needs to trust the result: the RMS
   reprojection error, the vertical (epipolar) error of the corners after rectification, and how much
   of each image the board covered. :class:`Thresholds` says what is refused.

Conventions: OpenCV's (``X_r = R X_l + T``; for a left/right rig ``T[0] ≈ -baseline``), metres
(the board's square size is given in metres, so T comes out in metres), pixels with their centres at
integer coordinates.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final, Literal

import cv2
import numpy as np

from companion.core.calibration import StereoCalibration
from companion.core.geometry import StereoGeometry
from companion.core.rectifier import Rectifier
from companion.errors import CalibrationError, InputError

__all__ = [
    "BoardDetection",
    "BoardSpec",
    "CalibrationReport",
    "StereoView",
    "Thresholds",
    "calibrate_stereo",
    "coverage",
    "detect_board",
    "pair_views",
]

log = logging.getLogger(__name__)

#: The ninths of an image, row-major, for coverage messages.
NINTHS: Final[tuple[str, ...]] = (
    "top-left", "top", "top-right", "left", "centre", "right", "bottom-left", "bottom", "bottom-right",
)
#: A ninth counts as covered when the boards' outlines cover at least this share of it.
_NINTH_MIN_SHARE: Final[float] = 0.05
#: ChArUco views need at least this many corners seen by both eyes.
_MIN_CHARUCO_CORNERS: Final[int] = 8
_CRITERIA: Final[tuple[int, int, float]] = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-7)


# --------------------------------------------------------------------------------------------------
# The board


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board.

    Attributes:
        kind: ``chessboard`` or ``charuco``.
        cols, rows: chessboard: inner corners per row and per column (OpenCV's pattern size; a board
            of 10x7 squares has 9x6); ChArUco: squares across and down.
        square_m: side of one square, metres (measure the print: it sets the baseline's scale).
        marker_m: ChArUco: side of one marker, metres.
        dictionary: ChArUco: the ``cv2.aruco`` dictionary name (e.g. ``DICT_5X5_100``).
    """

    kind: Literal["chessboard", "charuco"]
    cols: int
    rows: int
    square_m: float
    marker_m: float | None = None
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise InputError(f"board kind must be chessboard or charuco, got {self.kind!r}")
        least = 2 if self.kind == "chessboard" else 3
        if self.cols < least or self.rows < least:
            raise InputError(f"a {self.kind} needs at least {least}x{least} ({'inner corners' if least == 2 else 'squares'}), got {self.cols}x{self.rows}")
        if not (math.isfinite(self.square_m) and 0.001 <= self.square_m <= 1.0):
            raise InputError(f"board square size must be 0.001 to 1 m, got {self.square_m} (metres, not millimetres)")
        if self.kind == "charuco":
            if self.marker_m is None or not (0 < self.marker_m < self.square_m):
                raise InputError(f"a ChArUco marker must be smaller than its square ({self.square_m} m), got {self.marker_m}")
            if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, self.dictionary):
                raise InputError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50, DICT_5X5_100)")

    @classmethod
    def parse(cls, text: str) -> BoardSpec:
        """``chessboard:COLSxROWS:SQUARE_M`` (inner corners) or
        ``charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICTIONARY]`` (squares), e.g. ``chessboard:9x6:0.025``.

        Raises:
            InputError: naming what is wrong with the text.
        """
        parts = text.strip().split(":")
        kind = parts[0].lower()
        usage = "chessboard:COLSxROWS:SQUARE_M (inner corners) or charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]"
        if kind not in ("chessboard", "charuco") or len(parts) < 3:
            raise InputError(f"board {text!r}: expected {usage}")
        m = re.fullmatch(r"(\d+)[xX](\d+)", parts[1])
        if m is None:
            raise InputError(f"board {text!r}: size {parts[1]!r} must be COLSxROWS, e.g. 9x6")
        try:
            square = float(parts[2])
            marker = float(parts[3]) if kind == "charuco" and len(parts) > 3 else None
        except ValueError:
            raise InputError(f"board {text!r}: sizes must be numbers in metres") from None
        if kind == "chessboard" and len(parts) != 3:
            raise InputError(f"board {text!r}: expected {usage}")
        if kind == "charuco" and len(parts) not in (4, 5):
            raise InputError(f"board {text!r}: expected {usage}")
        dictionary = parts[4] if kind == "charuco" and len(parts) == 5 else "DICT_5X5_100"
        return cls(kind, int(m.group(1)), int(m.group(2)), square, marker, dictionary)  # type: ignore[arg-type]

    def describe(self) -> str:
        """The :meth:`parse` form."""
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"
        return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    def object_points(self) -> np.ndarray:
        """float32 ``(N, 3)``: chessboard inner corners row by row (x along a row), or the ChArUco
        board's corners by id; metres, on the board's plane z = 0."""
        if self.kind == "chessboard":
            j, i = np.mgrid[0 : self.rows, 0 : self.cols]
            return np.stack([i.ravel() * self.square_m, j.ravel() * self.square_m, np.zeros(i.size)], axis=1).astype(np.float32)
        return np.asarray(self.charuco_board().getChessboardCorners(), dtype=np.float32).reshape(-1, 3)

    def charuco_board(self) -> object:
        """The ``cv2.aruco.CharucoBoard`` (ChArUco only)."""
        aruco = cv2.aruco
        dictionary = aruco.getPredefinedDictionary(getattr(aruco, self.dictionary))
        return aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)


@dataclass(frozen=True)
class BoardDetection:
    """The board in one image.

    Attributes:
        image_points: float32 ``(N, 2)`` pixels.
        object_points: float32 ``(N, 3)`` the same corners on the board, metres.
        ids: ChArUco corner ids int32 ``(N,)``; for a chessboard ``arange(N)``.
    """

    image_points: np.ndarray
    object_points: np.ndarray
    ids: np.ndarray


def _subpix_window(points: np.ndarray, cols: int) -> int:
    """A cornerSubPix half-window a bit under half the smallest corner spacing along a row (2..11 px)."""
    rows = points.reshape(-1, cols, 2)
    spacing = float(np.linalg.norm(np.diff(rows, axis=1), axis=2).min())
    return int(max(2, min(11, math.floor(0.4 * spacing))))


def detect_board(grey: np.ndarray, board: BoardSpec) -> BoardDetection | None:
    """Find ``board`` in one eye's image.

    Args:
        grey: uint8 ``(H, W)`` (a BGR image is converted).
        board: what to look for.

    Returns:
        The detection, or None when the whole chessboard (or at least 8 ChArUco corners) is not seen.
    """
    if grey.ndim == 3:
        grey = cv2.cvtColor(grey, cv2.COLOR_BGR2GRAY)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
    if board.kind == "chessboard":
        size = (board.cols, board.rows)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
        found, corners = cv2.findChessboardCorners(grey, size, flags=flags)
        if found:
            win = _subpix_window(corners, board.cols)
            corners = cv2.cornerSubPix(grey, corners, (win, win), (-1, -1), criteria)
        else:
            # The sector-based detector copes with blur and uneven light; it is slower, so second.
            found, corners = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found or corners is None:
            return None
        pts = corners.reshape(-1, 2).astype(np.float32)
        n = pts.shape[0]
        return BoardDetection(pts, board.object_points(), np.arange(n, dtype=np.int32))
    detector = cv2.aruco.CharucoDetector(board.charuco_board())
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) < _MIN_CHARUCO_CORNERS:
        return None
    corners = cv2.cornerSubPix(grey, corners.astype(np.float32), (5, 5), (-1, -1), criteria)
    ids = ids.reshape(-1).astype(np.int32)
    return BoardDetection(corners.reshape(-1, 2), board.object_points()[ids], ids)


@dataclass(frozen=True)
class StereoView:
    """One view of the board seen by both eyes: the same corners, in the same order.

    Attributes:
        name: where it came from (a file name), for messages.
        object_points: float32 ``(N, 3)`` metres.
        left, right: float32 ``(N, 2)`` pixels in each eye.
    """

    name: str
    object_points: np.ndarray
    left: np.ndarray
    right: np.ndarray


def pair_views(name: str, left: BoardDetection | None, right: BoardDetection | None) -> StereoView | str:
    """The view both eyes agree on, or one line saying why there is none.

    A chessboard's corner order is only defined up to a half turn (the detectors may start at either
    end); the right eye's order is reversed when it runs against the left's. ChArUco corners are
    matched by id.
    """
    if left is None and right is None:
        return f"{name}: no board in either eye"
    if left is None:
        return f"{name}: no board in the left eye"
    if right is None:
        return f"{name}: no board in the right eye"
    if left.ids.shape == right.ids.shape and np.array_equal(left.ids, np.arange(left.ids.size)) and np.array_equal(
        right.ids, np.arange(right.ids.size)
    ):
        lp, rp = left.image_points, right.image_points
        if float(np.dot(lp[-1] - lp[0], rp[-1] - rp[0])) < 0:
            rp = rp[::-1].copy()
        return StereoView(name, left.object_points, lp, rp)
    common, li, ri = np.intersect1d(left.ids, right.ids, return_indices=True)
    if common.size < _MIN_CHARUCO_CORNERS:
        return f"{name}: only {common.size} board corners seen by both eyes (at least {_MIN_CHARUCO_CORNERS} needed)"
    return StereoView(name, left.object_points[li], left.image_points[li], right.image_points[ri])


# --------------------------------------------------------------------------------------------------
# Coverage


def coverage(points_per_view: Sequence[np.ndarray], image_size: tuple[int, int]) -> tuple[float, tuple[str, ...]]:
    """How much of an image the board covered, over all views.

    Args:
        points_per_view: float ``(N, 2)`` detected corners of each view, pixels.
        image_size: ``(width, height)``, pixels.

    Returns:
        ``(share, uncovered)``: the share of the image inside the union of the corners' outlines
        (convex hulls), in [0, 1]; and the ninths of the image (``top-left`` ...) that no outline
        covers by at least 5 %.
    """
    w, h = image_size
    scale = 4  # a quarter-resolution mask is plenty for a share
    mw, mh = max(1, -(-w // scale)), max(1, -(-h // scale))
    mask = np.zeros((mh, mw), np.uint8)
    for pts in points_per_view:
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if p.shape[0] < 3:
            continue
        hull = cv2.convexHull(np.round(p / scale * 16).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1, cv2.LINE_8, 4)
    share = float(mask.mean())
    uncovered = []
    for k, name in enumerate(NINTHS):
        r, c = divmod(k, 3)
        cell = mask[r * mh // 3 : (r + 1) * mh // 3, c * mw // 3 : (c + 1) * mw // 3]
        if cell.size == 0 or float(cell.mean()) < _NINTH_MIN_SHARE:
            uncovered.append(name)
    return share, tuple(uncovered)


# --------------------------------------------------------------------------------------------------
# Calibration


@dataclass(frozen=True)
class Thresholds:
    """What :func:`calibrate_stereo` refuses.

    Attributes:
        min_views: fewest views seen by both eyes.
        min_coverage: smallest share of each image the board must have covered over all views, and
            every ninth of it must be touched (distortion is extrapolated where the board never was).
        max_rms_px: largest RMS reprojection error (both eyes, all views), pixels.
        max_epipolar_px: largest RMS vertical error between the eyes after rectification, pixels (block
            matching searches along rows; a pixel off loses matches).
    """

    min_views: int = 10
    min_coverage: float = 0.3
    max_rms_px: float = 1.0
    max_epipolar_px: float = 0.5


@dataclass(frozen=True)
class CalibrationReport:
    """The result of :func:`calibrate_stereo` and the figures that say whether to trust it.

    Attributes:
        calibration: the stereo calibration (OpenCV's conventions, metres).
        geometry: the rectified rig it gives (focal, principal point, baseline).
        views: names of the views used.
        rms_px: RMS reprojection error of the stereo calibration, both eyes, pixels.
        rms_left_px, rms_right_px: each eye's own calibration's RMS error, pixels.
        view_rms_px: float64 ``(n_views, 2)`` per view and eye, pixels.
        epipolar_rms_px, epipolar_max_px: vertical distance between the two eyes' images of the same
            corner after rectification, RMS and largest, pixels.
        coverage_left, coverage_right: share of each image covered by the board, [0, 1].
        uncovered_left, uncovered_right: ninths of each image the board never touched.
        problems: why the calibration is refused (empty: accepted), one line each.
    """

    calibration: StereoCalibration
    geometry: StereoGeometry
    views: tuple[str, ...]
    rms_px: float
    rms_left_px: float
    rms_right_px: float
    view_rms_px: np.ndarray
    epipolar_rms_px: float
    epipolar_max_px: float
    coverage_left: float
    coverage_right: float
    uncovered_left: tuple[str, ...] = ()
    uncovered_right: tuple[str, ...] = ()
    problems: tuple[str, ...] = field(default=())

    @property
    def accepted(self) -> bool:
        return not self.problems

    def worst_views(self, n: int = 3) -> list[tuple[str, float]]:
        """The ``n`` views with the largest error (the larger eye's), pixels: the ones to retake."""
        worst = self.view_rms_px.max(axis=1)
        order = np.argsort(-worst)[:n]
        return [(self.views[i], float(worst[i])) for i in order]


def _coverage_problems(eye: str, share: float, uncovered: tuple[str, ...], thr: Thresholds) -> list[str]:
    out = []
    if share < thr.min_coverage:
        out.append(
            f"poor coverage: the board covered {share:.0%} of the {eye} image (at least {thr.min_coverage:.0%}); "
            "move it nearer the edges and corners"
        )
    if uncovered:
        out.append(f"poor coverage: the board never reached the {', '.join(uncovered)} of the {eye} image")
    return out


def _epipolar_errors(c: StereoCalibration, rect: Rectifier, views: Sequence[StereoView]) -> np.ndarray:
    """Rectified y(left) - y(right) of every corner, pixels."""
    diffs = []
    for v in views:
        yl = cv2.undistortPoints(v.left.reshape(-1, 1, 2).astype(np.float64), c.K1, c.D1, R=rect.R1, P=rect.P1)
        yr = cv2.undistortPoints(v.right.reshape(-1, 1, 2).astype(np.float64), c.K2, c.D2, R=rect.R2, P=rect.P2)
        diffs.append(yl.reshape(-1, 2)[:, 1] - yr.reshape(-1, 2)[:, 1])
    return np.concatenate(diffs) if diffs else np.zeros(0)


def _view_rms(
    obj: Sequence[np.ndarray], img: Sequence[np.ndarray], rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray],
    K: np.ndarray, D: np.ndarray,
) -> np.ndarray:
    out = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        p, _ = cv2.projectPoints(o, r, t, K, D)
        out.append(math.sqrt(float(np.mean(np.sum((p.reshape(-1, 2) - i.reshape(-1, 2)) ** 2, axis=1)))))
    return np.asarray(out)


def calibrate_stereo(
    views: Sequence[StereoView],
    image_size: tuple[int, int],
    thresholds: Thresholds = Thresholds(),
    *,
    fix_k3: bool = False,
    rectify_alpha: float = 0.0,
    source: str = "calibrate stereo",
) -> CalibrationReport:
    """Calibrate a stereo rig from views of a board and judge the result.

    Args:
        views: the views seen by both eyes (:func:`pair_views`).
        image_size: one eye's image size ``(width, height)``, pixels (all views share it).
        thresholds: what is refused (the report's ``problems``).
        fix_k3: keep the third radial coefficient at 0 (few views, or a lens with little distortion).
        rectify_alpha: the rectification's free scaling, for the report's geometry (as
            ``calibration.rectify_alpha``).
        source: names the result in messages.

    Returns:
        The report; its ``problems`` list what the thresholds refuse.

    Raises:
        CalibrationError: fewer views than ``thresholds.min_views`` (nothing is calibrated), or a
            rig whose right eye is not to the right of the left (eyes swapped).
    """
    n = len(views)
    if n < thresholds.min_views:
        raise CalibrationError(
            f"too few views: the board was seen by both eyes in {n} view(s); at least {thresholds.min_views} are "
            "needed (hold the whole board in both eyes, at different places, distances and tilts)",
            views=n,
        )
    w, h = int(image_size[0]), int(image_size[1])
    obj = [v.object_points.reshape(-1, 1, 3).astype(np.float32) for v in views]
    left = [v.left.reshape(-1, 1, 2).astype(np.float32) for v in views]
    right = [v.right.reshape(-1, 1, 2).astype(np.float32) for v in views]
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms_l, K1, D1, rv_l, tv_l = cv2.calibrateCamera(obj, left, (w, h), None, None, flags=flags, criteria=_CRITERIA)
    rms_r, K2, D2, rv_r, tv_r = cv2.calibrateCamera(obj, right, (w, h), None, None, flags=flags, criteria=_CRITERIA)
    out = cv2.stereoCalibrate(
        obj, left, right, K1, D1, K2, D2, (w, h),
        flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags, criteria=_CRITERIA,
    )
    rms, K1, D1, K2, D2, R, T = out[:7]
    calib = StereoCalibration(
        K1=K1, D1=D1.reshape(-1), K2=K2, D2=D2.reshape(-1), R=R, T=np.asarray(T).reshape(3),
        image_size=(w, h), source=source,
    )
    if calib.T[0] > 0:
        raise CalibrationError(
            f"{source}: the camera called 'right' is {calib.T[0]:.3f} m to the LEFT of the one called 'left' "
            "(T[0] > 0): the eyes are swapped; swap them (--swap-eyes) and calibrate again",
            T=calib.T.tolist(),
        )
    rect = Rectifier(calib, alpha=rectify_alpha)
    epi = _epipolar_errors(calib, rect, views)
    # Per view and eye: the left eye's board poses from its own calibration, the right's through R, T.
    view_rms = np.zeros((n, 2))
    for k in range(n):
        ok, rvec, tvec = cv2.solvePnP(obj[k], left[k], K1, D1)
        if not ok:
            rvec, tvec = rv_l[k], tv_l[k]
        rl = cv2.Rodrigues(rvec)[0]
        rr, tr = R @ rl, R @ tvec.reshape(3) + calib.T
        view_rms[k, 0] = _view_rms([obj[k]], [left[k]], [rvec], [tvec], K1, D1)[0]
        view_rms[k, 1] = _view_rms([obj[k]], [right[k]], [cv2.Rodrigues(rr)[0]], [tr], K2, D2)[0]
    cov_l, unc_l = coverage([v.left for v in views], (w, h))
    cov_r, unc_r = coverage([v.right for v in views], (w, h))
    epi_rms = math.sqrt(float(np.mean(epi**2))) if epi.size else float("nan")
    problems: list[str] = []
    problems += _coverage_problems("left", cov_l, unc_l, thresholds)
    problems += _coverage_problems("right", cov_r, unc_r, thresholds)
    if not rms <= thresholds.max_rms_px:
        problems.append(
            f"high error: RMS reprojection error {rms:.2f} px (at most {thresholds.max_rms_px:g}); "
            "retake the worst views, keep the board flat and the images sharp"
        )
    if not epi_rms <= thresholds.max_epipolar_px:
        problems.append(
            f"high error: after rectification the eyes disagree by {epi_rms:.2f} px vertically (RMS; at most "
            f"{thresholds.max_epipolar_px:g}); are the two images of each view taken at the same time?"
        )
    report = CalibrationReport(
        calibration=calib,
        geometry=rect.geometry,
        views=tuple(v.name for v in views),
        rms_px=float(rms),
        rms_left_px=float(rms_l),
        rms_right_px=float(rms_r),
        view_rms_px=view_rms,
        epipolar_rms_px=epi_rms,
        epipolar_max_px=float(np.abs(epi).max()) if epi.size else float("nan"),
        coverage_left=cov_l,
        coverage_right=cov_r,
        uncovered_left=unc_l,
        uncovered_right=unc_r,
        problems=tuple(problems),
    )
    log.debug("stereo calibration from %d views: RMS %.3f px, epipolar %.3f px", n, rms, epi_rms)
    return report
