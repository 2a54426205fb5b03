"""The recording format shared by ``companion record`` (writer) and the ``replay`` camera (reader).

A recording is either

* a folder: ``frame_000000.png``, ``frame_000001.png``, ... (lossless side-by-side BGR frames) and
  ``timestamps.csv``; or
* a video file ``NAME.mkv`` (FFV1, lossless) or ``NAME.avi`` with ``NAME.mkv.timestamps.csv`` beside it.

``timestamps.csv`` has a header ``index,timestamp_s,seq``: the frame's position in the recording, its
capture time (the recording process's monotonic clock, seconds; only differences matter) and the
source's sequence number (a gap means the source dropped frames).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.errors import CameraError, InputError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mkv", ".avi")
TIMESTAMPS_NAME = "timestamps.csv"
_HEADER = ["index", "timestamp_s", "seq"]


def timestamps_path(recording: Path) -> Path:
    """Where the timestamps of ``recording`` (a folder or a video file) live."""
    if recording.suffix.lower() in VIDEO_SUFFIXES:
        return recording.with_name(recording.name + ".timestamps.csv")
    return recording / TIMESTAMPS_NAME


def frame_path(folder: Path, index: int) -> Path:
    return folder / f"frame_{index:06d}.png"


@dataclass(frozen=True)
class Timestamps:
    """Per-frame capture times (float64 ``(N,)`` seconds) and source sequence numbers (int64 ``(N,)``)."""

    timestamp_s: np.ndarray
    seq: np.ndarray


def read_timestamps(recording: Path) -> Timestamps | None:
    """The recording's timestamps, or None when it has no timestamps file.

    Raises:
        CameraError: the file exists but is malformed (names the file and the line).
    """
    path = timestamps_path(recording)
    if not path.exists():
        return None
    times: list[float] = []
    seqs: list[int] = []
    try:
        with path.open(encoding="utf-8", newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header != _HEADER:
                raise CameraError(f"{path}: expected the header {','.join(_HEADER)}, got {header}")
            for line_no, row in enumerate(reader, start=2):
                try:
                    _, t, s = row
                    times.append(float(t))
                    seqs.append(int(s))
                except ValueError:
                    raise CameraError(f"{path}:{line_no}: expected index,timestamp_s,seq, got {row}") from None
    except OSError as err:
        raise CameraError(f"{path}: cannot read timestamps: {err.strerror or err}") from None
    ts = np.asarray(times, np.float64)
    if ts.size > 1 and np.any(np.diff(ts) < 0):
        raise CameraError(f"{path}: timestamps go backwards")
    return Timestamps(ts, np.asarray(seqs, np.int64))


class RecordingWriter:
    """Writes frames to a recording (see the module doc). Use as a context manager.

    Args:
        out: a folder (created; must be empty or new) or a ``.mkv``/``.avi`` file path.
        fps_hz: the nominal rate written into a video container, Hz.
    """

    def __init__(self, out: Path, fps_hz: float) -> None:
        self.out = out
        self.fps_hz = fps_hz
        self._video = None
        self._rows: list[tuple[int, float, int]] = []
        self._size: tuple[int, int] | None = None
        self._is_video = out.suffix.lower() in VIDEO_SUFFIXES
        if self._is_video:
            out.parent.mkdir(parents=True, exist_ok=True)
        else:
            if out.exists() and any(out.iterdir()):
                raise InputError(f"{out}: recording folder is not empty")
            out.mkdir(parents=True, exist_ok=True)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def frames(self) -> int:
        return len(self._rows)

    def write(self, image: np.ndarray, timestamp_s: float, seq: int) -> None:
        """Append one uint8 (H, 2W, 3) BGR side-by-side frame captured at ``timestamp_s``."""
        import cv2

        h, w = image.shape[:2]
        if self._size is None:
            self._size = (w, h)
            if self._is_video:
                fourcc = cv2.VideoWriter_fourcc(*"FFV1")
                self._video = cv2.VideoWriter(str(self.out), fourcc, float(self.fps_hz), (w, h))
                if not self._video.isOpened():
                    raise InputError(f"{self.out}: OpenCV cannot write FFV1 video here; record to a folder instead")
        elif self._size != (w, h):
            raise InputError(f"{self.out}: frame size changed from {self._size} to {(w, h)}")
        index = len(self._rows)
        if self._video is not None:
            self._video.write(image)
        elif not cv2.imwrite(str(frame_path(self.out, index)), image):
            raise InputError(f"{frame_path(self.out, index)}: cannot write PNG")
        self._rows.append((index, float(timestamp_s), int(seq)))

    def close(self) -> None:
        if self._video is not None:
            self._video.release()
            self._video = None
        path = timestamps_path(self.out)
        with path.open("w", encoding="utf-8", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(_HEADER)
            for index, t, s in self._rows:
                writer.writerow([index, repr(t), s])
        log.info("recorded %d frames to %s (timestamps in %s)", len(self._rows), self.out, path)
