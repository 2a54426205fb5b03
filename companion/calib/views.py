"""Stereo images for calibration: from a folder (side-by-side frames, or left/right files) or captured
live from a camera source.

Folder layouts (``layout="auto"`` picks the first that fits):

* ``pair``: sub-folders ``left/`` and ``right/`` holding files of the same names, or files named
  ``NAME_left.EXT`` and ``NAME_right.EXT`` side by side;
* ``sbs``: every image in the folder is one side-by-side frame (left eye first), as ``companion
  record`` and the ZED write them.

Images: PNG, JPEG, BMP, TIFF; 8-bit grey or BGR. Every view must have the same size.
"""

from __future__ import annotations

import logging
import math
import re
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.core.calibrate import detect_board, pair_views
from companion.core.stereo import to_bgr
from companion.errors import CalibrationError, CameraError, InputError
from companion.interfaces import CameraSource

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
_SIDE = re.compile(r"^(?P<name>.*?)[_\-.](?P<side>left|right)$", re.IGNORECASE)


@dataclass(frozen=True)
class StereoImage:
    """One stereo view.

    Attributes:
        name: the file it came from (the side-by-side file, or the pair's common name).
        left, right: uint8 ``(H, W, 3)`` BGR eyes (grey files are converted).
    """

    name: str
    left: np.ndarray
    right: np.ndarray

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (int(self.left.shape[1]), int(self.left.shape[0]))

    def side_by_side(self) -> np.ndarray:
        """uint8 ``(H, 2W, 3)``, left eye first (the pipeline's frame)."""
        return np.ascontiguousarray(np.concatenate([self.left, self.right], axis=1))


def read_image(path: Path) -> np.ndarray:
    """An 8-bit image as BGR uint8 ``(H, W, 3)``.

    Raises:
        InputError: missing, undecodable, or not 8-bit (the message names the file).
    """
    import cv2

    if not path.is_file():
        raise InputError(f"{path}: no such file")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: not a readable image (OpenCV could not decode it)")
    if image.dtype != np.uint8:
        raise InputError(f"{path}: 8-bit images only, got {image.dtype}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return np.ascontiguousarray(image[:, :, :3])
    return image


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def detect_layout(folder: Path) -> str:
    """``pair`` or ``sbs`` (see the module doc)."""
    if (folder / "left").is_dir() and (folder / "right").is_dir():
        return "pair"
    if any(_SIDE.match(p.stem) for p in _images(folder)):
        return "pair"
    return "sbs"


def _pairs(folder: Path) -> list[tuple[str, Path, Path]]:
    if (folder / "left").is_dir() and (folder / "right").is_dir():
        lefts = {p.name: p for p in _images(folder / "left")}
        rights = {p.name: p for p in _images(folder / "right")}
        missing = sorted(set(lefts) ^ set(rights))
        if missing:
            raise InputError(
                f"{folder}: left/ and right/ must hold the same file names; unmatched: {', '.join(missing[:5])}"
                + (" ..." if len(missing) > 5 else "")
            )
        return [(name, lefts[name], rights[name]) for name in sorted(lefts)]
    sides: dict[str, dict[str, Path]] = {}
    for p in _images(folder):
        m = _SIDE.match(p.stem)
        if m is None:
            raise InputError(f"{p}: in a folder of left/right files every image must be NAME_left or NAME_right")
        sides.setdefault(m.group("name"), {})[m.group("side").lower()] = p
    unmatched = sorted(n for n, s in sides.items() if len(s) != 2)
    if unmatched:
        raise InputError(f"{folder}: no partner for {', '.join(unmatched[:5])}" + (" ..." if len(unmatched) > 5 else ""))
    return [(name, s["left"], s["right"]) for name, s in sorted(sides.items())]


def load_stereo_images(folder: Path, layout: str = "auto", *, swap_eyes: bool = False) -> list[StereoImage]:
    """Every view in ``folder``.

    Args:
        folder: the folder (see the module doc for the layouts).
        layout: ``auto``, ``sbs`` or ``pair``.
        swap_eyes: the camera puts the right eye first (or the files are named the wrong way round).

    Raises:
        InputError: no such folder, no images, an unreadable image, a file without its partner.
        CalibrationError: views of different sizes (mixed sizes), or a side-by-side frame of odd width.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder")
    if layout == "auto":
        layout = detect_layout(folder)
    views: list[StereoImage] = []
    if layout == "pair":
        for name, lp, rp in _pairs(folder):
            left, right = read_image(lp), read_image(rp)
            if left.shape != right.shape:
                raise CalibrationError(
                    f"mixed sizes: {lp} is {left.shape[1]}x{left.shape[0]} but {rp} is {right.shape[1]}x{right.shape[0]}"
                )
            views.append(StereoImage(name, left, right))
    elif layout == "sbs":
        for p in _images(folder):
            frame = read_image(p)
            if frame.shape[1] % 2:
                raise CalibrationError(f"{p}: a side-by-side frame must have an even width, got {frame.shape[1]}")
            half = frame.shape[1] // 2
            views.append(StereoImage(p.name, np.ascontiguousarray(frame[:, :half]), np.ascontiguousarray(frame[:, half:])))
    else:
        raise InputError(f"layout must be auto, sbs or pair, got {layout!r}")
    if not views:
        raise InputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    if swap_eyes:
        views = [StereoImage(v.name, v.right, v.left) for v in views]
    sizes: dict[tuple[int, int], list[str]] = {}
    for v in views:
        sizes.setdefault(v.eye_size_px, []).append(v.name)
    if len(sizes) > 1:
        parts = [f"{len(names)} with {w}x{h} eyes (e.g. {names[0]})" for (w, h), names in sorted(sizes.items(), key=lambda kv: -len(kv[1]))]
        raise CalibrationError(f"mixed sizes in {folder}: {'; '.join(parts)}; every view must come from one camera mode")
    return views


# --------------------------------------------------------------------------------------------------
# Live capture


@dataclass(frozen=True)
class _Seen:
    centre: tuple[float, float]
    area: float
    angle: float


def _board_signature(points: np.ndarray, image_size: tuple[int, int]) -> _Seen:
    import cv2

    w, h = image_size
    p = points.reshape(-1, 2)
    hull = cv2.convexHull(p.astype(np.float32))
    d = p[-1] - p[0]
    return _Seen(
        (float(p[:, 0].mean()) / w, float(p[:, 1].mean()) / h),
        float(cv2.contourArea(hull)) / float(w * h),
        math.degrees(math.atan2(float(d[1]), float(d[0]))),
    )


def _is_new(seen: _Seen, kept: Sequence[_Seen]) -> bool:
    for k in kept:
        moved = math.hypot(seen.centre[0] - k.centre[0], seen.centre[1] - k.centre[1])
        resized = max(seen.area, k.area) / max(min(seen.area, k.area), 1e-9)
        turned = abs((seen.angle - k.angle + 180.0) % 360.0 - 180.0)
        if moved < 0.1 and resized < 1.3 and turned < 10.0:
            return False
    return True


def capture_views(
    camera: CameraSource,
    board: object,
    count: int,
    *,
    on_kept: Callable[[int, StereoImage], None] = lambda i, v: None,
    stop: threading.Event | None = None,
    max_frames: int | None = None,
) -> list[StereoImage]:
    """Watch ``camera`` and keep ``count`` views that show the whole board in both eyes, each at a new
    place, size or angle in the image (a view too like one kept is skipped).

    Args:
        camera: an open camera source (side-by-side frames).
        board: a :class:`~companion.core.calibrate.BoardSpec`.
        count: views to keep.
        on_kept: called with (index, view) for each view kept (progress, saving).
        stop: set it to stop early (Ctrl-C).
        max_frames: give up after this many frames (tests); None = no limit.

    Returns:
        The views kept (fewer than ``count`` when stopped).

    Raises:
        CameraError: the camera failed.
    """
    kept: list[StereoImage] = []
    signatures: list[_Seen] = []
    frames = 0
    while len(kept) < count and (stop is None or not stop.is_set()):
        if max_frames is not None and frames >= max_frames:
            break
        frame = camera.read()
        frames += 1
        image = to_bgr(frame.image)  # board detection and the saved views need BGR (or grey)
        half = image.shape[1] // 2
        left, right = image[:, :half], image[:, half:]
        pair = pair_views(f"live_{len(kept):03d}", detect_board(left, board), detect_board(right, board))
        if isinstance(pair, str):
            continue
        seen = _board_signature(pair.left, (half, image.shape[0]))
        if not _is_new(seen, signatures):
            continue
        view = StereoImage(f"view_{len(kept):03d}.png", np.ascontiguousarray(left).copy(), np.ascontiguousarray(right).copy())
        kept.append(view)
        signatures.append(seen)
        on_kept(len(kept) - 1, view)
    return kept


def save_view(folder: Path, view: StereoImage) -> Path:
    """Write ``view`` as a side-by-side PNG ``folder/view.name``; returns the path.

    Raises:
        InputError: the file cannot be written.
    """
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / view.name
    if not cv2.imwrite(str(path), view.side_by_side()):
        raise InputError(f"{path}: cannot write the view")
    return path


def open_camera(camera: CameraSource) -> None:
    """Open a camera, as a one-line error naming it."""
    try:
        camera.open()
    except CameraError:
        raise
    except Exception as err:  # an OpenCV surprise: still one line
        raise CameraError(f"{camera.name}: cannot open: {type(err).__name__}: {err}") from None
