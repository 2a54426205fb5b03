"""The ``replay`` camera source: a recording of the service's own (a folder of PNGs, or a video with its
timestamps) played back at its recorded rate or a given one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from companion.errors import CameraError
from companion.interfaces import Frame
from companion.pacing import RatePacer, RecordedPacer
from companion.service.camera_frame import check_frame

log = logging.getLogger(__name__)

Clock = Callable[[], float]


class ReplayCamera:
    """Frames from a recording (see :mod:`companion.service.recording`), at the recorded rate (its
    timestamps) or at ``rate_hz``; optionally looping. The end of a non-looping recording raises a
    CameraError with ``ended=True`` in its context (the capture thread then stops reopening it).

    Args:
        path: the recording (a folder of PNGs with timestamps.csv, or an .mkv/.avi with its sidecar).
        width_px, height_px: the expected eye size (a recording of another size is an error).
        rate_hz: deliver at this rate; None = the recorded timestamps (``fallback_fps_hz`` without them).
        loop: start again at the end.
        preload: decode every frame at open (costs memory: H·2W·3 bytes a frame).
    """

    def __init__(
        self,
        path: Path,
        width_px: int,
        height_px: int,
        *,
        rate_hz: float | None = None,
        fallback_fps_hz: float = 30.0,
        loop: bool = False,
        preload: bool = False,
        clock: Clock = time.monotonic,
    ) -> None:
        self.name = f"replay:{path}"
        self.path = Path(path)
        self.width_px = width_px
        self.height_px = height_px
        self.rate_hz = rate_hz
        self.fallback_fps_hz = fallback_fps_hz
        self.loop = loop
        self.preload = preload
        self._clock = clock
        self._stop = threading.Event()
        self._video = None
        self._files: list[Path] = []
        self._frames: list[np.ndarray] | None = None
        self._times: np.ndarray | None = None
        self._index = 0
        self._seq = 0
        self._at_recorded = RecordedPacer(clock, self._stop)
        self._pacer: RatePacer | None = None
        self._opened = False

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (self.width_px, self.height_px)

    @property
    def frame_count(self) -> int:
        if self._frames is not None:
            return len(self._frames)
        return len(self._files) if self._files else (len(self._times) if self._times is not None else 0)

    def open(self) -> None:
        from companion.service.recording import VIDEO_SUFFIXES, read_timestamps

        self.close()
        self._stop.clear()
        p = self.path
        if not p.exists():
            # Permanent: retrying will not make it appear (the capture thread stops on ended=True).
            raise CameraError(f"{self.name}: no such recording", ended=True)
        ts = read_timestamps(p)
        self._times = ts.timestamp_s if ts is not None else None
        if p.is_dir():
            self._files = sorted(p.glob("frame_*.png"))
            if not self._files:
                raise CameraError(f"{self.name}: no frame_*.png in the folder", ended=True)
            if self._times is not None and len(self._times) != len(self._files):
                raise CameraError(
                    f"{self.name}: {len(self._files)} frames but {len(self._times)} timestamps"
                )
        elif p.suffix.lower() in VIDEO_SUFFIXES:
            self._open_video()
        else:
            raise CameraError(
                f"{self.name}: not a recording (a folder, or a {'/'.join(VIDEO_SUFFIXES)} file)", ended=True
            )
        if self.preload:
            frames = []
            while True:
                image = self._decode_next(allow_end=True)
                if image is None:
                    break
                frames.append(image)
            if not frames:
                raise CameraError(f"{self.name}: the recording has no frames")
            self._frames = frames
            self._release_video()
        self._index = 0
        self._at_recorded.restart()
        period = 1.0 / (self.rate_hz or self.fallback_fps_hz)
        self._pacer = RatePacer(period, self._clock, self._stop)
        self._opened = True
        log.info("%s: open (%s)", self.name, "preloaded" if self.preload else "streaming from disk")

    def _open_video(self) -> None:
        import cv2

        self._release_video()
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise CameraError(f"{self.name}: OpenCV cannot open the video")
        self._video = cap

    def _release_video(self) -> None:
        video, self._video = self._video, None
        if video is not None:
            video.release()

    def _decode_next(self, allow_end: bool) -> np.ndarray | None:
        """The frame at ``self._index`` (advancing it), or None at the end."""
        import cv2

        i = self._index
        if self._frames is not None:
            if i >= len(self._frames):
                return None
            self._index += 1
            return self._frames[i]
        if self._files:
            if i >= len(self._files):
                return None
            image = cv2.imread(str(self._files[i]), cv2.IMREAD_COLOR)
            if image is None:
                raise CameraError(f"{self.name}: cannot decode {self._files[i].name}")
        else:
            if self._video is None:
                return None
            ok, image = self._video.read()
            if not ok:
                return None
        self._index += 1
        return check_frame(image, f"{self.name} frame {i}", self.width_px, self.height_px)

    def _rewind(self) -> None:
        self._index = 0
        if self._video is not None:
            self._open_video()

    def read(self) -> Frame:
        if not self._opened:
            raise CameraError(f"{self.name}: not open")
        index = self._index
        image = self._decode_next(allow_end=True)
        if image is None:
            if not self.loop:
                raise CameraError(f"{self.name}: end of the recording", ended=True)
            self._rewind()
            self._at_recorded.restart()
            index = 0
            image = self._decode_next(allow_end=False)
            if image is None:
                raise CameraError(f"{self.name}: the recording has no frames", ended=True)
        self._wait_for(index)
        t = self._clock()
        self._seq += 1
        return Frame(image=image, timestamp_s=t, seq=self._seq)

    def _wait_for(self, index: int) -> None:
        if self.rate_hz is None and self._times is not None and index < len(self._times):
            self._at_recorded.wait(float(self._times[index]))  # at the recorded timestamps
            return
        assert self._pacer is not None
        self._pacer.wait()

    def close(self) -> None:
        self._stop.set()
        self._release_video()
        self._opened = False

