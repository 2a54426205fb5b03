"""The capture and pipeline threads: blocking camera reads, handing over only the newest frame.

:class:`FrameMailbox` is a one-slot mailbox: ``put`` replaces a frame nobody took (and counts it as
dropped), ``take`` removes the frame, so a frame is handed over at most once and the queue can never
grow. :class:`CaptureThread` reads the camera in a loop, puts each frame in the mailbox, and when the
camera disappears closes it and reopens it with a doubling back-off (``reconnect_initial_s`` ..
``reconnect_max_s``), reporting its status for the health message.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass

from companion.errors import CameraError
from companion.interfaces import CameraSource, Frame
from companion.service.backoff import LogBackoff

log = logging.getLogger(__name__)


class FrameMailbox:
    """One slot holding the newest unconsumed frame. Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Condition(threading.Lock())
        self._frame: Frame | None = None
        self._kicked = False
        self._overwritten = 0
        self._put = 0
        self._taken = 0
        self._last_put_s: float | None = None
        self._interval_s: float | None = None

    def put(self, frame: Frame) -> bool:
        """Store ``frame``; returns True if it replaced one that was never taken (a dropped frame)."""
        with self._lock:
            dropped = self._frame is not None
            if dropped:
                self._overwritten += 1
            self._frame = frame
            self._put += 1
            if self._last_put_s is not None:
                dt = frame.timestamp_s - self._last_put_s
                if 0.0 < dt < 1.0:  # a gap (reconnect, pause) says nothing about the rate
                    self._interval_s = dt if self._interval_s is None else 0.9 * self._interval_s + 0.1 * dt
            self._last_put_s = frame.timestamp_s
            self._lock.notify_all()
            return dropped

    @property
    def interval_s(self) -> float | None:
        """The camera's frame interval (moving average of capture-time differences), seconds."""
        with self._lock:
            return self._interval_s

    def take(self) -> Frame | None:
        """Remove and return the newest frame, or None if there is none (never the same frame twice)."""
        with self._lock:
            return self._take_locked()

    def _take_locked(self) -> Frame | None:
        frame, self._frame = self._frame, None
        if frame is not None:
            self._taken += 1
        return frame

    def wait_take(self, timeout_s: float) -> Frame | None:
        """Block until a frame is there (and take it), :meth:`kick` is called, or ``timeout_s`` passes."""
        with self._lock:
            if self._frame is None and not self._kicked:
                self._lock.wait_for(lambda: self._frame is not None or self._kicked, timeout_s)
            self._kicked = False
            return self._take_locked()

    def kick(self) -> None:
        """Wake a :meth:`wait_take` without a frame (the consumer has other work, or must stop)."""
        with self._lock:
            self._kicked = True
            self._lock.notify_all()

    @property
    def overwritten(self) -> int:
        """Frames replaced before anyone took them."""
        with self._lock:
            return self._overwritten

    def counts(self) -> tuple[int, int, int]:
        """(put, taken, overwritten) so far."""
        with self._lock:
            return self._put, self._taken, self._overwritten


@dataclass(frozen=True)
class CaptureStatus:
    """What the capture thread reports (health's ``camera`` object).

    Attributes:
        state: opening / streaming / reconnecting / ended / stopped.
        frames: frames read from the source.
        source_gaps: frames the source itself skipped (gaps in Frame.seq).
        overwritten: frames replaced in the mailbox before processing took them.
        reconnects: successful reopenings after a loss.
        last_error: the last camera error's message, or None.
        fps: frames read per second over the last second.
        skew_ms: a two-camera source's skew between the eyes (``PairCamera.skew_status``), else None.
    """

    source: str
    state: str
    frames: int
    source_gaps: int
    overwritten: int
    reconnects: int
    last_error: str | None
    fps: float
    skew_ms: dict | None = None

    @property
    def ok(self) -> bool:
        return self.state == "streaming"

    @property
    def dropped(self) -> int:
        """Frames captured (or skipped by the source) that were never processed."""
        return self.source_gaps + self.overwritten


class CaptureThread:
    """Reads ``source`` in a daemon thread and puts each frame into ``mailbox``.

    Args:
        source: the camera (opened here, with retries).
        mailbox: where the newest frame goes.
        on_frame: called (in this thread) after each put: wake the consumer.
        on_status: called (in this thread) when the state changes (streaming, reconnecting, ...).
        reconnect_initial_s, reconnect_max_s: the back-off between reopen attempts, seconds.
    """

    def __init__(
        self,
        source: CameraSource,
        mailbox: FrameMailbox,
        *,
        on_frame: Callable[[], None] = lambda: None,
        on_status: Callable[[str], None] = lambda state: None,
        reconnect_initial_s: float = 0.2,
        reconnect_max_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.source = source
        self.mailbox = mailbox
        self._on_frame = on_frame
        self._on_status = on_status
        self._initial = reconnect_initial_s
        self._max = reconnect_max_s
        self._clock = clock
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._state = "opening"
        self._frames = 0
        self._gaps = 0
        self._reconnects = 0
        self._last_error: str | None = None
        self._last_seq: int | None = None
        self._recent: list[float] = []
        self._first_frame = threading.Event()

    # ------------------------------------------------------------------ control

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="capture", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop reading and release the camera.

        The thread closes the camera itself when it leaves its loop (closing it from here while a
        read is in progress could free a buffer under OpenCV). Only if it is still blocked after
        ``timeout_s`` is the camera closed from here, as a last resort.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            if self._thread.is_alive():
                log.warning("%s: capture thread still blocked after %.1f s; closing the camera anyway",
                            self.source.name, timeout_s)
                self._close_quietly()
        else:
            self._close_quietly()
        self._set_state("stopped")

    def wait_first_frame(self, timeout_s: float) -> bool:
        """Block until the first frame was read (True) or ``timeout_s`` passed (False)."""
        return self._first_frame.wait(timeout_s)

    def status(self) -> CaptureStatus:
        now = self._clock()
        skew = getattr(self.source, "skew_status", None)
        skew_ms = skew() if callable(skew) else None
        with self._lock:
            recent = [t for t in self._recent if now - t <= 1.0]
            return CaptureStatus(
                source=self.source.name,
                state=self._state,
                frames=self._frames,
                source_gaps=self._gaps,
                overwritten=self.mailbox.overwritten,
                reconnects=self._reconnects,
                last_error=self._last_error,
                fps=float(len(recent)),
                skew_ms=skew_ms,
            )

    # ------------------------------------------------------------------ the thread

    def _set_state(self, state: str, error: str | None = None) -> None:
        with self._lock:
            changed = state != self._state
            self._state = state
            if error is not None:
                self._last_error = error
        if changed:
            try:
                self._on_status(state)
            except Exception:
                log.exception("capture status callback failed")

    def _open_with_backoff(self, reconnecting: bool) -> bool:
        """Open the source, retrying with a doubling delay; False when stopped, or when the source
        says retrying is pointless (a CameraError with ``ended=True``: a recording that is not there).
        The failures are logged at once, then less and less often (:class:`LogBackoff`)."""
        delay = self._initial
        reports = LogBackoff(first_interval_s=max(self._max, 1.0), max_interval_s=max(self._max, 600.0))
        while not self._stop.is_set():
            try:
                self.source.open()
                if reconnecting:
                    with self._lock:
                        self._reconnects += 1
                    log.info("%s: camera back", self.source.name)
                self._last_seq = None
                self._set_state("streaming")
                return True
            except CameraError as err:
                if err.context.get("ended"):
                    log.error("%s; not retrying", err)
                    self._set_state("ended", str(err))
                    return False
                self._set_state("reconnecting" if reconnecting else "opening", str(err))
                if reports.due(self._clock()):
                    more = f"; {reports.suppressed} more failures since the last report" if reports.suppressed else ""
                    log.warning("%s; retrying in %.1f s (reported again in %.0f s if it goes on%s)",
                                err, delay, reports.interval_s, more)
                else:
                    log.debug("%s; retrying in %.1f s", err, delay)
            except Exception as err:  # a bug or an OpenCV surprise: keep flying safely, keep trying
                log.exception("%s: unexpected error while opening", self.source.name)
                self._set_state("reconnecting" if reconnecting else "opening", f"{type(err).__name__}: {err}")
            self._stop.wait(delay)
            delay = min(self._max, delay * 2.0)
        return False

    def _run(self) -> None:
        try:
            self._loop()
        finally:
            self._close_quietly()

    def _loop(self) -> None:
        if not self._open_with_backoff(reconnecting=False):
            return
        while not self._stop.is_set():
            try:
                frame = self.source.read()
            except CameraError as err:
                if self._stop.is_set():
                    return
                ended = bool(err.context.get("ended"))
                log.warning("%s", err)
                self._set_state("ended" if ended else "reconnecting", str(err))
                self._close_quietly()
                if ended:
                    return
                if not self._open_with_backoff(reconnecting=True):
                    return
                continue
            except Exception as err:
                if self._stop.is_set():
                    return
                log.exception("%s: unexpected error while reading", self.source.name)
                self._set_state("reconnecting", f"{type(err).__name__}: {err}")
                self._close_quietly()
                if not self._open_with_backoff(reconnecting=True):
                    return
                continue
            self._count(frame)
            self.mailbox.put(frame)
            self._first_frame.set()
            try:
                self._on_frame()
            except Exception:
                log.exception("capture frame callback failed")

    def _count(self, frame: Frame) -> None:
        now = self._clock()
        with self._lock:
            self._frames += 1
            if self._last_seq is not None and frame.seq > self._last_seq + 1:
                self._gaps += frame.seq - self._last_seq - 1
            self._last_seq = frame.seq
            self._recent.append(now)
            if len(self._recent) > 512:
                self._recent = [t for t in self._recent if now - t <= 1.0]

    def _close_quietly(self) -> None:
        try:
            self.source.close()
        except Exception:
            log.exception("%s: error while closing the camera", self.source.name)


class ProcessingThread:
    """Runs the pipeline on the newest frame, one at a time, in its own thread.

    It takes frames straight from the mailbox (no hop through the event loop, so a frame that arrives
    while the thread is idle is processed at once) and hands each outcome to ``on_result(frame,
    result, error)`` (called in this thread: post it to the loop). Between frames it runs the jobs
    given to :meth:`submit` (build the pipeline, reconfigure it, reset its filter): they are
    serialised with processing, so a reconfigure never races a frame, and the pipeline is built and
    used by the same thread (CuPy's current device is per thread).

    Late frames: when the thread becomes free and the frame waiting for it has already waited longer
    than half a frame interval, the next frame is due sooner than this one is old; with
    ``skip_late_frames`` the thread waits for that one instead (up to 1.25 intervals, else it takes
    the late frame after all) and counts the late one in :attr:`skipped`. A pipeline slower than the
    camera then processes fewer frames, each with a bounded wait, instead of every frame after a
    wait that grows with the backlog of the previous one.

    Args:
        mailbox: where the capture thread puts frames.
        process: frame -> result (runs in this thread).
        on_result: called after every frame with (frame, result or None, exception or None).
        skip_late_frames: see above.
        clock: the clock of the frame timestamps, seconds.
    """

    def __init__(
        self,
        mailbox: FrameMailbox,
        process: Callable[[Frame], object],
        on_result: Callable[[Frame, object | None, BaseException | None], None],
        *,
        skip_late_frames: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.mailbox = mailbox
        self._process = process
        self._on_result = on_result
        self.skip_late_frames = skip_late_frames
        self._clock = clock
        self._skipped = 0
        self._skipped_lock = threading.Lock()
        self._jobs: collections.deque[tuple[Future, Callable[..., object], tuple]] = collections.deque()
        self._jobs_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.processing_enabled = threading.Event()  # frames wait in the mailbox until set

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="pipeline", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., object], *args: object) -> Future:
        """Run ``fn(*args)`` in this thread before the next frame; the future gets its outcome."""
        fut: Future = Future()
        with self._jobs_lock:
            if self._stop.is_set():
                fut.set_exception(RuntimeError("the pipeline thread is stopped"))
                return fut
            self._jobs.append((fut, fn, args))
        self.mailbox.kick()
        return fut

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self.mailbox.kick()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error("pipeline thread still busy after %.1f s", timeout_s)
        with self._jobs_lock:
            jobs, self._jobs = list(self._jobs), collections.deque()
        for fut, _, _ in jobs:
            fut.cancel()

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._jobs_lock:
                job = self._jobs.popleft() if self._jobs else None
            if job is not None:
                fut, fn, args = job
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn(*args))
                    except BaseException as err:  # handed to whoever awaits the job
                        fut.set_exception(err)
                continue
            if not self.processing_enabled.is_set():
                self._stop.wait(0.01)
                continue
            frame = self.mailbox.wait_take(0.2)
            if frame is None or self._stop.is_set():
                continue
            if self.skip_late_frames:
                frame = self._fresher(frame)
            try:
                result = self._process(frame)
            except Exception as err:  # reported with context by on_result; processing goes on
                self._safe_report(frame, None, err)
                continue
            self._safe_report(frame, result, None)

    @property
    def skipped(self) -> int:
        """Frames taken from the mailbox but not processed because a fresher one was due sooner."""
        with self._skipped_lock:
            return self._skipped

    def _fresher(self, frame: Frame) -> Frame:
        interval = self.mailbox.interval_s
        if interval is None or interval > 0.25:
            return frame  # rate unknown, or slow enough that no frame waits long
        waited = self._clock() - frame.timestamp_s
        if waited <= 0.5 * interval:
            return frame
        newer = self.mailbox.wait_take(interval - waited + 0.25 * interval)
        if newer is None or self._stop.is_set():
            return frame  # the next one did not come (or a job is waiting): the late one it is
        with self._skipped_lock:
            self._skipped += 1
        return newer

    def _safe_report(self, frame: Frame, result: object | None, err: BaseException | None) -> None:
        try:
            self._on_result(frame, result, err)
        except Exception:
            log.exception("pipeline result callback failed")
