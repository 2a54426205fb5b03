"""The service's camera source over a recorded sequence (an ASL/EuRoC folder or a rosbag): what
``camera.source = "replay"`` reads when ``camera.replay_path`` is one (``companion record``'s own
recordings stay with :class:`companion.service.camera_replay.ReplayCamera`)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from companion.errors import CameraError, InputError
from companion.interfaces import Frame
from companion.pacing import RatePacer, RecordedPacer

__all__ = ["RecordedCamera"]

log = logging.getLogger(__name__)


class RecordedCamera:
    """Side-by-side BGR frames from a recorded sequence, at the recorded rate (its timestamps) or at
    ``rate_hz``; optionally looping. The end of a non-looping sequence raises a CameraError with
    ``ended=True`` (the capture thread then stops reopening it).

    Args:
        path: an ASL/EuRoC folder, a ``.bag``, or a ROS 2 bag (:func:`~companion.recorded.sequence.open_sequence`).
        width_px, height_px: the expected eye size (frames of another size are an error, never rescaled).
        rate_hz: deliver at this rate; None = at the recorded timestamps.
        loop: start again at the end.
        left_topic, right_topic: a bag's image topics (None: found by name).
        max_skew_ms: the most a left and a right frame's times may differ to make a pair.
        clock: the frames' clock (monotonic seconds).
    """

    def __init__(
        self,
        path: Path,
        width_px: int,
        height_px: int,
        *,
        rate_hz: float | None = None,
        loop: bool = False,
        left_topic: str | None = None,
        right_topic: str | None = None,
        max_skew_ms: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name = f"replay:{path}"
        self.path = Path(path)
        self.width_px = width_px
        self.height_px = height_px
        self.rate_hz = rate_hz
        self.loop = loop
        self.left_topic = left_topic
        self.right_topic = right_topic
        self.max_skew_ms = max_skew_ms
        self._clock = clock
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._sequence: Any = None
        self._pairs: Iterator[Any] | None = None
        self._seq = 0
        self._at_recorded = RecordedPacer(clock, self._stop, unit_s=1e-9)
        self._at_rate = RatePacer(1.0 / rate_hz, clock, self._stop) if rate_hz is not None else None

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (self.width_px, self.height_px)

    def open(self) -> None:
        """Open the sequence. Raises CameraError (``ended=True``: retrying will not help)."""
        from companion.recorded.sequence import open_sequence

        self.close()
        self._stop.clear()
        try:
            seq = open_sequence(
                self.path, left_topic=self.left_topic, right_topic=self.right_topic, max_skew_ms=self.max_skew_ms
            )
        except InputError as err:
            raise CameraError(f"{self.name}: {err}", ended=True) from None
        with self._lock:
            self._sequence = seq
            self._pairs = seq.pairs()
        self._at_recorded.restart()
        if self._at_rate is not None:
            self._at_rate.restart()
        log.info("%s: open (%s, topics %s and %s)", self.name, seq.kind, *seq.topics)

    def _next_pair(self) -> Any:
        with self._lock:
            if self._pairs is None:
                raise CameraError(f"{self.name}: not open")
            try:
                return next(self._pairs)
            except StopIteration:
                pass
            report = self._sequence.report
            if not self.loop or report.pairs == 0:
                log.info("%s: end of the recording: %s", self.name, report.summary())
                raise CameraError(f"{self.name}: end of the recording ({report.summary()})", ended=True) from None
            self._pairs = self._sequence.pairs()
            self._at_recorded.restart()
            try:
                return next(self._pairs)
            except StopIteration:
                raise CameraError(f"{self.name}: the recording has no pairs", ended=True) from None

    def read(self) -> Frame:
        """The next pair as one uint8 ``(H, 2W, 3)`` BGR frame, stamped with ``clock()`` when delivered.

        Raises:
            CameraError: not open, the end of the recording (``ended=True``), or a frame of another size.
        """
        import cv2

        from companion.errors import FrameError
        from companion.recorded.sequence import side_by_side

        while True:
            pair = self._next_pair()
            h, w = pair.left.shape[:2]
            if (w, h) != (self.width_px, self.height_px):
                raise CameraError(
                    f"{self.name}: the recording's eyes are {w}x{h}, but camera.width_px x height_px is "
                    f"{self.width_px}x{self.height_px}",
                    ended=True,
                )
            try:
                image = side_by_side(pair.left, pair.right)
                break
            except FrameError as err:  # one bad pair is skipped, as a camera drops a frame
                log.warning("%s: pair %d skipped: %s", self.name, pair.index, err)
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        self._wait_for(pair.timestamp_ns)
        self._seq += 1
        return Frame(image=np.ascontiguousarray(image), timestamp_s=self._clock(), seq=self._seq)

    def _wait_for(self, t_ns: int) -> None:
        if self._at_rate is None:
            self._at_recorded.wait(t_ns)
        else:
            self._at_rate.wait()

    def close(self) -> None:
        """Stop waiting and release the sequence (safe to call twice)."""
        self._stop.set()
        with self._lock:
            pairs, self._pairs = self._pairs, None
            seq, self._sequence = self._sequence, None
        if pairs is not None and hasattr(pairs, "close"):
            pairs.close()  # runs the reader's cleanup (a bag is closed)
        if seq is not None:
            seq.close()
