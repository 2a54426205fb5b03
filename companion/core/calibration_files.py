"""Calibration files: OpenCV stereo calibrations read and written (``.yaml``/``.yml``/``.xml`` via
``cv2.FileStorage``, ``.json``, ``.npz``; keys ``K1 D1 K2 D2 R T`` and ``image_size``), and any
calibration file loaded for frames of one eye size, by its extension (a ZED factory ``.conf`` through
:mod:`companion.core.zed_conf`).
"""

from __future__ import annotations

import json
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import cv2
import numpy as np

from companion.core.calibration import StereoCalibration, fmt_size
from companion.core.zed_conf import load_zed_conf
from companion.errors import CalibrationError

__all__ = [
    "OPENCV_CALIBRATION_SUFFIXES",
    "load_calibration",
    "load_opencv_calibration",
    "save_calibration",
]

OPENCV_CALIBRATION_SUFFIXES: Final[tuple[str, ...]] = (".yaml", ".yml", ".xml", ".json", ".npz")


# --------------------------------------------------------------------------------------------------
# Reading

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
            f"calibration {path} is for {fmt_size(calib.image_size)} but frames are {fmt_size(size)}",
            path=str(path),
            calibration_size=calib.image_size,
            frame_size=size,
        )
    return calib


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
