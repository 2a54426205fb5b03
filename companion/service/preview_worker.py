"""The preview's drawing and JPEG encoding, in a child process of their own.

Why a process and not the preview thread: the drawing (NumPy on the disparity, the overlay's Python)
holds the GIL in short bursts, and every burst can delay the pipeline and the control loop in the
service's threads. In a child process the flight loop shares nothing with it but the CPU, and the child
runs below the flight loop's priority (nice :data:`WORKER_NICE`) with one OpenCV thread, so the scheduler
serves the flight loop first, yet still gets enough of a busy machine to draw a few previews a second
(at nice 19 it got about 1.5 % of a core beside two busy processes: no picture at all). What the service's preview thread still does per preview: write the frame and the disparity into
a pipe (the kernel copies; the GIL is released) and read back the JPEG.

Protocol (private, both ends are this module): once its imports are done the child writes one byte
(:data:`_READY`), so a start-up slowed by a busy machine never counts against a preview's deadline; the
parent then writes ``<III`` (lengths of a pickled
:class:`_Job`, the frame's bytes, the disparity's bytes) followed by the three; the child answers
``<I`` and a pickled :class:`_Reply`. The child exits when its input closes (the service stopped or
died), so it never outlives the service.
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from companion.errors import CompanionError

log = logging.getLogger(__name__)

_JOB_HEADER = struct.Struct("<III")
_REPLY_HEADER = struct.Struct("<I")
#: The largest reply accepted (a JPEG preview is tens of kB), bytes.
_MAX_REPLY_BYTES = 64 << 20
#: What the child writes once it is ready for jobs.
_READY = b"R"
#: The child's niceness: below the service (0), far above idle work. Its demand is small (a few ms a
#: preview), so it takes only what it needs; the priority matters when the cores are contended: at nice
#: 19 (weight 15 against 1024 for nice 0) two busy loops left it about 1.5 % of a core, no picture at
#: all; at nice 5 (weight 335) it still gets its few per cent, and the flight loop 3x more than it.
WORKER_NICE = 5


class PreviewWorkerError(CompanionError):
    """The preview worker failed, hung or could not start; the message says which (it is restarted on
    a later preview)."""


class PreviewWorkerStarting(PreviewWorkerError):
    """The worker is still starting (importing): this preview is skipped; not a failure."""


@dataclass(frozen=True)
class _Job:
    inputs: Any  # companion.service.preview_frame.PreviewInputs with image and disparity set to None
    image_shape: tuple[int, ...]
    disparity_shape: tuple[int, ...] | None
    width_px: int
    quality: int


@dataclass(frozen=True)
class _Reply:
    jpeg: bytes
    draw_encode_ms: float
    height_px: int
    width_px: int
    error: str | None = None


class PreviewWorker:
    """Draws and encodes previews in a child process (started on the first :meth:`render`).

    Args:
        timeout_s: the longest one preview may take once the worker is ready (writing, drawing, reading
            back), seconds; a worker that takes longer is killed.
        startup_timeout_s: the longest the worker's start-up (its imports) may take, seconds; a preview
            asked for meanwhile is skipped (:class:`PreviewWorkerStarting`), not an error.
        restart_after_s: after a failure, no new worker is started for this long, seconds (a worker
            that crashes at once is not restarted five times a second).
        command: the child's command line (default: this Python, ``-m companion.service.preview_worker``).
    """

    def __init__(
        self,
        timeout_s: float = 10.0,
        restart_after_s: float = 2.0,
        command: list[str] | None = None,
        startup_timeout_s: float = 60.0,
    ) -> None:
        self.timeout_s = float(timeout_s)
        self.startup_timeout_s = float(startup_timeout_s)
        self._started_at = 0.0
        self._ready = False
        self._cancelled = False
        self.restart_after_s = float(restart_after_s)
        self._command = command or [sys.executable, "-m", __name__]
        self._proc: subprocess.Popen[bytes] | None = None
        self._retry_at = 0.0
        self.starts = 0

    def render(self, inputs: Any, width_px: int, quality: int) -> tuple[bytes, float, int, int]:
        """One preview: ``inputs`` (a :class:`companion.service.preview_frame.PreviewInputs`) drawn at ``width_px``
        and encoded at JPEG ``quality``.

        Returns:
            (JPEG bytes, the child's drawing and encoding time in ms, height px, width px).

        Raises:
            PreviewWorkerError: the worker could not start, failed, or took longer than ``timeout_s``
                (it is then stopped; the next call after ``restart_after_s`` starts a new one).
        """
        image = np.ascontiguousarray(inputs.image, dtype=np.uint8)
        disparity = inputs.disparity
        if disparity is not None:
            disparity = np.ascontiguousarray(disparity, dtype=np.float32)
        job = _Job(
            inputs=replace(inputs, image=None, disparity=None),
            image_shape=tuple(image.shape),
            disparity_shape=None if disparity is None else tuple(disparity.shape),
            width_px=int(width_px),
            quality=int(quality),
        )
        meta = pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL)
        parts = [meta, memoryview(image).cast("B"), memoryview(disparity).cast("B") if disparity is not None else b""]
        proc = self._ensure_started()
        if not self._ready:
            self._wait_ready(proc)
        deadline = time.monotonic() + self.timeout_s
        try:
            self._write(proc, [_JOB_HEADER.pack(*(len(p) for p in parts)), *parts], deadline)
            (n,) = _REPLY_HEADER.unpack(self._read(proc, _REPLY_HEADER.size, deadline))
            if n > _MAX_REPLY_BYTES:
                raise PreviewWorkerError(f"preview worker: a reply of {n} bytes (at most {_MAX_REPLY_BYTES})")
            reply = pickle.loads(self._read(proc, n, deadline))
        except PreviewWorkerError:
            self._fail()
            raise
        except (OSError, pickle.UnpicklingError, EOFError) as err:
            self._fail()
            raise PreviewWorkerError(f"preview worker: {type(err).__name__}: {err}") from None
        if reply.error is not None:
            raise PreviewWorkerError(f"preview worker: drawing failed: {reply.error}")
        return reply.jpeg, reply.draw_encode_ms, reply.height_px, reply.width_px

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the child (closing its input ends it; killed if it does not end). Safe twice."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        for stream in (proc.stdin, proc.stdout):
            if stream is not None:
                stream.close()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    # ------------------------------------------------------------------ internals

    def _ensure_started(self) -> subprocess.Popen[bytes]:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            return proc
        if proc is not None:
            self._fail()
            raise PreviewWorkerError(f"preview worker exited with {proc.returncode}")
        if time.monotonic() < self._retry_at:
            raise PreviewWorkerError("preview worker: waiting to restart after a failure")
        env = dict(os.environ)
        # The child imports this package from where the service found it, whatever its working folder.
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        try:
            proc = subprocess.Popen(self._command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, close_fds=True)
        except OSError as err:
            self._retry_at = time.monotonic() + self.restart_after_s
            raise PreviewWorkerError(f"preview worker could not start: {err}") from None
        assert proc.stdin is not None and proc.stdout is not None
        os.set_blocking(proc.stdin.fileno(), False)
        self._proc = proc
        self._ready = False
        self._started_at = time.monotonic()
        self.starts += 1
        log.info("preview worker started (pid %d)", proc.pid)
        return proc

    def _wait_ready(self, proc: subprocess.Popen[bytes]) -> None:
        """Wait for the child's ready byte (its imports), at most ``startup_timeout_s``; :meth:`cancel`
        ends the wait (:class:`PreviewWorkerStarting`)."""
        assert proc.stdout is not None
        fd = proc.stdout.fileno()
        while not self._cancelled:
            ready, _, _ = select.select([fd], [], [], 0.1)
            if ready:
                if os.read(fd, 1) == _READY:
                    self._ready = True
                    log.info("preview worker ready after %.1f s", time.monotonic() - self._started_at)
                    return
                self._fail()
                raise PreviewWorkerError(f"preview worker exited while starting (code {proc.poll()})")
            if time.monotonic() - self._started_at > self.startup_timeout_s:
                self._fail()
                raise PreviewWorkerError(f"preview worker: not started within {self.startup_timeout_s:g} s")
        raise PreviewWorkerStarting("preview worker: stopping while it started")

    def warm_up(self) -> None:
        """Start the worker now and wait until it is ready (a caller that knows a viewer is coming:
        the first picture then needs no start-up).

        Raises:
            PreviewWorkerError: it could not start.
        """
        proc = self._ensure_started()
        if not self._ready:
            self._wait_ready(proc)

    def cancel(self) -> None:
        """End a wait for the worker's start-up (another thread is stopping the preview)."""
        self._cancelled = True

    def _fail(self) -> None:
        """Stop a worker that failed; a new one may start after ``restart_after_s``."""
        proc, self._proc = self._proc, None
        self._retry_at = time.monotonic() + self.restart_after_s
        if proc is None:
            return
        if proc.poll() is None:
            proc.kill()
        for stream in (proc.stdin, proc.stdout):
            if stream is not None:
                try:
                    stream.close()
                except OSError:
                    log.debug("preview worker: closing a pipe after a failure", exc_info=True)
        try:
            proc.wait(1.0)
        except subprocess.TimeoutExpired:
            log.error("preview worker pid %d did not exit after SIGKILL", proc.pid)

    def _write(self, proc: subprocess.Popen[bytes], parts: list[Any], deadline: float) -> None:
        assert proc.stdin is not None
        fd = proc.stdin.fileno()
        for part in parts:
            view = memoryview(part).cast("B")
            while view:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise PreviewWorkerError(f"preview worker: not reading its input within {self.timeout_s:g} s")
                _, ready, _ = select.select([], [fd], [], left)
                if ready:
                    try:
                        view = view[os.write(fd, view) :]
                    except BlockingIOError:
                        continue

    def _read(self, proc: subprocess.Popen[bytes], n: int, deadline: float) -> bytes:
        assert proc.stdout is not None
        fd = proc.stdout.fileno()
        out = bytearray()
        while len(out) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise PreviewWorkerError(f"preview worker: no answer within {self.timeout_s:g} s")
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                chunk = os.read(fd, n - len(out))
                if not chunk:
                    raise PreviewWorkerError(f"preview worker exited (code {proc.poll()})")
                out += chunk
        return bytes(out)


# ---------------------------------------------------------------------- the child


def _read_exactly(stream: Any, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        chunk = stream.read(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def serve(stdin: Any, stdout: Any) -> None:
    """The child's loop: jobs from ``stdin``, replies to ``stdout`` (binary streams), until ``stdin``
    closes."""
    from companion.service.preview_frame import encode_jpeg, render_preview

    while True:
        head = _read_exactly(stdin, _JOB_HEADER.size)
        if head is None:
            return
        n_meta, n_image, n_disp = _JOB_HEADER.unpack(head)
        blobs = [_read_exactly(stdin, n) if n else b"" for n in (n_meta, n_image, n_disp)]
        if any(b is None for b in blobs):
            return
        meta, image_bytes, disp_bytes = blobs
        t0 = time.perf_counter()
        try:
            job: _Job = pickle.loads(meta)
            image = np.frombuffer(image_bytes, np.uint8).reshape(job.image_shape)
            disparity = None
            if job.disparity_shape is not None:
                disparity = np.frombuffer(disp_bytes, np.float32).reshape(job.disparity_shape)
            out = render_preview(replace(job.inputs, image=image, disparity=disparity), job.width_px)
            reply = _Reply(encode_jpeg(out, job.quality), (time.perf_counter() - t0) * 1e3, int(out.shape[0]), int(out.shape[1]))
        except Exception as err:  # noqa: BLE001 - reported to the service, which logs it and goes on
            log.exception("preview worker: drawing failed")
            reply = _Reply(b"", 0.0, 0, 0, f"{type(err).__name__}: {err}")
        data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        stdout.write(_REPLY_HEADER.pack(len(data)))
        stdout.write(data)
        stdout.flush()


def main() -> int:
    """``python -m companion.service.preview_worker``: the child. Below the service's priority, one
    OpenCV thread."""
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="preview worker: %(levelname)s %(message)s")
    # Ctrl+C in a terminal reaches the whole process group: the service decides, and the child ends
    # when the service closes its input (no traceback of its own).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The imports first, at the service's priority: at a lower one beside busy processes they took a minute.
    import cv2

    import companion.service.preview_frame  # noqa: F401  (the imports are the start-up: done before the ready byte)

    cv2.setNumThreads(1)
    try:
        os.nice(max(0, WORKER_NICE - os.nice(0)))
    except OSError:
        log.debug("could not lower the priority")
    try:
        sys.stdout.buffer.write(_READY)
        sys.stdout.buffer.flush()
        serve(sys.stdin.buffer, sys.stdout.buffer)
    except BrokenPipeError:
        # The service stopped (or gave up on this worker) while it started or drew: nothing to say.
        # Python's own advice: point stdout at /dev/null so that the flush at exit does not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


if __name__ == "__main__":
    # Run the imported module's main, not this __main__ copy: the replies' classes must pickle under
    # the module's own name, which the service unpickles.
    from companion.service.preview_worker import main as _main

    sys.exit(_main())
