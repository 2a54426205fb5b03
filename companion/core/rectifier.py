"""The rectifier: raw eye images of one calibrated rig made row-aligned, as the matchers need them.

:class:`Rectifier` runs ``cv2.stereoRectify`` and ``cv2.initUndistortRectifyMap`` once and then
remaps every frame into preallocated buffers; :class:`IdentityRectifier` stands in for frames that
are already rectified (the simulator). :func:`make_rectifier` picks one from the config.
:func:`remap_linear_reference` states the remap's exact arithmetic, which the GPU kernel reproduces.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from companion.config.core import CalibrationConfig
from companion.core.calibration import StereoCalibration, fmt_size, readonly
from companion.core.calibration_files import load_calibration
from companion.core.geometry import StereoGeometry
from companion.errors import CalibrationError, FrameError

__all__ = [
    "AnyRectifier",
    "IdentityRectifier",
    "Rectifier",
    "make_rectifier",
    "remap_linear_reference",
]

log = logging.getLogger(__name__)


def _check_eye(name: str, image: np.ndarray, size: tuple[int, int]) -> None:
    w, h = size
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.shape[:2] != (h, w):
        got = f"{image.shape[1]}x{image.shape[0]}" if isinstance(image, np.ndarray) and image.ndim >= 2 else repr(
            getattr(image, "shape", type(image).__name__)
        )
        raise FrameError(f"{name} image is {got} but the rectifier was built for {w}x{h}")


def _check_out(name: str, out: np.ndarray, src: np.ndarray) -> None:
    if out.shape != src.shape or out.dtype != src.dtype:
        raise FrameError(
            f"{name} output buffer must be {src.dtype} {tuple(src.shape)}, got {out.dtype} {tuple(out.shape)}"
        )


@dataclass(frozen=True, eq=False)
class Rectifier:
    """Rectification of one calibrated rig at one resolution; maps are computed once, at construction.

    Built with ``cv2.stereoRectify(..., flags=CALIB_ZERO_DISPARITY, alpha=alpha)`` (output size = input
    size) and ``cv2.initUndistortRectifyMap(..., CV_32FC1)`` (for a ``fisheye`` calibration their
    ``cv2.fisheye`` twins, with ``alpha`` clipped to [0, 1] as the balance and the whole image as the valid
    rectangle). Each rectified pixel ``(u, v)`` of the
    left eye takes the raw left image sampled at ``(map_left_x[v, u], map_left_y[v, u])`` with
    bilinear interpolation and a constant 0 border (likewise for the right eye);
    :func:`remap_linear_reference` states the exact arithmetic, which a GPU kernel can reproduce.

    Attributes:
        calibration: the raw calibration.
        alpha: stereoRectify free scaling (0 valid pixels only, 1 all source pixels, -1 OpenCV's choice).
        geometry: the rectified rig: focal ``P1[0,0]`` px, principal point ``(P1[0,2], P1[1,2])`` px,
            baseline ``-P2[0,3] / P2[0,0]`` in metres.
        R1, R2: float64 ``(3, 3)`` rectifying rotations; P1, P2: float64 ``(3, 4)`` projections; Q:
            float64 ``(4, 4)`` disparity-to-depth matrix.
        map_left_x, map_left_y, map_right_x, map_right_y: float32 ``(H, W)`` read-only maps, raw
            pixel coordinates for each rectified pixel.
        valid_roi_left, valid_roi_right: ``(x, y, w, h)`` of the all-valid rectified region, px.

    Raises:
        CalibrationError: the rig is not left/right (vertical rig, or the "right" camera is on the
            left, i.e. T[0] > 0), which would give negative disparities.
    """

    calibration: StereoCalibration
    alpha: float = 0.0
    geometry: StereoGeometry = field(init=False)
    R1: np.ndarray = field(init=False, repr=False)
    R2: np.ndarray = field(init=False, repr=False)
    P1: np.ndarray = field(init=False, repr=False)
    P2: np.ndarray = field(init=False, repr=False)
    Q: np.ndarray = field(init=False, repr=False)
    map_left_x: np.ndarray = field(init=False, repr=False)
    map_left_y: np.ndarray = field(init=False, repr=False)
    map_right_x: np.ndarray = field(init=False, repr=False)
    map_right_y: np.ndarray = field(init=False, repr=False)
    valid_roi_left: tuple[int, int, int, int] = field(init=False)
    valid_roi_right: tuple[int, int, int, int] = field(init=False)

    is_identity = False

    def __post_init__(self) -> None:
        c = self.calibration
        size = c.image_size
        if c.model == "fisheye":
            # cv2.fisheye has no valid-pixel rectangle; its balance plays alpha's part (0: no black
            # border, 1: every source pixel), and OpenCV's own choice (-1) is taken as 0.
            R1, R2, P1, P2, Q = cv2.fisheye.stereoRectify(
                c.K1,
                c.D1.reshape(4, 1),
                c.K2,
                c.D2.reshape(4, 1),
                size,
                c.R,
                c.T.reshape(3, 1),
                cv2.CALIB_ZERO_DISPARITY,
                newImageSize=size,
                balance=min(1.0, max(0.0, float(self.alpha))),
                fov_scale=1.0,
            )
            roi1 = roi2 = (0, 0, size[0], size[1])
        else:
            R1, R2, P1, P2, Q, roi1, roi2 = cv2.stereoRectify(
                c.K1,
                c.D1,
                c.K2,
                c.D2,
                size,
                c.R,
                c.T.reshape(3, 1),  # OpenCV 5 wants a column vector here
                flags=cv2.CALIB_ZERO_DISPARITY,
                alpha=float(self.alpha),
                newImageSize=size,
            )
        f = float(P1[0, 0])
        tx, ty = float(P2[0, 3]), float(P2[1, 3])
        if abs(ty) > abs(tx):
            raise CalibrationError(
                f"calibration {c.source}: T = {c.T.tolist()} m describes a vertical rig; a left/right pair is needed",
                source=c.source,
            )
        if not tx < 0:
            raise CalibrationError(
                f"calibration {c.source}: T = {c.T.tolist()} m puts the right camera to the LEFT of the left one "
                "(disparities would be negative); OpenCV's T[0] is -baseline for a left/right rig; "
                "are the eyes swapped or the sign of T flipped?",
                source=c.source,
            )
        if c.model == "fisheye":
            mlx, mly = cv2.fisheye.initUndistortRectifyMap(c.K1, c.D1.reshape(4, 1), R1, P1, size, cv2.CV_32FC1)
            mrx, mry = cv2.fisheye.initUndistortRectifyMap(c.K2, c.D2.reshape(4, 1), R2, P2, size, cv2.CV_32FC1)
        else:
            mlx, mly = cv2.initUndistortRectifyMap(c.K1, c.D1, R1, P1, size, cv2.CV_32FC1)
            mrx, mry = cv2.initUndistortRectifyMap(c.K2, c.D2, R2, P2, size, cv2.CV_32FC1)
        geometry = StereoGeometry(
            width_px=size[0],
            height_px=size[1],
            focal_px=f,
            cx_px=float(P1[0, 2]),
            cy_px=float(P1[1, 2]),
            baseline_m=abs(tx / f),
        )
        values: dict[str, Any] = {
            "geometry": geometry,
            "R1": readonly(R1),
            "R2": readonly(R2),
            "P1": readonly(P1),
            "P2": readonly(P2),
            "Q": readonly(Q),
            "map_left_x": readonly(mlx),
            "map_left_y": readonly(mly),
            "map_right_x": readonly(mrx),
            "map_right_y": readonly(mry),
            "valid_roi_left": tuple(int(v) for v in roi1),
            "valid_roi_right": tuple(int(v) for v in roi2),
        }
        for name, value in values.items():
            object.__setattr__(self, name, value)
        log.debug(
            "rectifier for %s at %s: f=%.2f px, c=(%.2f, %.2f) px, B=%.4f m",
            c.source,
            fmt_size(size),
            geometry.focal_px,
            geometry.cx_px,
            geometry.cy_px,
            geometry.baseline_m,
        )

    def rectify(
        self,
        left_grey: np.ndarray,
        right_grey: np.ndarray,
        out_left: np.ndarray | None = None,
        out_right: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rectify a raw pair (``cv2.remap``, INTER_LINEAR, constant 0 border).

        Args:
            left_grey, right_grey: raw eye images, uint8 ``(H, W)`` (any channels work), may be views.
            out_left, out_right: optional preallocated outputs of the same shape and dtype; given
                both, the call allocates nothing.

        Returns:
            ``(left, right)`` rectified images (``out_left``/``out_right`` when given).

        Raises:
            FrameError: an image is not the calibration's size, or an output buffer does not match.
        """
        size = self.calibration.image_size
        _check_eye("left", left_grey, size)
        _check_eye("right", right_grey, size)
        left = self._remap(left_grey, self.map_left_x, self.map_left_y, out_left, "left")
        right = self._remap(right_grey, self.map_right_x, self.map_right_y, out_right, "right")
        return left, right

    @staticmethod
    def _remap(
        src: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, out: np.ndarray | None, name: str
    ) -> np.ndarray:
        if out is not None:
            _check_out(name, out, src)
        result = cv2.remap(
            src, map_x, map_y, cv2.INTER_LINEAR, dst=out, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        if out is not None and result is not out:
            np.copyto(out, result)  # cv2 reallocated (e.g. a strided out); keep the contract
            return out
        return result


@dataclass(frozen=True, eq=False)
class IdentityRectifier:
    """Stand-in for frames that are already rectified (the simulator; no calibration file).

    ``rectify`` returns its inputs unchanged (the ``out_*`` buffers are ignored; always use the
    returned arrays); the maps are None.

    Attributes:
        geometry: the rectified rig the frames come from.
    """

    geometry: StereoGeometry
    calibration: None = None
    map_left_x: None = None
    map_left_y: None = None
    map_right_x: None = None
    map_right_y: None = None

    is_identity = True

    def rectify(
        self,
        left_grey: np.ndarray,
        right_grey: np.ndarray,
        out_left: np.ndarray | None = None,
        out_right: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(left_grey, right_grey)`` unchanged after checking their size against the geometry.

        Raises:
            FrameError: an image is not ``geometry.width_px x geometry.height_px``.
        """
        size = (self.geometry.width_px, self.geometry.height_px)
        _check_eye("left", left_grey, size)
        _check_eye("right", right_grey, size)
        return left_grey, right_grey


AnyRectifier = Rectifier | IdentityRectifier


def make_rectifier(cfg: CalibrationConfig, width_px: int, height_px: int) -> AnyRectifier:
    """Build the rectifier for frames of one eye size ``width_px x height_px``.

    ``cfg.file`` set: load it (:func:`load_calibration`) and build a :class:`Rectifier` with
    ``cfg.rectify_alpha``. Unset: an :class:`IdentityRectifier` over
    ``StereoGeometry.ideal(width_px, height_px, cfg.ideal_hfov_deg, cfg.ideal_baseline_m)``.

    Raises:
        CalibrationError: the file cannot be loaded or does not fit the frames.
    """
    if cfg.file is None:
        return IdentityRectifier(
            StereoGeometry.ideal(width_px, height_px, cfg.ideal_hfov_deg, cfg.ideal_baseline_m)
        )
    calib = load_calibration(cfg.file, (width_px, height_px))
    return Rectifier(calib, alpha=cfg.rectify_alpha)


# --------------------------------------------------------------------------------------------------
# Reference remap (the arithmetic a GPU kernel must reproduce)


def remap_linear_reference(src: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """NumPy statement of ``cv2.remap(src, map_x, map_y, INTER_LINEAR, BORDER_CONSTANT, 0)`` for uint8.

    Slow; for tests and as the specification of a GPU kernel. Per output pixel, in float32::

        x0 = floor(mx); y0 = floor(my); a = mx - x0; b = my - y0      # exact in float32
        p.. = src[y0 + j, x0 + i] (0 outside the image)
        top = fma(a, p01 - p00, p00); bot = fma(a, p11 - p10, p10)    # single-rounding FMA
        out = clamp(round_half_even(fma(b, bot - top, top)), 0, 255)

    This is OpenCV 5.x's float SIMD path; it was checked bit-exact against cv2.remap 5.0.0 on
    random images and maps (older OpenCV quantises the map to 1/32 px in fixed point instead). A
    float32 product of an integer-valued difference (|d| <= 255) and a fraction is exact in
    float64, so float64 multiply-add then rounding to float32 emulates the FMA here.

    Args:
        src: uint8 ``(H, W)``.
        map_x, map_y: float32 ``(h, w)`` source coordinates, pixels.

    Returns:
        uint8 ``(h, w)``.
    """
    f32, f64 = np.float32, np.float64
    h, w = src.shape
    mx = np.asarray(map_x, dtype=f32)
    my = np.asarray(map_y, dtype=f32)
    x0f = np.floor(mx)
    y0f = np.floor(my)
    a = (mx - x0f).astype(f32)
    b = (my - y0f).astype(f32)
    x0 = x0f.astype(np.int64)
    y0 = y0f.astype(np.int64)

    def px(y: np.ndarray, x: np.ndarray) -> np.ndarray:
        inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
        v = src[np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)].astype(f32)
        return np.where(inside, v, f32(0)).astype(f32)

    def fma(m: np.ndarray, d: np.ndarray, c: np.ndarray) -> np.ndarray:
        return (m.astype(f64) * d.astype(f64) + c.astype(f64)).astype(f32)

    p00, p01 = px(y0, x0), px(y0, x0 + 1)
    p10, p11 = px(y0 + 1, x0), px(y0 + 1, x0 + 1)
    top = fma(a, (p01 - p00).astype(f32), p00)
    bot = fma(a, (p11 - p10).astype(f32), p10)
    s = fma(b, (bot - top).astype(f32), top)
    return np.clip(np.rint(s), 0, 255).astype(np.uint8)
