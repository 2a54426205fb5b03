"""The service's preview for ``companion view`` and its flight recording, both off the flight path.

Threads (each with its own synchronous ZeroMQ context; none runs on the event loop)::

    pipeline thread ──offer(frame, result) only when wanted──▶ PreviewPublisher thread ──XPUB──▶ viewers
      (wants_frame(): one bool read per frame)                 (at most preview_rate_hz, only while
                                                                a subscriber exists)
                                                                   │ pipe ▲ JPEG
                                                                   ▼      │
                                                               preview worker process (nice 5):
                                                               draw + JPEG (preview_worker.py)
    health PUB ──▶ FlightRecorder thread ◀── preview XPUB     (health.jsonl + preview/*.jpg, bounded)

The flight loop pays nothing for the preview while nobody watches: :meth:`PreviewPublisher.wants_frame`
is False, so the pipeline asks for no disparity image and hands nothing over. While someone watches,
the publisher raises the flag once per preview period; the pipeline then returns the disparity of
that one frame (the CPU backend copies it, the GPU backend downloads it downsampled by
``gpu.disparity_preview_downsample``) and hands over references to the frame and its result. Drawing
and encoding happen in a child process (:mod:`companion.service.preview_worker`: no GIL shared with
the flight loop, the lowest CPU priority); the publisher's thread only writes the frame into its pipe
and reads the JPEG back. A frame offered while it is busy replaces the waiting one (never a queue),
and a send that would block is dropped (``dropped`` counts them). The worker's start-up (its imports)
is not part of a preview's deadline; a worker that fails or hangs (10 s on one preview) is killed,
reported in ``last_error`` and health's ``preview.failing`` (the page shows it), and started again on
a later preview.

ZeroMQ's XPUB socket reports subscriptions: the publisher knows whether anyone listens without any
request. A viewer that hangs or dies costs nothing: its queue is bounded (``SNDHWM``) and the send
never blocks.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.config.document import render_config_toml
from companion.errors import ConfigError
from companion.service.backoff import LogBackoff
from companion.service.preview_frame import PreviewInputs, near_far_m, pack, unpack
from companion.service.preview_worker import PreviewWorker, PreviewWorkerError, PreviewWorkerStarting
from companion.service.runtime import remove_socket, resolve_endpoint, restrict_socket

log = logging.getLogger(__name__)

Clock = Callable[[], float]


@dataclass(frozen=True)
class _Offer:
    frame: Any  # companion.interfaces.Frame
    result: Any  # companion.core.pipeline.FrameResult
    pipeline: Any  # companion.core.pipeline.Pipeline (layout, geometry, config at that frame)


class PreviewPublisher:
    """Draws and publishes the preview in its own thread, only while someone subscribes.

    Args:
        view_cfg: a callable returning the ``[view]`` section in force (rate, size and quality apply live).
        endpoint: the XPUB endpoint to bind.
        clock: monotonic clock, seconds (the service's; frame times are on it).
        on_error: called (in this thread) with a one-line message when drawing or sending fails.

    Raises (from :meth:`start`):
        ConfigError: the endpoint cannot be bound.
    """

    def __init__(
        self,
        view_cfg: Callable[[], Any],
        endpoint: str,
        *,
        clock: Clock = time.monotonic,
        on_error: Callable[[str], None] = lambda message: None,
        environ: Mapping[str, str] | None = None,
    ) -> None:
        self._view_cfg = view_cfg
        self.endpoint = endpoint
        self._environ = environ
        self._clock = clock
        self._on_error = on_error
        self._want = False
        self._cond = threading.Condition(threading.Lock())
        self._slot: _Offer | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ctx: Any = None
        self._sock: Any = None
        self._topics: set[bytes] = set()
        self.subscribed_since_s: float | None = None
        self.published = 0
        self.dropped = 0
        self.errors = 0
        self.last_encode_ms: float | None = None  # the worker's drawing and encoding of the last preview
        self._worker = PreviewWorker()
        self.failing: str | None = None  # why the last preview failed; None once one succeeds
        self._warm_up = False
        self._error_log = LogBackoff(first_interval_s=5.0, max_interval_s=120.0)

    # ------------------------------------------------------------------ any thread

    def wants_frame(self) -> bool:
        """True when the next processed frame should be offered (someone watches and a preview is due)."""
        return self._want

    def offer(self, frame: Any, result: Any, pipeline: Any) -> None:
        """Hand over a processed frame (references only); replaces one still waiting. Cheap."""
        with self._cond:
            self._want = False
            self._slot = _Offer(frame, result, pipeline)
            self._cond.notify()

    def warm_up(self) -> None:
        """Start the drawing worker now, in the caller's thread, and wait until it is ready; only while
        nobody watches (the preview thread uses the worker only for a viewer).

        Raises:
            PreviewWorkerError: it could not start.
        """
        if self.subscribed:
            return
        self._worker.warm_up()

    @property
    def subscribed(self) -> bool:
        return bool(self._topics)

    def start(self, warm_up: bool = False) -> None:
        """Bind the socket and start the thread; ``warm_up``: start the drawing worker at once (a viewer
        is sure to come: ``demo --view``), else on the first preview a viewer asks for."""
        import zmq

        self._warm_up = warm_up

        self._ctx = zmq.Context()
        sock = self._ctx.socket(zmq.XPUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDHWM, 4)  # a slow viewer loses frames, never holds them
        try:
            sock.bind(resolve_endpoint(self.endpoint, "preview", self._environ))
            self.endpoint = sock.getsockopt_string(zmq.LAST_ENDPOINT)
            restrict_socket(self.endpoint)  # the camera's view is the service's group's, like the controls
        except (zmq.ZMQError, ConfigError) as err:
            sock.close(0)
            self._ctx.destroy(linger=0)
            self._ctx = None
            raise ConfigError(f"view.preview_endpoint {self.endpoint!r}: cannot bind: {err}") from None
        self._sock = sock
        self._thread = threading.Thread(target=self._run, name="preview", daemon=True)
        self._thread.start()
        log.info("preview on %s", self.endpoint)

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the thread and close the socket. Safe twice."""
        self._stop.set()
        self._worker.cancel()
        self._want = False
        with self._cond:
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error("preview thread still busy after %.1f s", timeout_s)
            self._thread = None
        self._worker.close()
        if self._sock is not None:
            self._sock.close(0)
            self._sock = None
            remove_socket(self.endpoint)  # a file left behind would look like a running service
        if self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None

    # ------------------------------------------------------------------ the thread

    def _drain_subscriptions(self) -> None:
        import zmq

        while True:
            try:
                msg = self._sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
            if not msg:
                continue
            topic = msg[1:]
            if msg[0] == 1:
                if not self._topics:
                    self.subscribed_since_s = self._clock()
                    log.info("preview: a viewer subscribed")
                self._topics.add(topic)
            elif msg[0] == 0:
                self._topics.discard(topic)
                if not self._topics:
                    self.subscribed_since_s = None
                    log.info("preview: no viewer left")

    def _run(self) -> None:
        # This thread keeps the service's priority: it starts the worker, which inherits the starting
        # thread's niceness (Linux) and may only lower its own, never raise it back to
        # WORKER_NICE: from a thread at nice 10 the worker's imports and previews ran at nice 10, too
        # low to draw beside two busy processes. Its own work is small (it mostly waits on the
        # worker's pipe, without the GIL), and a lowered thread that holds the GIL keeps the flight
        # loop's threads waiting while the scheduler runs others.
        if self._warm_up:
            from companion.service.preview_worker import PreviewWorkerError

            try:
                self._worker.warm_up()
            except PreviewWorkerError as err:
                log.warning("preview: %s (tried again on the first preview)", err)
        next_due_s = 0.0
        while not self._stop.is_set():
            try:
                self._drain_subscriptions()
            except Exception as err:  # a closed socket at shutdown, or a ZeroMQ surprise
                if self._stop.is_set():
                    return
                log.exception("preview: reading subscriptions failed")
                self._report(f"preview: {type(err).__name__}: {err}")
            now = self._clock()
            watched = self.subscribed
            if not watched:
                self._want = False
                with self._cond:
                    self._slot = None
            elif now >= next_due_s and self._slot is None:
                self._want = True
            with self._cond:
                if self._slot is None and not self._stop.is_set():
                    self._cond.wait(0.05)
                offer, self._slot = self._slot, None
            if offer is None or not watched:
                continue
            cfg = self._view_cfg()
            period_s = 1.0 / cfg.preview_rate_hz
            next_due_s = max(next_due_s + period_s, self._clock() - 0.5 * period_s)
            self._publish(offer, cfg)

    def _publish(self, offer: _Offer, cfg: Any) -> None:
        import zmq

        try:
            jpeg, encode_ms, height_px, width_px = self._worker.render(
                _inputs(offer), cfg.preview_width_px, cfg.preview_jpeg_quality
            )
        except PreviewWorkerStarting:
            return  # stopping while the worker started: nothing went wrong
        except PreviewWorkerError as err:  # the worker is restarted later; the service flies on
            self._failed(offer, str(err))
            return
        except Exception as err:  # a bug here must not stop the preview thread (nor anything else)
            log.debug("preview: frame %s failed", getattr(offer.frame, "seq", "?"), exc_info=True)
            self._failed(offer, f"{type(err).__name__}: {err}")
            return
        self.last_encode_ms = encode_ms
        self.failing = None
        self._error_log.reset()
        result = offer.result
        near_m, far_m = near_far_m(offer.pipeline.config)
        header = {
            "type": "preview",
            "seq": self.published + 1,
            "frame_seq": int(offer.frame.seq),
            "time_s": float(offer.frame.timestamp_s),
            "unix_time_s": time.time(),
            "width_px": int(width_px),
            "height_px": int(height_px),
            "encode_ms": encode_ms,
            "near_m": near_m,
            "far_m": far_m,
            "decision": result.decision.kind.value,
            "dropped": self.dropped,
        }
        try:
            self._sock.send_multipart(pack(header, jpeg), flags=zmq.NOBLOCK)
            self.published += 1
        except zmq.Again:
            self.dropped += 1
        except zmq.ZMQError as err:
            if not self._stop.is_set():
                self._report(f"preview: send failed: {err}")

    def _failed(self, offer: _Offer, message: str) -> None:
        """A preview that failed: counted, shown (health's ``preview.failing`` and ``last_error``), and
        logged less and less often while it goes on (a failing worker is not a flood of log lines)."""
        self.errors += 1
        self.failing = message
        if self._error_log.due(self._clock()):
            more = f" ({self._error_log.suppressed} more since the last line)" if self._error_log.suppressed else ""
            log.error("preview: frame %s: %s%s", getattr(offer.frame, "seq", "?"), message, more)
        self._report(f"preview: {message}")

    def status(self) -> dict[str, Any]:
        """For the health message: previews published and failed, and why the last one failed (None
        once a preview succeeds again)."""
        return {"published": self.published, "errors": self.errors, "failing": self.failing}

    def _report(self, message: str) -> None:
        try:
            self._on_error(message)
        except Exception:
            log.exception("preview: error callback failed")


def _inputs(offer: _Offer) -> Any:
    """What the preview of ``offer`` is drawn from (references; the worker gets copies through its pipe)."""
    pipeline = offer.pipeline
    cfg = pipeline.config
    near_m, far_m = near_far_m(cfg)
    result = offer.result
    inputs = PreviewInputs(
        image=offer.frame.image,
        timestamp_s=float(offer.frame.timestamp_s),
        seq=int(offer.frame.seq),
        depth_m=result.refined.depth_m,
        decision=result.decision,
        disparity=result.disparity,
        layout=pipeline.estimator.layout,
        focal_baseline_px_m=pipeline.geometry.focal_baseline_px_m,
        near_m=near_m,
        far_m=far_m,
        max_disparity_px=float(cfg.stereo.num_disparities),
    )
    return inputs


class FlightRecorder:
    """Records the service's health messages (and every N-th preview frame) into a new folder, bounded.

    It is a plain subscriber of the health PUB and the preview XPUB sockets, in its own thread, so the
    service does no file I/O on its loop or in its pipeline. The run folder
    ``record_dir/YYYYmmdd-HHMMSS[-N]/`` holds ``config.toml`` (the config at start), ``health.jsonl``
    (one health message a line, as ``companion sitl --workdir`` writes it) and ``preview/`` (JPEG
    frames named by the frame's time, with ``preview/index.jsonl``: one preview header a line, plus
    its ``file``). Preview frames stop at 80 % of ``max_bytes``, health lines at 100 %.

    Args:
        record_dir: the parent folder (absolute).
        health_endpoint: the service's health PUB endpoint.
        preview_endpoint: the preview XPUB endpoint, or None (health only).
        preview_every: keep every N-th preview frame (0 = none).
        max_bytes: the run folder's bound, bytes.
        config_text: the config as TOML, written once.
        on_error: called with a one-line message when recording stops or fails.
    """

    def __init__(
        self,
        record_dir: Path,
        health_endpoint: str,
        preview_endpoint: str | None,
        *,
        preview_every: int,
        max_bytes: int,
        config_text: str = "",
        on_error: Callable[[str], None] = lambda message: None,
    ) -> None:
        self.record_dir = record_dir
        self.health_endpoint = health_endpoint
        self.preview_endpoint = preview_endpoint if preview_every > 0 else None
        self.preview_every = preview_every
        self.max_bytes = max_bytes
        self._config_text = config_text
        self._on_error = on_error
        self.run_dir: Path | None = None
        self.bytes_written = 0
        self.health_lines = 0
        self.preview_frames = 0
        self._previews_seen = 0
        self._full_preview = False
        self._full = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ctx: Any = None

    def start(self) -> Path:
        """Create the run folder and start recording; returns the folder.

        Raises:
            OSError: the folder cannot be created or written.
        """
        import zmq

        self.record_dir.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        run = self.record_dir / stamp
        n = 1
        while run.exists():
            n += 1
            run = self.record_dir / f"{stamp}-{n}"
        run.mkdir()
        if self.preview_endpoint is not None:
            (run / "preview").mkdir()
        self.run_dir = run
        if self._config_text:
            self._write_bytes(run / "config.toml", self._config_text.encode("utf-8"))
        self._ctx = zmq.Context()
        health = self._ctx.socket(zmq.SUB)
        health.setsockopt(zmq.LINGER, 0)
        health.setsockopt(zmq.RCVHWM, 1000)
        health.setsockopt(zmq.SUBSCRIBE, b"")
        health.connect(self.health_endpoint)
        preview = None
        if self.preview_endpoint is not None:
            preview = self._ctx.socket(zmq.SUB)
            preview.setsockopt(zmq.LINGER, 0)
            preview.setsockopt(zmq.RCVHWM, 4)
            preview.setsockopt(zmq.SUBSCRIBE, b"preview")
            preview.connect(self.preview_endpoint)
        self._thread = threading.Thread(target=self._run, args=(health, preview), name="recorder", daemon=True)
        self._thread.start()
        log.info("recording to %s (at most %.0f MB)", run, self.max_bytes / 1e6)
        return run

    def close(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        if self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None

    def _write_bytes(self, path: Path, data: bytes) -> None:
        path.write_bytes(data)
        self.bytes_written += len(data)

    def _run(self, health: Any, preview: Any) -> None:
        import zmq

        poller = zmq.Poller()
        poller.register(health, zmq.POLLIN)
        if preview is not None:
            poller.register(preview, zmq.POLLIN)
        assert self.run_dir is not None
        try:
            with (self.run_dir / "health.jsonl").open("ab") as out:
                while not self._stop.is_set():
                    ready = dict(poller.poll(100))
                    if health in ready:
                        while True:
                            try:
                                raw = health.recv(zmq.NOBLOCK)
                            except zmq.Again:
                                break
                            self._health_line(out, raw)
                        out.flush()
                    if preview is not None and preview in ready:
                        while True:
                            try:
                                frames = preview.recv_multipart(zmq.NOBLOCK)
                            except zmq.Again:
                                break
                            self._preview_frame(frames)
        except OSError as err:
            log.error("recording to %s stopped: %s", self.run_dir, err)
            self._report(f"recording stopped: {err.strerror or err}")
        finally:
            health.close(0)
            if preview is not None:
                preview.close(0)

    def _health_line(self, out: Any, raw: bytes) -> None:
        if self._full:
            return
        if self.bytes_written + len(raw) + 1 > self.max_bytes:
            self._full = True
            log.warning("recording %s: view.record_max_mb reached; no more health lines", self.run_dir)
            self._report("recording: view.record_max_mb reached; health no longer recorded")
            return
        out.write(raw + b"\n")
        self.bytes_written += len(raw) + 1
        self.health_lines += 1

    def _preview_frame(self, frames: list[bytes]) -> None:
        self._previews_seen += 1
        if self._full_preview or (self._previews_seen - 1) % self.preview_every:
            return
        try:
            header, jpeg = unpack(frames)
        except Exception as err:
            log.warning("recording: a bad preview message: %s", err)
            return
        if self.bytes_written + len(jpeg) > 0.8 * self.max_bytes:
            self._full_preview = True
            log.warning("recording %s: 80 %% of view.record_max_mb reached; no more preview frames", self.run_dir)
            return
        assert self.run_dir is not None
        name = f"t{float(header.get('time_s', 0.0)):011.3f}_{int(header.get('frame_seq', 0)):07d}.jpg"
        self._write_bytes(self.run_dir / "preview" / name, jpeg)
        line = json.dumps({**header, "file": name}).encode("utf-8") + b"\n"
        with (self.run_dir / "preview" / "index.jsonl").open("ab") as index:
            index.write(line)
        self.bytes_written += len(line)
        self.preview_frames += 1

    def _report(self, message: str) -> None:
        try:
            self._on_error(message)
        except Exception:
            log.exception("recorder: error callback failed")


class ViewPlane:
    """The service's preview publisher and flight recorder, as the daemon starts and stops them.

    A preview or a recording that cannot start is reported (``on_error``, the log) and left out: the
    service flies without them rather than not at all.

    Args:
        get_config: returns the whole config in force (its ``[view]`` section applies live where it can).
        clock: the service's monotonic clock, seconds.
        on_error: called with one line when something of the view fails (the health's ``last_error``).
    """

    def __init__(
        self,
        get_config: Callable[[], Any],
        *,
        clock: Clock = time.monotonic,
        on_error: Callable[[str], None],
        environ: Mapping[str, str] | None = None,
    ) -> None:
        self._get_config = get_config
        self._clock = clock
        self._on_error = on_error
        self._environ = environ
        self.publisher: PreviewPublisher | None = None
        self.recorder: FlightRecorder | None = None

    def open(self, health_endpoint: str) -> None:
        cfg = self._get_config()
        view = cfg.view
        if view.preview_enabled:
            publisher = PreviewPublisher(
                lambda: self._get_config().view,
                view.preview_endpoint,
                clock=self._clock,
                on_error=self._on_error,
                environ=self._environ,
            )
            try:
                publisher.start()
                self.publisher = publisher
            except ConfigError as err:
                log.error("no preview: %s", err)
                self._on_error(f"no preview: {err}")
        if view.record_dir is not None:
            recorder = FlightRecorder(
                view.record_dir,
                health_endpoint,
                self.publisher.endpoint if self.publisher is not None else None,
                preview_every=view.record_preview_every,
                max_bytes=int(view.record_max_mb * 1e6),
                config_text=render_config_toml(cfg, [f"# the config in force when the service started (pid {os.getpid()})"]),
                on_error=self._on_error,
            )
            try:
                recorder.start()
                self.recorder = recorder
            except OSError as err:
                log.error("not recording: view.record_dir %s: %s", view.record_dir, err.strerror or err)
                self._on_error(f"not recording: view.record_dir {view.record_dir}: {err.strerror or err}")

    def wants_frame(self) -> bool:
        """True when the next frame should come with its disparity and be offered (a viewer, a due preview)."""
        publisher = self.publisher
        return publisher is not None and publisher.wants_frame()

    def offer(self, frame: Any, result: Any, pipeline: Any) -> None:
        publisher = self.publisher
        if publisher is not None:
            publisher.offer(frame, result, pipeline)

    def close(self) -> None:
        """Stop the recorder, then the publisher (the recorder keeps what it got). Safe twice."""
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        if self.publisher is not None:
            self.publisher.close()
            self.publisher = None
