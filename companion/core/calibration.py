"""Stereo calibration loaders and the rectifier.

Two file families are read into one :class:`StereoCalibration` (OpenCV's conventions, metres):

* the ZED factory file ``SN<serial>.conf`` (INI, millimetres, one section per resolution);
* an OpenCV stereo calibration (``.yaml``/``.yml``/``.xml`` via ``cv2.FileStorage``, ``.json``, ``.npz``)
  with keys ``K1 D1 K2 D2 R T`` and ``image_size`` (or ``image_width``/``image_height``).

:class:`Rectifier` runs ``cv2.stereoRectify`` and ``cv2.initUndistortRectifyMap`` once and then
remaps every frame into preallocated buffers; :class:`IdentityRectifier` stands in for frames that
are already rectified (the simulator). :func:`make_rectifier` picks one from the config.

OpenCV convention used throughout: a point ``X_l`` in the left camera frame (x right, y down,
z forward) is ``X_r = R @ X_l + T`` in the right camera frame. For a left/right rig the right
camera sits at ``+baseline`` along x, so ``T ≈ (-baseline, 0, 0)`` and, after rectification,
``P2[0, 3] = -f·baseline < 0`` and disparity ``d = x_left - x_right = f·baseline / Z > 0``.
"""

from __future__ import annotations

import configparser
import json
import logging
import math
import re
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import cv2
import numpy as np

from companion.config.core import CalibrationConfig
from companion.core.geometry import StereoGeometry
from companion.errors import CalibrationError, FrameError

__all__ = [
    "OPENCV_CALIBRATION_SUFFIXES",
    "ZED_RESOLUTIONS",
    "LENS_MODELS",
    "AnyRectifier",
    "IdentityRectifier",
    "Rectifier",
    "StereoCalibration",
    "load_calibration",
    "load_opencv_calibration",
    "load_zed_conf",
    "make_rectifier",
    "remap_linear_reference",
    "save_calibration",
]

log = logging.getLogger(__name__)

#: ZED section suffix -> one-eye image size (width, height) in pixels.
ZED_RESOLUTIONS: Final[Mapping[str, tuple[int, int]]] = MappingProxyType(
    {"2K": (2208, 1242), "FHD": (1920, 1080), "HD": (1280, 720), "VGA": (672, 376)}
)

OPENCV_CALIBRATION_SUFFIXES: Final[tuple[str, ...]] = (".yaml", ".yml", ".xml", ".json", ".npz")

#: Lens models the rectifier handles: OpenCV's pinhole (radial-tangential) and its fisheye (equidistant).
LENS_MODELS: Final[tuple[str, ...]] = ("pinhole", "fisheye")

# Distortion vector lengths OpenCV's pinhole model accepts.
_DIST_LENGTHS: Final[frozenset[int]] = frozenset({4, 5, 8, 12, 14})


def _fmt_size(size: tuple[int, int]) -> str:
    return f"{size[0]}x{size[1]}"


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


# --------------------------------------------------------------------------------------------------
# Calibration data


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """Raw (unrectified) stereo calibration in OpenCV's conventions.

    Attributes:
        K1, K2: camera matrices of the left and right eye, float64 ``(3, 3)``, pixels.
        D1, D2: distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]),
            float64 ``(n,)`` with n in {4, 5, 8, 12, 14}.
        R: rotation from the left to the right camera frame, float64 ``(3, 3)``.
        T: translation from the left to the right camera frame (``X_r = R X_l + T``), float64
            ``(3,)``, METRES; ``T[0] ≈ -baseline`` for a left/right rig.
        image_size: one eye's raw image size ``(width, height)``, pixels.
        source: where the calibration came from (file and section), for messages.
        model: the lens model: ``"pinhole"`` (OpenCV's radial-tangential family, D of 4 to 14
            coefficients) or ``"fisheye"`` (the equidistant model of ``cv2.fisheye``, Kalibr's
            ``equidistant``: D is ``k1 k2 k3 k4``).

    The arrays are stored as read-only float64 copies.

    Raises:
        CalibrationError: a wrong shape, a non-finite value, a non-rotation R, a zero T, a
            non-positive focal length or image size.
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int]
    source: str = "<memory>"
    model: str = "pinhole"

    def __post_init__(self) -> None:
        src = self.source
        if self.model not in LENS_MODELS:
            raise CalibrationError(
                f"calibration {src}: distortion_model {self.model!r} is not one the pipeline rectifies "
                f"({', '.join(LENS_MODELS)})",
                source=src,
                key="distortion_model",
            )

        def arr(name: str, value: Any, shape: tuple[int, ...] | None) -> np.ndarray:
            try:
                a = np.array(value, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise CalibrationError(f"calibration {src}: {name} is not numeric ({exc})", source=src, key=name) from None
            if shape is None:
                a = a.reshape(-1)
                if self.model == "fisheye" and a.size != 4:
                    raise CalibrationError(
                        f"calibration {src}: {name} has {a.size} coefficients; the fisheye model takes 4 (k1..k4)",
                        source=src,
                        key=name,
                    )
                if a.size not in _DIST_LENGTHS:
                    raise CalibrationError(
                        f"calibration {src}: {name} has {a.size} coefficients; OpenCV takes 4, 5, 8, 12 or 14",
                        source=src,
                        key=name,
                    )
            else:
                if a.size == math.prod(shape) and a.ndim <= 2:
                    a = a.reshape(shape)
                if a.shape != shape:
                    raise CalibrationError(
                        f"calibration {src}: {name} must be {shape}, got shape {a.shape}", source=src, key=name
                    )
            if not np.all(np.isfinite(a)):
                raise CalibrationError(f"calibration {src}: {name} has non-finite values", source=src, key=name)
            return _readonly(a)

        for name in ("K1", "K2"):
            k = arr(name, getattr(self, name), (3, 3))
            if not (k[0, 0] > 0 and k[1, 1] > 0) or not np.allclose(k[2], (0.0, 0.0, 1.0)):
                raise CalibrationError(
                    f"calibration {src}: {name} is not a camera matrix (fx, fy > 0, last row 0 0 1): {k.tolist()}",
                    source=src,
                    key=name,
                )
            object.__setattr__(self, name, k)
        for name in ("D1", "D2"):
            object.__setattr__(self, name, arr(name, getattr(self, name), None))
        rot = arr("R", self.R, (3, 3))
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-4) or np.linalg.det(rot) <= 0:
            raise CalibrationError(
                f"calibration {src}: R is not a rotation matrix (R^T R = I, det R = +1): {np.round(rot, 6).tolist()}",
                source=src,
                key="R",
            )
        object.__setattr__(self, "R", rot)
        t = arr("T", self.T, (3,))
        if not np.linalg.norm(t) > 0:
            raise CalibrationError(f"calibration {src}: T is zero; the two cameras cannot coincide", source=src, key="T")
        object.__setattr__(self, "T", t)
        try:
            w, h = (int(v) for v in self.image_size)
        except (TypeError, ValueError):
            raise CalibrationError(
                f"calibration {src}: image_size must be (width, height), got {self.image_size!r}", source=src, key="image_size"
            ) from None
        if w <= 0 or h <= 0:
            raise CalibrationError(f"calibration {src}: image_size must be positive, got {w}x{h}", source=src, key="image_size")
        object.__setattr__(self, "image_size", (w, h))

    @property
    def baseline_m(self) -> float:
        """Distance between the two optical centres, metres (``|T|``)."""
        return float(np.linalg.norm(self.T))


# --------------------------------------------------------------------------------------------------
# ZED factory calibration (SN<serial>.conf)
#
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
    known = ", ".join(f"{n} {_fmt_size(s)}" for n, s in ZED_RESOLUTIONS.items())
    raise CalibrationError(
        f"calibration {path} has no section for {_fmt_size(image_size)}; ZED resolutions are {known} (one eye)",
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


# --------------------------------------------------------------------------------------------------
# OpenCV stereo calibration (.yaml/.yml/.xml/.json/.npz)

_REQUIRED_KEYS: Final[tuple[str, ...]] = ("K1", "D1", "K2", "D2", "R", "T")
_T_UNIT_SCALE: Final[Mapping[str, float]] = MappingProxyType({"m": 1.0, "mm": 1e-3})


def _opencv_parse_reason(message: str, path: Path) -> str:
    """OpenCV's parse error without its source-file noise: ``not valid YAML: line 3: Missing , ...``.

    OpenCV says ``OpenCV(5.0.0) /io/.../persistence_yml.cpp:681: error: (-212:Parsing error) parseValue
    in function '/path/file.yaml(3): Missing , between the elements'``.
    """
    kind = {".xml": "XML", ".json": "JSON"}.get(path.suffix.lower(), "YAML")
    m = re.search(r"\((\d+)\):\s*(.+?)'?\s*$", message.strip().splitlines()[-1] if message.strip() else "")
    if m is not None:
        why = m.group(2).strip()
        if "Only collections" in why:
            why = "it is not a mapping of keys (K1: ..., D1: ..., ...)"
        return f"not valid {kind} for cv2.FileStorage: line {m.group(1)}: {why}"
    lines = [ln.strip() for ln in message.strip().splitlines() if ln.strip()]
    tail = lines[-1] if lines else "unknown error"
    tail = re.sub(r"^OpenCV\([^)]*\)\s+\S+:\d+:\s*error:\s*\([^)]*\)\s*", "", tail)
    return f"not valid {kind} for cv2.FileStorage: {tail}"


def _filestorage_values(path: Path) -> dict[str, Any]:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # cv2 raises SystemError chained to cv2.error on parse errors
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
        raise CalibrationError(
            f"cannot parse calibration file {path}: {_opencv_parse_reason(str(cause), path)}", path=str(path)
        ) from None
    try:
        if not fs.isOpened():
            raise CalibrationError(f"cannot open calibration file {path} with cv2.FileStorage", path=str(path))
        root = fs.root()
        values: dict[str, Any] = {}
        for key in root.keys() if root.isMap() else ():
            node = fs.getNode(key)
            if node.isMap():
                try:
                    values[key] = node.mat()
                except cv2.error:
                    if key in _REQUIRED_KEYS:
                        raise CalibrationError(
                            f"calibration {path}: {key} is not a matrix (an opencv-matrix needs rows, cols, dt "
                            "and data)",
                            path=str(path),
                            key=key,
                        ) from None
                    continue  # a map that is not an opencv-matrix (metadata): not ours to read
                if values[key] is None and key in _REQUIRED_KEYS:
                    raise CalibrationError(
                        f"calibration {path}: {key} is not a matrix (an opencv-matrix needs rows, cols, dt and data)",
                        path=str(path),
                        key=key,
                    )
            elif node.isSeq():
                values[key] = [node.at(i).real() for i in range(node.size())]
            elif node.isString():
                values[key] = node.string()
            elif node.isInt() or node.isReal():
                values[key] = node.real()
        return values
    finally:
        fs.release()


def _json_values(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"cannot parse calibration file {path}: not valid JSON: {exc}", path=str(path)) from None
    except UnicodeDecodeError:
        raise CalibrationError(f"cannot parse calibration file {path}: not valid JSON: not text (binary data)", path=str(path)) from None
    if not isinstance(data, dict):
        raise CalibrationError(f"calibration file {path} must hold a JSON object", path=str(path))
    values: dict[str, Any] = {}
    for key, v in data.items():
        # cv2.FileStorage's JSON form of a matrix: {"type_id": "opencv-matrix", "rows", "cols", "data"}.
        if isinstance(v, dict) and {"rows", "cols", "data"} <= v.keys():
            try:
                v = np.asarray(v["data"], dtype=np.float64).reshape(int(v["rows"]), int(v["cols"]))
            except (TypeError, ValueError) as exc:
                raise CalibrationError(
                    f"calibration {path}: {key} is a malformed matrix ({exc})", path=str(path), key=key
                ) from None
        values[key] = v
    return values


def _npz_values(path: Path) -> dict[str, Any]:
    if not zipfile.is_zipfile(path):
        raise CalibrationError(
            f"cannot parse calibration file {path}: not an .npz archive (write one with numpy.savez)", path=str(path)
        )
    try:
        with np.load(path, allow_pickle=False) as npz:
            if not hasattr(npz, "files"):
                raise CalibrationError(f"cannot parse calibration file {path}: a single array, not an .npz archive")
            return {k: (str(npz[k]) if npz[k].dtype.kind in "US" else npz[k]) for k in npz.files}
    except ValueError as exc:
        reason = (
            "it holds Python objects (pickled data), which are never loaded; save plain arrays with numpy.savez"
            if "pickle" in str(exc).lower() or "object arrays" in str(exc).lower()
            else str(exc)
        )
        raise CalibrationError(f"cannot parse calibration file {path}: {reason}", path=str(path)) from None
    except (zipfile.BadZipFile, EOFError, KeyError, OSError) as exc:
        raise CalibrationError(
            f"cannot parse calibration file {path}: a damaged .npz archive ({type(exc).__name__}: {exc})", path=str(path)
        ) from None


def _image_size_from(values: Mapping[str, Any], path: Path) -> tuple[int, int]:
    if "image_size" in values:
        raw = values["image_size"]
        try:
            seq = np.asarray(raw, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            seq = np.empty(0)
        if seq.size != 2 or not np.all(np.isfinite(seq)) or not np.all(seq == np.round(seq)):
            raise CalibrationError(
                f"calibration {path}: image_size must be [width, height] in pixels, got {raw!r}",
                path=str(path),
                key="image_size",
            )
        return int(seq[0]), int(seq[1])
    if "image_width" in values and "image_height" in values:
        try:
            return int(float(values["image_width"])), int(float(values["image_height"]))
        except (TypeError, ValueError):
            raise CalibrationError(
                f"calibration {path}: image_width/image_height must be integers", path=str(path), key="image_width"
            ) from None
    raise CalibrationError(
        f"calibration {path} is missing image_size (or image_width and image_height)", path=str(path), key="image_size"
    )


def load_opencv_calibration(path: str | Path) -> StereoCalibration:
    """Load an OpenCV stereo calibration.

    Formats, by extension: ``.yaml``/``.yml``/``.xml`` (``cv2.FileStorage``), ``.json`` (plain lists
    or FileStorage's ``opencv-matrix`` objects), ``.npz`` (``np.savez``). Keys: ``K1 D1 K2 D2 R T``
    as produced by ``cv2.stereoCalibrate`` (``X_r = R X_l + T``) and ``image_size`` ``[width, height]``
    or ``image_width`` + ``image_height``.

    ``distortion_model: fisheye`` (optional; default ``pinhole``) marks an equidistant lens
    (``cv2.fisheye``, D = k1..k4).

    Units of T: metres, unless the file has ``T_units: mm`` (millimetres, e.g. a board measured in
    mm); ``T_units: m`` is also accepted, anything else is an error.

    Raises:
        CalibrationError: unreadable or unparsable file, a missing key (named), a bad shape/value.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in OPENCV_CALIBRATION_SUFFIXES:
        raise CalibrationError(
            f"calibration {path}: unknown extension {suffix!r}; "
            f"expected one of {', '.join(OPENCV_CALIBRATION_SUFFIXES)}",
            path=str(path),
        )
    if path.is_dir():
        raise CalibrationError(f"cannot read calibration file {path}: it is a directory", path=str(path))
    if not path.is_file():
        # Checked up front: cv2.FileStorage would only log to stderr and report "not opened".
        raise CalibrationError(f"cannot read calibration file {path}: no such file", path=str(path))
    if path.stat().st_size == 0:
        raise CalibrationError(f"calibration file {path} is empty", path=str(path))
    try:
        if suffix == ".json":
            values = _json_values(path)
        elif suffix == ".npz":
            values = _npz_values(path)
        else:
            values = _filestorage_values(path)
    except OSError as exc:
        raise CalibrationError(f"cannot read calibration file {path}: {exc.strerror or exc}", path=str(path)) from None

    for key in _REQUIRED_KEYS:
        if key not in values or values[key] is None:
            raise CalibrationError(f"calibration {path} is missing {key}", path=str(path), key=key)
    unit = str(values.get("T_units", "m")).strip().lower()
    if unit not in _T_UNIT_SCALE:
        raise CalibrationError(
            f"calibration {path}: T_units = {unit!r}; expected 'm' or 'mm'", path=str(path), key="T_units"
        )
    try:
        T = np.asarray(values["T"], dtype=np.float64) * _T_UNIT_SCALE[unit]
    except (TypeError, ValueError):
        raise CalibrationError(f"calibration {path}: T is not numeric", path=str(path), key="T") from None
    model = str(values.get("distortion_model", "pinhole")).strip().lower()
    return StereoCalibration(
        K1=values["K1"],
        D1=values["D1"],
        K2=values["K2"],
        D2=values["D2"],
        R=values["R"],
        T=T,
        image_size=_image_size_from(values, path),
        source=str(path),
        model=model,
    )


def load_calibration(path: str | Path, image_size: tuple[int, int]) -> StereoCalibration:
    """Load a stereo calibration for frames of one eye size, dispatching on the extension.

    ``.conf`` is a ZED factory file (the section is chosen by ``image_size``); ``.yaml``, ``.yml``,
    ``.xml``, ``.json`` and ``.npz`` are OpenCV calibrations, which must be for exactly
    ``image_size`` (never silently rescaled).

    Args:
        path: calibration file.
        image_size: one eye's frame size ``(width, height)``, pixels.

    Raises:
        CalibrationError: unknown extension, unreadable file (path and reason), missing keys, or a
            calibration for another resolution than the frames'.
    """
    path = Path(path)
    size = (int(image_size[0]), int(image_size[1]))
    suffix = path.suffix.lower()
    if suffix == ".conf":
        return load_zed_conf(path, size)
    if suffix not in OPENCV_CALIBRATION_SUFFIXES:
        raise CalibrationError(
            f"calibration {path}: unknown extension {suffix!r}; expected .conf (ZED) or "
            f"{', '.join(OPENCV_CALIBRATION_SUFFIXES)} (OpenCV)",
            path=str(path),
        )
    calib = load_opencv_calibration(path)
    if calib.image_size != size:
        raise CalibrationError(
            f"calibration {path} is for {_fmt_size(calib.image_size)} but frames are {_fmt_size(size)}",
            path=str(path),
            calibration_size=calib.image_size,
            frame_size=size,
        )
    return calib


# --------------------------------------------------------------------------------------------------
# Rectification


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
            "R1": _readonly(R1),
            "R2": _readonly(R2),
            "P1": _readonly(P1),
            "P2": _readonly(P2),
            "Q": _readonly(Q),
            "map_left_x": _readonly(mlx),
            "map_left_y": _readonly(mly),
            "map_right_x": _readonly(mrx),
            "map_right_y": _readonly(mry),
            "valid_roi_left": tuple(int(v) for v in roi1),
            "valid_roi_right": tuple(int(v) for v in roi2),
        }
        for name, value in values.items():
            object.__setattr__(self, name, value)
        log.debug(
            "rectifier for %s at %s: f=%.2f px, c=(%.2f, %.2f) px, B=%.4f m",
            c.source,
            _fmt_size(size),
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


# --------------------------------------------------------------------------------------------------
# Writing (the project's format)


def save_calibration(calib: StereoCalibration, path: str | Path, metadata: Mapping[str, Any] | None = None) -> Path:
    """Write ``calib`` in the project's format (docs/calibration.md), readable by
    :func:`load_opencv_calibration`: ``K1 D1 K2 D2 R T`` (OpenCV's conventions, ``X_r = R X_l + T``,
    T in metres, so ``T[0] ≈ -baseline``), ``T_units: m`` and ``image_size: [width, height]``, plus
    ``metadata`` (numbers and strings: how it was made, its errors), which loaders ignore.

    The format follows the extension: ``.yaml``/``.yml``/``.xml`` (``cv2.FileStorage``), ``.json``
    (plain lists), ``.npz`` (``np.savez``).

    Raises:
        CalibrationError: an unknown extension, or the file cannot be written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in OPENCV_CALIBRATION_SUFFIXES:
        raise CalibrationError(
            f"calibration {path}: unknown extension {suffix!r}; expected one of {', '.join(OPENCV_CALIBRATION_SUFFIXES)}",
            path=str(path),
        )
    arrays = {"K1": calib.K1, "D1": calib.D1, "K2": calib.K2, "D2": calib.D2, "R": calib.R, "T": calib.T}
    meta: dict[str, Any] = {"T_units": "m"}
    if calib.model != "pinhole":
        meta["distortion_model"] = calib.model
    for key, value in (metadata or {}).items():
        if key in arrays or key in ("image_size", "T_units", "distortion_model"):
            raise CalibrationError(f"calibration {path}: metadata may not be called {key!r}", path=str(path))
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise CalibrationError(f"calibration {path}: metadata {key!r} must be a number or a string", path=str(path))
        meta[key] = value
    w, h = calib.image_size
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if suffix == ".json":
            doc: dict[str, Any] = {k: np.asarray(v).tolist() for k, v in arrays.items()}
            doc["image_size"] = [w, h]
            doc.update(meta)
            path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        elif suffix == ".npz":
            extra = {k: np.asarray(v) for k, v in meta.items()}
            np.savez(path, **{k: np.asarray(v) for k, v in arrays.items()}, image_size=np.array([w, h]), **extra)
        else:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
            if not fs.isOpened():
                raise OSError(f"cv2.FileStorage cannot write {path}")
            try:
                for key, value in arrays.items():
                    a = np.asarray(value, dtype=np.float64)
                    fs.write(key, a.reshape(-1, 1) if a.ndim == 1 else a)
                fs.startWriteStruct("image_size", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
                fs.write("", int(w))
                fs.write("", int(h))
                fs.endWriteStruct()
                for key, value in meta.items():
                    fs.write(key, value)
            finally:
                fs.release()
    except (OSError, cv2.error) as err:
        reason = getattr(err, "strerror", None) or str(err).strip().splitlines()[-1]
        raise CalibrationError(f"cannot write calibration file {path}: {reason}", path=str(path)) from None
    return path
