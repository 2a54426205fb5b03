"""The ZED factory calibration file ``SN<serial>.conf``: read into a :class:`StereoCalibration` for one
resolution (INI, millimetres, one section per resolution), in OpenCV's convention.
"""

from __future__ import annotations

import configparser
import math
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Final

import cv2
import numpy as np

from companion.core.calibration import StereoCalibration, fmt_size
from companion.errors import CalibrationError

__all__ = [
    "ZED_RESOLUTIONS",
    "load_zed_conf",
]

#: ZED section suffix -> one-eye image size (width, height) in pixels.
ZED_RESOLUTIONS: Final[Mapping[str, tuple[int, int]]] = MappingProxyType(
    {"2K": (2208, 1242), "FHD": (1920, 1080), "HD": (1280, 720), "VGA": (672, 376)}
)


# Conventions, from Stereolabs' own code:
# * stereolabs/zed-opencv-calibration, stereo_calibration/src/opencv_calibration.cpp
#   (StereoCalib::saveCalibZED) WRITES an SN*.conf from cv::stereoCalibrate's (R, T):
#   "Baseline = -T[0]", "TY = T[1]", "TZ = T[2]", "RX_<res> = Rv[0]", "CV_<res> = Rv[1]",
#   "RZ_<res> = Rv[2]" with Rv = cv::Rodrigues(R); stereo_calibration/include/opencv_calibration.hpp
#   (setFrom) notes "the zed configuration file store the absolute value of the Tx part".
# * stereolabs/zed-opencv-native, python/zed_opencv_native.py (init_calibration) READS it back the
#   same way: T = [-Baseline, TY, TZ], R = cv2.Rodrigues([RX_res, CV_res, RZ_res]), then
#   stereoRectify(CALIB_ZERO_DISPARITY) and initUndistortRectifyMap(CV_32FC1).
# So: T_opencv = (-Baseline, TY, TZ) / 1000 m, R = Rodrigues((RX, CV, RZ)) (tilt, convergence, roll),
# used as is (not transposed). Caveats: the C++ samples (zed-open-capture examples/include/
# calibration.hpp, zed-opencv-native cpp/include/calibration.hpp) pass +Baseline, which makes
# P2[0,3] > 0 and negative disparities; RTAB-Map's CameraStereoZedOC.cpp negates all of T
# ("inverted to get positive baseline"), which flips TY/TZ against the writer above. Those readers
# look TY/TZ up as TY_<res>/TZ_<res> while the writer (and factory files) use plain TY/TZ; both
# spellings are accepted here, the per-resolution one first.


def _zed_resolution(image_size: tuple[int, int], path: Path) -> str:
    for name, size in ZED_RESOLUTIONS.items():
        if tuple(image_size) == size:
            return name
    known = ", ".join(f"{n} {fmt_size(s)}" for n, s in ZED_RESOLUTIONS.items())
    raise CalibrationError(
        f"calibration {path} has no section for {fmt_size(image_size)}; ZED resolutions are {known} (one eye)",
        path=str(path),
        image_size=tuple(image_size),
    )


def _read_ini(path: Path) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(interpolation=None, strict=False, inline_comment_prefixes=("#", ";"))
    try:
        with path.open(encoding="utf-8-sig") as f:
            parser.read_file(f, source=str(path))
    except IsADirectoryError:
        raise CalibrationError(f"cannot read calibration file {path}: it is a directory", path=str(path)) from None
    except OSError as exc:
        raise CalibrationError(
            f"cannot read calibration file {path}: {exc.strerror or exc}", path=str(path)
        ) from None
    except UnicodeDecodeError:
        raise CalibrationError(
            f"calibration file {path} is not a valid ZED .conf: it is not text (binary data)", path=str(path)
        ) from None
    except configparser.MissingSectionHeaderError as exc:
        raise CalibrationError(
            f"calibration file {path} is not a valid ZED .conf: line {exc.lineno} comes before any [SECTION] "
            f"header ({exc.line.strip()[:40]!r})",
            path=str(path),
        ) from None
    except configparser.ParsingError as exc:
        lines = ", ".join(str(n) for n, _ in exc.errors[:3]) if getattr(exc, "errors", None) else "?"
        raise CalibrationError(
            f"calibration file {path} is not a valid ZED .conf: line(s) {lines} are not 'key = value'",
            path=str(path),
        ) from None
    except configparser.Error as exc:
        reason = " ".join(str(exc).split())
        raise CalibrationError(f"calibration file {path} is not a valid ZED .conf: {reason}", path=str(path)) from None
    if not parser.sections():
        raise CalibrationError(f"calibration file {path} is not a valid ZED .conf: it has no [SECTION]s", path=str(path))
    return parser


def _section(parser: configparser.ConfigParser, name: str, path: Path) -> configparser.SectionProxy:
    # Sections are matched case-insensitively, as Stereolabs' SimpleIni-based readers do.
    for actual in parser.sections():
        if actual.upper() == name:
            return parser[actual]
    have = ", ".join(parser.sections()[:8]) or "none"
    raise CalibrationError(
        f"calibration {path} has no [{name}] section (it has: {have}); is it this camera's file, and is the "
        "camera in a mode the file covers?",
        path=str(path),
        key=name,
    )


def _zed_value(
    section: configparser.SectionProxy, keys: tuple[str, ...], path: Path, default: float | None = None
) -> float:
    for key in keys:
        raw = section.get(key)  # option names are case-insensitive in configparser
        if raw is None or raw.strip() == "":
            continue
        try:
            value = float(raw)
        except ValueError:
            raise CalibrationError(
                f"calibration {path}: [{section.name}] {key} = {raw!r} is not a number", path=str(path), key=key
            ) from None
        if not math.isfinite(value):
            raise CalibrationError(
                f"calibration {path}: [{section.name}] {key} = {raw!r} is not finite", path=str(path), key=key
            )
        return value
    if default is not None:
        return default
    spelled = " or ".join(keys)
    raise CalibrationError(f"calibration {path}: [{section.name}] is missing {spelled}", path=str(path), key=keys[0])


def load_zed_conf(path: str | Path, image_size: tuple[int, int]) -> StereoCalibration:
    """Load a ZED factory calibration ``SN<serial>.conf`` for one resolution.

    The section is chosen by the frame's one-eye size: 2K 2208x1242, FHD 1920x1080, HD 1280x720,
    VGA 672x376. Per eye (``[LEFT_CAM_<res>]``, ``[RIGHT_CAM_<res>]``): ``fx fy cx cy k1 k2`` required,
    ``p1 p2 k3`` optional (0 when absent). ``[STEREO]``: ``Baseline`` (mm, stored positive), ``TY``
    and ``TZ`` (mm; ``TY_<res>``/``TZ_<res>`` also accepted), and per resolution ``RX_<res>``,
    ``CV_<res>``, ``RZ_<res>`` (Rodrigues vector components, radians).

    Converted to OpenCV's convention (see the module comment for the sources):
    ``T = (-Baseline, TY, TZ) / 1000`` metres and ``R = Rodrigues((RX, CV, RZ))``, which gives
    positive disparity ``x_left - x_right``.

    Args:
        path: the ``.conf`` file.
        image_size: one eye's frame size ``(width, height)``, pixels.

    Raises:
        CalibrationError: unreadable file, unknown resolution, a missing or non-numeric key, or a
            baseline that is not a positive number of millimetres.
    """
    path = Path(path)
    res = _zed_resolution(image_size, path)
    parser = _read_ini(path)

    def eye(side: str) -> tuple[np.ndarray, np.ndarray]:
        sec = _section(parser, f"{side}_CAM_{res}", path)
        fx, fy, cx, cy = (_zed_value(sec, (k,), path) for k in ("fx", "fy", "cx", "cy"))
        k1, k2 = (_zed_value(sec, (k,), path) for k in ("k1", "k2"))
        p1, p2, k3 = (_zed_value(sec, (k,), path, default=0.0) for k in ("p1", "p2", "k3"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return K, np.array([k1, k2, p1, p2, k3])

    K1, D1 = eye("LEFT")
    K2, D2 = eye("RIGHT")
    stereo = _section(parser, "STEREO", path)
    baseline_mm = _zed_value(stereo, ("Baseline",), path)
    if baseline_mm < 1.0:
        # The file stores |T_x| in millimetres (ZED 120, ZED Mini 63); a tiny or negative value is
        # metres or a sign error, and either would silently mis-scale every depth.
        raise CalibrationError(
            f"calibration {path}: [STEREO] Baseline = {baseline_mm} must be a positive distance in millimetres",
            path=str(path),
            key="Baseline",
        )
    ty_mm = _zed_value(stereo, (f"TY_{res}", "TY"), path)
    tz_mm = _zed_value(stereo, (f"TZ_{res}", "TZ"), path)
    rvec = np.array([_zed_value(stereo, (f"{k}_{res}",), path) for k in ("RX", "CV", "RZ")], dtype=np.float64)
    R, _ = cv2.Rodrigues(rvec.reshape(3, 1))
    T = np.array([-baseline_mm, ty_mm, tz_mm]) / 1000.0
    return StereoCalibration(
        K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, image_size=tuple(image_size), source=f"{path} [{res}]"
    )

