"""Import the stereo calibrations drone people already have into the project's format.

Four families, told apart by their keys (never by the file's name):

* **Kalibr** ``camchain.yaml``: ``cam0`` and ``cam1`` maps with ``camera_model`` (``pinhole`` only: the
  pipeline rectifies pinhole lenses), ``intrinsics`` ``[fu, fv, pu, pv]``, ``distortion_model``
  (``radtan``, ``equidistant`` or ``none``), ``distortion_coeffs``, ``resolution`` ``[w, h]``, and
  ``cam1.T_cn_cnm1``: the 4x4 transform taking a point in cam0's frame to cam1's (``X_1 = T X_0``),
  which is OpenCV's ``(R, T)`` as it stands.
* **ASL / EuRoC** ``sensor.yaml``, one per eye: ``T_BS`` (the sensor's pose in the body frame,
  ``X_B = T_BS X_S``, a 4x4 as ``{rows, cols, data}`` or nested lists), ``intrinsics``,
  ``distortion_model`` (``radial-tangential``/``radtan`` or ``equidistant``),
  ``distortion_coefficients``, ``resolution``. Left to right: ``X_1 = T_BS1^-1 T_BS0 X_0``.
* **ROS** ``camera_info`` YAML, one per eye: ``camera_calibration``'s file (``camera_matrix``,
  ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix`` as ``{rows, cols, data}``,
  ``image_width``/``image_height``) or the message itself (``K D R P``, ROS 2's ``k d r p``,
  ``width``/``height``). ``distortion_model`` ``plumb_bob`` or ``rational_polynomial`` (pinhole) or
  ``equidistant`` (fisheye). The eyes' relative pose comes from the rectification: with ``R1, R2`` the
  rectifying rotations and the right ``P``'s ``Tx = P[0,3]/P[0,0]`` (``-baseline``),
  ``R = R2^T R1`` and ``T = R2^T (Tx, Ty, 0)``. The eye whose ``P[0,3]`` is 0 is the left one.
* **OpenCV** stereo files (``cv2.FileStorage`` YAML or XML; one file, or ``intrinsics.yml`` and
  ``extrinsics.yml`` as OpenCV's stereo sample writes them): ``M1 D1 M2 D2 R T`` or ``K1 D1 K2 D2 R T``
  (``cameraMatrix1``/``distCoeffs1`` also), ``image_size`` or ``image_width``/``image_height`` (else
  the ``image_size`` argument), ``T_units`` (else the ``t_units`` argument).

Every reader returns a :class:`~companion.core.calibration.StereoCalibration` in OpenCV's convention
(``X_r = R X_l + T``, metres, ``T[0] ≈ -baseline``: docs/calibration.md). A file that is not one of
these, or misses a key, raises a :class:`~companion.errors.CalibrationError` naming the key; a lens
model the pipeline cannot rectify (Kalibr ``omni``, ``ds``, ``eucm``; ``fov`` distortion) is refused by
its name.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from companion.core.calibration import StereoCalibration
from companion.errors import CalibrationError

__all__ = ["FORMATS", "ImportedCalibration", "camera_info_calibration", "detect_format", "import_calibration", "read_document"]

#: format name -> what it is, for messages.
FORMATS: Final[Mapping[str, str]] = {
    "kalibr": "a Kalibr camchain.yaml",
    "asl": "ASL/EuRoC sensor.yaml files",
    "ros": "ROS camera_info YAML files",
    "opencv": "an OpenCV stereo calibration",
    "rosbag": "a rosbag's camera_info topics",
}

_KALIBR_DISTORTION: Final[Mapping[str, str]] = {"radtan": "pinhole", "equidistant": "fisheye", "equi": "fisheye", "none": "pinhole"}
_ASL_DISTORTION: Final[Mapping[str, str]] = {
    "radial-tangential": "pinhole", "radtan": "pinhole", "plumb_bob": "pinhole", "equidistant": "fisheye", "none": "pinhole",
}
_ROS_DISTORTION: Final[Mapping[str, str]] = {
    "plumb_bob": "pinhole", "rational_polynomial": "pinhole", "equidistant": "fisheye", "fisheye": "fisheye", "": "pinhole",
}
_OPENCV_ALIASES: Final[Mapping[str, tuple[str, ...]]] = {
    "K1": ("K1", "M1", "cameraMatrix1", "camera_matrix_1"),
    "D1": ("D1", "distCoeffs1", "dist_coeffs_1"),
    "K2": ("K2", "M2", "cameraMatrix2", "camera_matrix_2"),
    "D2": ("D2", "distCoeffs2", "dist_coeffs_2"),
    "R": ("R",),
    "T": ("T",),
}
_T_SCALE: Final[Mapping[str, float]] = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


@dataclass(frozen=True)
class ImportedCalibration:
    """What :func:`import_calibration` found.

    Attributes:
        calibration: the rig in the project's convention.
        format: a key of :data:`FORMATS`.
        files: the files read, left eye's first where there are two.
        notes: one line each worth telling the user (an eye order found from the files, a third camera
            left out).
    """

    calibration: StereoCalibration
    format: str
    files: tuple[Path, ...]
    notes: tuple[str, ...] = ()


# ------------------------------------------------------------------------------------------------ reading


def _yaml_loader() -> type:
    import yaml

    class Loader(yaml.SafeLoader):
        """PyYAML's safe loader that also reads OpenCV's ``!!opencv-matrix`` maps as arrays."""

    def matrix(loader: Any, node: Any) -> np.ndarray:
        m = loader.construct_mapping(node, deep=True)
        return np.asarray(m.get("data", []), dtype=np.float64).reshape(int(m.get("rows", 0)), int(m.get("cols", 0)))

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    Loader.add_constructor("tag:yaml.org,2002:opencv-nd-matrix", matrix)
    return Loader


def _filestorage_document(path: Path, text: str | None) -> dict[str, Any]:
    """Every top-level key of an OpenCV FileStorage file: matrices as arrays, sequences as lists."""
    import cv2

    added = 0  # lines put before the file's own, for the line numbers of OpenCV's messages
    try:
        if text is not None:
            # FileStorage needs its own %YAML:1.0 header; a file written without it is read from memory.
            stripped = text.lstrip()
            if stripped.startswith("%YAML"):
                body = text
            else:
                head = "%YAML:1.0\n" + ("" if stripped.startswith("---") else "---\n")
                body, added = head + text, head.count("\n")
            fs = cv2.FileStorage(body, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        else:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
        lines = [ln.strip() for ln in str(cause).strip().splitlines() if ln.strip()]
        last = lines[-1] if lines else "unknown error"
        m = re.search(r"\((\d+)\):\s*(.+?)'?\s*$", last)
        why = f"line {int(m.group(1)) - added}: {m.group(2)}" if m is not None else last[:160]
        raise CalibrationError(f"cannot parse {path}: not a valid OpenCV file ({why})", path=str(path)) from None
    try:
        if not fs.isOpened():
            raise CalibrationError(f"cannot parse {path}: cv2.FileStorage cannot open it", path=str(path))

        def value(node: Any) -> Any:
            if node.isMap():
                try:
                    mat = node.mat()
                except cv2.error:
                    mat = None
                if mat is not None:
                    return np.asarray(mat, dtype=np.float64)
                return {k: value(node.getNode(k)) for k in node.keys()}
            if node.isSeq():
                return [value(node.at(i)) for i in range(node.size())]
            if node.isString():
                return node.string()
            if node.isInt() or node.isReal():
                return node.real()
            return None

        root = fs.root()
        if not root.isMap():
            raise CalibrationError(f"{path} is not a mapping of keys", path=str(path))
        return {k: value(fs.getNode(k)) for k in root.keys()}
    finally:
        fs.release()


def read_document(path: Path) -> dict[str, Any]:
    """The top-level mapping of one calibration file.

    ``.xml`` files and YAML holding OpenCV's ``!!opencv-matrix`` tags are read by ``cv2.FileStorage``;
    other YAML by PyYAML (a leading ``%YAML:1.0`` line, which OpenCV and the EuRoC files write and
    PyYAML rejects, is dropped first).

    Raises:
        CalibrationError: no such file, not text, not YAML/XML, or not a mapping.
    """
    import yaml

    path = Path(path)
    if path.is_dir():
        raise CalibrationError(f"cannot read {path}: it is a directory", path=str(path))
    if not path.is_file():
        raise CalibrationError(f"cannot read {path}: no such file", path=str(path))
    if path.suffix.lower() == ".xml":
        return _filestorage_document(path, None)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise CalibrationError(f"cannot read {path}: it is not text", path=str(path)) from None
    except OSError as exc:
        raise CalibrationError(f"cannot read {path}: {exc.strerror or exc}", path=str(path)) from None
    if not text.strip():
        raise CalibrationError(f"{path} is empty", path=str(path))
    if "!!opencv-matrix" in text:
        return _filestorage_document(path, text)
    body = re.sub(r"\A\s*%YAML:\d+\.\d+[^\n]*\n", "", text)
    try:
        doc = yaml.load(body, Loader=_yaml_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise CalibrationError(f"cannot parse {path}: not valid YAML{where}: {problem}", path=str(path)) from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path} is not a mapping of keys (key: value)", path=str(path))
    return doc


def detect_format(doc: Mapping[str, Any]) -> str | None:
    """The :data:`FORMATS` key a document's keys say it is, or None."""
    if isinstance(doc.get("cam0"), dict) and ("intrinsics" in doc["cam0"] or "camera_model" in doc["cam0"]):
        return "kalibr"
    if "T_BS" in doc or doc.get("sensor_type") is not None:
        return "asl"
    if any(k in doc for k in ("camera_matrix", "projection_matrix", "K", "k", "P", "p")) and "K1" not in doc and "M1" not in doc:
        return "ros"
    if any(a in doc for names in _OPENCV_ALIASES.values() for a in names):
        return "opencv"
    return None


# ------------------------------------------------------------------------------------------------ helpers


def _need(doc: Mapping[str, Any], key: str, where: str, path: Path) -> Any:
    if key not in doc or doc[key] is None:
        raise CalibrationError(f"{path} is missing {where}{key}", path=str(path), key=key)
    return doc[key]


def _numbers(value: Any, key: str, path: Path, size: int | None = None) -> np.ndarray:
    """A flat float64 array from a list, nested lists, an array or a ``{rows, cols, data}`` map."""
    if isinstance(value, Mapping):
        if "data" not in value:
            raise CalibrationError(f"{path}: {key} has no data", path=str(path), key=key)
        value = value["data"]
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: {key} is not a list of numbers: {str(value)[:80]}", path=str(path), key=key) from None
    if size is not None and a.size != size:
        raise CalibrationError(f"{path}: {key} must hold {size} numbers, got {a.size}", path=str(path), key=key)
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{path}: {key} has non-finite values", path=str(path), key=key)
    return a


def _size(value: Any, key: str, path: Path) -> tuple[int, int]:
    a = _numbers(value, key, path, 2)
    if not np.all(a == np.round(a)) or np.any(a <= 0):
        raise CalibrationError(f"{path}: {key} must be [width, height] in pixels, got {a.tolist()}", path=str(path), key=key)
    return int(a[0]), int(a[1])


def _camera_matrix(fu: float, fv: float, pu: float, pv: float) -> np.ndarray:
    return np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]])


def _pinhole_distortion(coeffs: np.ndarray, model: str, key: str, path: Path) -> np.ndarray:
    """Kalibr's/ASL's coefficients in OpenCV's order: radtan ``k1 k2 p1 p2`` is OpenCV's own order;
    equidistant ``k1..k4`` is cv2.fisheye's; none is no distortion."""
    if coeffs.size == 0:
        return np.zeros(4)
    if model == "fisheye" and coeffs.size != 4:
        raise CalibrationError(f"{path}: {key} must hold 4 equidistant coefficients (k1..k4), got {coeffs.size}", path=str(path), key=key)
    return coeffs


# ------------------------------------------------------------------------------------------------ Kalibr


def _kalibr_camera(doc: Mapping[str, Any], name: str, path: Path) -> tuple[np.ndarray, np.ndarray, str, tuple[int, int]]:
    cam = doc.get(name)
    if not isinstance(cam, Mapping):
        raise CalibrationError(f"{path} is missing {name} (a Kalibr camchain has cam0 and cam1)", path=str(path), key=name)
    model = str(_need(cam, "camera_model", f"{name}.", path)).strip().lower()
    if model != "pinhole":
        raise CalibrationError(
            f"{path}: {name}.camera_model is {model!r}, which the pipeline cannot rectify; calibrate the rig with "
            "Kalibr's pinhole-radtan or pinhole-equi model",
            path=str(path),
            key="camera_model",
        )
    dist_name = str(cam.get("distortion_model", "none")).strip().lower()
    lens = _KALIBR_DISTORTION.get(dist_name)
    if lens is None:
        raise CalibrationError(
            f"{path}: {name}.distortion_model is {dist_name!r}, which the pipeline cannot rectify (radtan, equidistant "
            "or none)",
            path=str(path),
            key="distortion_model",
        )
    fu, fv, pu, pv = _numbers(_need(cam, "intrinsics", f"{name}.", path), f"{name}.intrinsics", path, 4)
    coeffs = _numbers(cam.get("distortion_coeffs", []), f"{name}.distortion_coeffs", path)
    D = _pinhole_distortion(coeffs, lens, f"{name}.distortion_coeffs", path)
    size = _size(_need(cam, "resolution", f"{name}.", path), f"{name}.resolution", path)
    return _camera_matrix(fu, fv, pu, pv), D, lens, size


def _transform(value: Any, key: str, path: Path) -> np.ndarray:
    m = _numbers(value, key, path, 16).reshape(4, 4)
    if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise CalibrationError(f"{path}: {key} is not a rigid transform (last row must be 0 0 0 1)", path=str(path), key=key)
    return m


def _from_kalibr(doc: Mapping[str, Any], path: Path) -> ImportedCalibration:
    K1, D1, lens1, size1 = _kalibr_camera(doc, "cam0", path)
    K2, D2, lens2, size2 = _kalibr_camera(doc, "cam1", path)
    if lens1 != lens2:
        raise CalibrationError(f"{path}: cam0 and cam1 have different distortion models; one rig needs one", path=str(path))
    if size1 != size2:
        raise CalibrationError(
            f"{path}: cam0 is {size1[0]}x{size1[1]} but cam1 is {size2[0]}x{size2[1]}; both eyes must have one size",
            path=str(path),
        )
    T = _transform(_need(doc["cam1"], "T_cn_cnm1", "cam1.", path), "cam1.T_cn_cnm1", path)
    notes = []
    extra = sorted(k for k in doc if re.fullmatch(r"cam\d+", str(k)) and k not in ("cam0", "cam1"))
    if extra:
        notes.append(f"{path.name} also has {', '.join(extra)}; cam0 (left) and cam1 (right) were used")
    calib = StereoCalibration(K1, D1, K2, D2, T[:3, :3], T[:3, 3], size1, source=str(path), model=lens1)
    return ImportedCalibration(calib, "kalibr", (path,), tuple(notes))


# ------------------------------------------------------------------------------------------------ ASL


def _asl_camera(doc: Mapping[str, Any], path: Path) -> tuple[np.ndarray, np.ndarray, str, tuple[int, int], np.ndarray]:
    kind = str(doc.get("sensor_type", "camera")).strip().lower()
    if kind != "camera":
        raise CalibrationError(f"{path} is the sensor.yaml of a {kind!r}, not of a camera", path=str(path), key="sensor_type")
    model = str(doc.get("camera_model", "pinhole")).strip().lower()
    if model != "pinhole":
        raise CalibrationError(
            f"{path}: camera_model is {model!r}, which the pipeline cannot rectify (pinhole only)", path=str(path), key="camera_model"
        )
    dist_name = str(doc.get("distortion_model", "none")).strip().lower()
    lens = _ASL_DISTORTION.get(dist_name)
    if lens is None:
        raise CalibrationError(
            f"{path}: distortion_model is {dist_name!r}, which the pipeline cannot rectify (radial-tangential or "
            "equidistant)",
            path=str(path),
            key="distortion_model",
        )
    fu, fv, pu, pv = _numbers(_need(doc, "intrinsics", "", path), "intrinsics", path, 4)
    coeffs = _numbers(doc.get("distortion_coefficients", []), "distortion_coefficients", path)
    D = _pinhole_distortion(coeffs, lens, "distortion_coefficients", path)
    size = _size(_need(doc, "resolution", "", path), "resolution", path)
    T_BS = _transform(_need(doc, "T_BS", "", path), "T_BS", path)
    return _camera_matrix(fu, fv, pu, pv), D, lens, size, T_BS


def _from_asl(docs: Sequence[Mapping[str, Any]], paths: Sequence[Path]) -> ImportedCalibration:
    if len(docs) != 2:
        raise CalibrationError(
            f"{paths[0]} is one eye's sensor.yaml; give both: the left's (cam0) and then the right's (cam1)", path=str(paths[0])
        )
    K1, D1, lens1, size1, T_B0 = _asl_camera(docs[0], paths[0])
    K2, D2, lens2, size2, T_B1 = _asl_camera(docs[1], paths[1])
    if lens1 != lens2:
        raise CalibrationError(f"{paths[0]} and {paths[1]} have different distortion models; one rig needs one", path=str(paths[0]))
    if size1 != size2:
        raise CalibrationError(
            f"{paths[0]} is {size1[0]}x{size1[1]} but {paths[1]} is {size2[0]}x{size2[1]}; both eyes must have one size",
            path=str(paths[0]),
        )
    # X_B = T_B0 X_0 = T_B1 X_1, so X_1 = T_B1^-1 T_B0 X_0.
    T_10 = np.linalg.inv(T_B1) @ T_B0
    calib = StereoCalibration(K1, D1, K2, D2, T_10[:3, :3], T_10[:3, 3], size1, source=f"{paths[0]} + {paths[1]}", model=lens1)
    return ImportedCalibration(calib, "asl", (paths[0], paths[1]))


# ------------------------------------------------------------------------------------------------ ROS camera_info


@dataclass(frozen=True)
class _RosEye:
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    lens: str
    size: tuple[int, int]


def _ros_field(doc: Mapping[str, Any], names: tuple[str, ...], where: str, path: Path) -> Any:
    for name in names:
        if name in doc and doc[name] is not None:
            return doc[name]
    raise CalibrationError(f"{path} is missing {where}{' or '.join(names)}", path=str(path), key=names[0])


def _ros_eye(doc: Mapping[str, Any], path: Path) -> _RosEye:
    K = _numbers(_ros_field(doc, ("camera_matrix", "K", "k"), "", path), "K", path, 9).reshape(3, 3)
    D = _numbers(_ros_field(doc, ("distortion_coefficients", "D", "d"), "", path), "D", path)
    R = _numbers(_ros_field(doc, ("rectification_matrix", "R", "r"), "", path), "R", path, 9).reshape(3, 3)
    P = _numbers(_ros_field(doc, ("projection_matrix", "P", "p"), "", path), "P", path, 12).reshape(3, 4)
    model = str(doc.get("distortion_model") or "").strip().lower()
    lens = _ROS_DISTORTION.get(model)
    if lens is None:
        raise CalibrationError(
            f"{path}: distortion_model is {model!r}, which the pipeline cannot rectify (plumb_bob, rational_polynomial "
            "or equidistant)",
            path=str(path),
            key="distortion_model",
        )
    if D.size == 0 or not np.any(D):
        D = np.zeros(4 if lens == "fisheye" else 5)
    elif lens == "pinhole" and D.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{path}: D has {D.size} coefficients; plumb_bob has 5, rational_polynomial 8", path=str(path), key="D")
    w = _ros_field(doc, ("image_width", "width"), "", path)
    h = _ros_field(doc, ("image_height", "height"), "", path)
    size = _size([w, h], "image_width/image_height", path)
    return _RosEye(K, D, R, P, lens, size)


def camera_info_calibration(left: Mapping[str, Any], right: Mapping[str, Any], left_name: str, right_name: str) -> tuple[StereoCalibration, bool]:
    """The rig of two ``camera_info`` messages or files (module doc).

    Args:
        left, right: the two eyes' fields (``K D R P distortion_model width height`` in any of the
            spellings of the module doc); the order is checked, not trusted.
        left_name, right_name: where each came from (a file or a topic), for messages.

    Returns:
        ``(calibration, swapped)``: ``swapped`` when the eye given as left has the baseline in its ``P``
        (it is the right eye).

    Raises:
        CalibrationError: a missing field (named), a lens model the pipeline cannot rectify, eyes of two
            sizes, or no baseline in either ``P``.
    """
    a, b = _ros_eye(left, Path(left_name)), _ros_eye(right, Path(right_name))
    swapped = False
    if abs(a.P[0, 3]) > 1e-9 and abs(b.P[0, 3]) <= 1e-9:
        a, b, swapped = b, a, True
        left_name, right_name = right_name, left_name
    if abs(b.P[0, 3]) <= 1e-9:
        raise CalibrationError(
            f"{left_name} and {right_name}: neither projection matrix holds a baseline (P[0,3] = 0 in both): these "
            "are two monocular calibrations, not a stereo pair",
            path=left_name,
            key="P",
        )
    if a.lens != b.lens:
        raise CalibrationError(f"{left_name} and {right_name} have different distortion models; one rig needs one", path=left_name)
    if a.size != b.size:
        raise CalibrationError(
            f"{left_name} is {a.size[0]}x{a.size[1]} but {right_name} is {b.size[0]}x{b.size[1]}; both eyes must have one size",
            path=left_name,
        )
    # In the rectified frames the right eye sits at -Tx along x: X_rect_r = X_rect_l + t_rect.
    t_rect = np.array(
        [b.P[0, 3] / b.P[0, 0] - a.P[0, 3] / a.P[0, 0], b.P[1, 3] / b.P[1, 1] - a.P[1, 3] / a.P[1, 1], 0.0]
    )
    R = b.R.T @ a.R
    T = b.R.T @ t_rect
    calib = StereoCalibration(a.K, a.D, b.K, b.D, R, T, a.size, source=f"{left_name} + {right_name}", model=a.lens)
    return calib, swapped


def _from_ros(docs: Sequence[Mapping[str, Any]], paths: Sequence[Path]) -> ImportedCalibration:
    if len(docs) != 2:
        raise CalibrationError(
            f"{paths[0]} is one eye's camera_info; give both: the left's and then the right's", path=str(paths[0])
        )
    calib, swapped = camera_info_calibration(docs[0], docs[1], str(paths[0]), str(paths[1]))
    notes = (f"{paths[1].name} is the left eye (its P has no baseline), {paths[0].name} the right",) if swapped else ()
    files = (paths[1], paths[0]) if swapped else (paths[0], paths[1])
    return ImportedCalibration(calib, "ros", files, notes)


# ------------------------------------------------------------------------------------------------ OpenCV


def _from_opencv(
    docs: Sequence[Mapping[str, Any]], paths: Sequence[Path], image_size: tuple[int, int] | None, t_units: str | None
) -> ImportedCalibration:
    merged: dict[str, Any] = {}
    for doc in docs:
        merged.update(doc)
    where = " + ".join(str(p) for p in paths)
    values: dict[str, Any] = {}
    for key, names in _OPENCV_ALIASES.items():
        found = next((n for n in names if merged.get(n) is not None), None)
        if found is None:
            also = f" (or {', '.join(names[1:])})" if len(names) > 1 else ""
            raise CalibrationError(f"{where} is missing {key}{also}", path=str(paths[0]), key=key)
        values[key] = merged[found]
    size: tuple[int, int] | None = None
    for key in ("image_size", "imageSize"):
        if merged.get(key) is not None:
            size = _size(merged[key], key, paths[0])
            break
    if size is None and merged.get("image_width") is not None and merged.get("image_height") is not None:
        size = _size([merged["image_width"], merged["image_height"]], "image_width/image_height", paths[0])
    if size is None:
        size = image_size
    elif image_size is not None and tuple(image_size) != size:
        raise CalibrationError(
            f"{where} is for {size[0]}x{size[1]}, not the {image_size[0]}x{image_size[1]} given", path=str(paths[0]), key="image_size"
        )
    if size is None:
        raise CalibrationError(
            f"{where} is missing image_size (or image_width and image_height); give the eye's size with --image-size WxH",
            path=str(paths[0]),
            key="image_size",
        )
    unit = str(merged.get("T_units") or t_units or "m").strip().lower()
    if unit not in _T_SCALE:
        raise CalibrationError(f"{where}: T_units = {unit!r}; expected m, cm or mm", path=str(paths[0]), key="T_units")
    T = _numbers(values["T"], "T", paths[0], 3) * _T_SCALE[unit]
    lens = str(merged.get("distortion_model") or "pinhole").strip().lower()
    calib = StereoCalibration(
        values["K1"], values["D1"], values["K2"], values["D2"], values["R"], T, size, source=where, model=lens
    )
    return ImportedCalibration(calib, "opencv", tuple(paths))


# ------------------------------------------------------------------------------------------------ entry point


def import_calibration(
    paths: Sequence[str | Path], *, image_size: tuple[int, int] | None = None, t_units: str | None = None
) -> ImportedCalibration:
    """Read one or two calibration files of a family of the module doc, told apart by their keys.

    Args:
        paths: one file (Kalibr, OpenCV) or two (ASL, ROS: the left eye's first; OpenCV: intrinsics and
            extrinsics).
        image_size: one eye's ``(width, height)``, pixels, for OpenCV files that do not hold it.
        t_units: the unit of an OpenCV file's T when it has no ``T_units`` (``m``, ``cm``, ``mm``).

    Raises:
        CalibrationError: one line: an unknown family, a missing key (named), a lens model the pipeline
            cannot rectify (named), two files of different families, a bad value.
    """
    files = [Path(p) for p in paths]
    if not 1 <= len(files) <= 2:
        raise CalibrationError(f"give one or two calibration files, not {len(files)}")
    docs = [read_document(p) for p in files]
    kinds = [detect_format(d) for d in docs]
    for path, kind in zip(files, kinds):
        if kind is None:
            raise CalibrationError(
                f"{path} is not a calibration this command knows: no cam0 (Kalibr), T_BS (ASL sensor.yaml), "
                "camera_matrix or K (ROS camera_info), or K1/M1 (OpenCV) key",
                path=str(path),
            )
    if len(set(kinds)) > 1:
        raise CalibrationError(
            f"{files[0]} is {FORMATS[kinds[0]]} but {files[1]} is {FORMATS[kinds[1]]}; give files of one kind", path=str(files[0])
        )
    kind = kinds[0]
    if kind == "kalibr":
        if len(files) > 1:
            raise CalibrationError(f"{files[0]} is a Kalibr camchain, which holds both eyes: give it alone", path=str(files[0]))
        return _from_kalibr(docs[0], files[0])
    if kind == "asl":
        return _from_asl(docs, files)
    if kind == "ros":
        return _from_ros(docs, files)
    return _from_opencv(docs, files, image_size, t_units)
