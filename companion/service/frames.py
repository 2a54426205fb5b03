"""The daemon's frame parts: capture (the camera and its thread) and the pipeline (its thread, the
newest result and the frame counters).

::

    CapturePart: camera ──CaptureThread──▶ FrameMailbox (one slot) ──▶ PipelinePart: ProcessingThread
                                                                       (Pipeline.process; between frames
                                                                        the jobs: build, reconfigure, reset)
                                                                              │ newest result, on the loop
                                                                              ▼
                                                                       PipelinePart.latest

Each part owns its state, has ``start`` and ``stop(budget_s)``, and gives what health reads as a
small typed snapshot (:meth:`CapturePart.status`, :meth:`PipelinePart.counts`).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from companion.backends import make_pipeline, resolve_backend
from companion.config import CompanionConfig
from companion.errors import CompanionError, FrameError
from companion.framepool import FrameBuffers
from companion.interfaces import CameraSource, Frame
from companion.service.capture import CaptureStatus, CaptureThread, FrameMailbox, ProcessingThread
from companion.service.parts import StartupError, call_on_loop, stop_in_thread

if TYPE_CHECKING:
    from companion.service.camera_sim import TelemetryPose

log = logging.getLogger(__name__)

Clock = Callable[[], float]


@dataclass(frozen=True)
class Processed:
    """A frame result with where it came from."""

    result: Any  # companion.core.pipeline.FrameResult
    seq: int
    done_s: float


@dataclass(frozen=True)
class FrameCounts:
    """The pipeline part's counters (health's frame fields).

    Attributes:
        processed: frames processed into a result.
        processed_twice: frames handed to the pipeline twice (refused; proves the mailbox).
        frame_errors: frames rejected or failed in a stage.
        skipped: late frames skipped for a fresher one (``service.skip_late_frames``).
        fps: results in the last second, per second.
        backend: the disparity backend matching the frames now (``cupy``, ``cpu-sgm``, ...), or None
            before the pipeline is built.
        device_lost: the GPU fault that put the CPU engine in its place, one line; None while the
            backend configured works.
    """

    processed: int
    processed_twice: int
    frame_errors: int
    skipped: int
    fps: float
    backend: str | None = None
    device_lost: str | None = None


class CapturePart:
    """The capture part: the camera (the one ``camera`` names unless one is given), its thread (blocking
    reads, reconnects with back-off) and the frame buffers the camera decodes into.

    Args:
        mailbox: where the capture thread puts each frame.
        frame_buffers: the pipeline's pinned buffers lent to the camera (or none).
        camera: a camera source, or None for the one the config names.
        on_status: called in the capture thread with each new state ("streaming", "reconnecting", ...).
        clock: monotonic seconds (the clock of frame timestamps).
    """

    name = "capture"
    stop_budget_s = 1.0

    def __init__(
        self,
        mailbox: FrameMailbox,
        frame_buffers: FrameBuffers,
        *,
        camera: CameraSource | None,
        on_status: Callable[[str], None],
        clock: Clock,
    ) -> None:
        self.mailbox = mailbox
        self.frame_buffers = frame_buffers
        self.camera = camera
        self._on_status = on_status
        self._clock = clock
        self._thread: CaptureThread | None = None
        self._telemetry_pose: TelemetryPose | None = None  # the sim camera's pose source, when it has one

    def open(self, cfg: CompanionConfig, link: Any) -> None:
        """Build the camera ``cfg.camera`` names (a simulated one may render from ``link``'s telemetry).

        Raises:
            StartupError: its eyes are not ``camera.width_px`` x ``camera.height_px``.
        """
        if self.camera is None:
            from companion.service.camera import make_camera
            from companion.service.camera_sim import TelemetryPose, placement_from_config

            if cfg.camera.source == "sim" and cfg.camera.sim_pose == "telemetry":
                self._telemetry_pose = TelemetryPose(
                    link.state, placement_from_config(cfg), cfg.camera.sim_pose_max_age_s, self._clock
                )
            self.camera = make_camera(cfg, pose_provider=self._telemetry_pose, clock=self._clock)
        if hasattr(self.camera, "frame_buffers"):  # a UVC camera decodes into the GPU's pinned buffers
            self.camera.frame_buffers = self.frame_buffers
        eye = tuple(self.camera.eye_size_px)
        if eye != (cfg.camera.width_px, cfg.camera.height_px):
            raise StartupError(
                f"camera {self.camera.name} gives {eye[0]}x{eye[1]} eyes but camera.width_px/height_px say "
                f"{cfg.camera.width_px}x{cfg.camera.height_px}"
            )

    def start(self, cfg: CompanionConfig) -> None:
        """Start the capture thread on the opened camera."""
        assert self.camera is not None
        self._thread = CaptureThread(
            self.camera,
            self.mailbox,
            on_status=self._on_status,
            reconnect_initial_s=cfg.camera.reconnect_initial_s,
            reconnect_max_s=cfg.camera.reconnect_max_s,
            clock=self._clock,
        )
        self._thread.start()

    async def stop(self, budget_s: float) -> bool:
        if self._thread is None:
            return True
        return await stop_in_thread("the capture thread", self._thread.stop, budget_s)

    def status(self) -> CaptureStatus | None:
        """The capture thread's status (health's ``camera``), or None before it started."""
        return self._thread.status() if self._thread is not None else None

    def place(self, cfg: CompanionConfig) -> None:
        """A new config's camera placement for the simulated camera's telemetry pose (one reference swap)."""
        if self._telemetry_pose is not None:
            from companion.service.camera_sim import placement_from_config

            self._telemetry_pose.placement = placement_from_config(cfg)


class PipelinePart:
    """The pipeline part: its thread, the pipeline it builds and uses, the newest result and the counters.

    Args:
        mailbox: where the capture part puts frames.
        frame_buffers: the buffers the camera decodes into (offered the estimator's pinned ones).
        view: the preview plane now (offered a frame when a viewer watches), or None.
        on_result: called on the loop after each new result (wakes the control loop).
        on_error: records a one-line fault (health's ``last_error``).
        clock: monotonic seconds (the clock of frame timestamps).
    """

    name = "pipeline"
    stop_budget_s = 1.0

    def __init__(
        self,
        mailbox: FrameMailbox,
        frame_buffers: FrameBuffers,
        *,
        view: Callable[[], Any],
        on_result: Callable[[], None],
        on_error: Callable[[str], None],
        clock: Clock,
    ) -> None:
        self.mailbox = mailbox
        self.frame_buffers = frame_buffers
        self._view = view
        self._on_new_result = on_result
        self._on_error = on_error
        self._clock = clock
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: ProcessingThread | None = None
        self.pipeline: Any = None  # companion.core.pipeline.Pipeline, built in the thread
        self.latest: Processed | None = None
        self.first_result: asyncio.Event | None = None
        self._last_processed_key: tuple[int, float] | None = None
        self._processed = 0
        self._processed_twice = 0
        self._frame_errors = 0
        self._processed_times: collections.deque = collections.deque(maxlen=256)
        self.processed_seqs: list[int] = []  # every processed frame's seq (bench), when record_seqs
        self.record_seqs = False

    # ------------------------------------------------------------------------------ start and stop

    async def start(self, cfg: CompanionConfig) -> None:
        """Start the thread and build the pipeline there (CuPy's current device is per thread).

        Raises:
            StartupError: the pipeline could not be built.
        """
        self._loop = asyncio.get_running_loop()
        self.first_result = asyncio.Event()
        self._thread = ProcessingThread(
            self.mailbox,
            self._process,
            self._on_result_threadsafe,
            skip_late_frames=cfg.service.skip_late_frames,
            clock=self._clock,
        )
        self._thread.start()
        try:
            self.pipeline = await asyncio.wrap_future(self._thread.submit(self._build, cfg))
        except CompanionError as err:
            raise StartupError(f"pipeline: {err}") from None
        self._thread.processing_enabled.set()

    async def stop(self, budget_s: float) -> bool:
        """Stop the thread, then release the estimator (the GPU backend frees its memory)."""
        stopped = True
        if self._thread is not None:
            stopped = await stop_in_thread("the pipeline thread", self._thread.stop, budget_s)
            self._thread = None
        pipeline, self.pipeline = self.pipeline, None
        if pipeline is not None:
            closer = getattr(pipeline.estimator, "close", None)
            if closer is not None:
                try:
                    closer()
                except Exception:
                    log.exception("releasing the disparity backend failed")
        return stopped

    # ------------------------------------------------------------------------------ jobs

    def _build(self, cfg: CompanionConfig) -> Any:
        pipeline = make_pipeline(cfg, cfg.camera.width_px, cfg.camera.height_px, clock=time.perf_counter)
        flown = pipeline.config
        log.info(
            "disparity backend %s (matcher %s); planner.block_erode_px %s",
            resolve_backend(cfg), flown.stereo.matcher, flown.planner.block_erode_px,
        )
        self.offer_frame_pool(pipeline, cfg)
        return pipeline

    def offer_frame_pool(self, pipeline: Any, cfg: CompanionConfig) -> None:
        """In the pipeline thread: the camera decodes into the estimator's pinned buffers, when it has
        them (the GPU backend) and ``gpu.camera_frame_buffers`` > 0; else into memory of its own."""
        from companion.service.camera import frame_channels

        make_pool = getattr(pipeline.estimator, "frame_pool", None)
        count = cfg.gpu.camera_frame_buffers
        self.frame_buffers.pool = (
            make_pool(count, channels=frame_channels(cfg.camera)) if make_pool is not None and count > 0 else None
        )

    def _reconfigure(self, cfg: CompanionConfig) -> list[str]:
        """In the pipeline thread: swap the config in; release a replaced estimator (GPU threads)."""
        old = self.pipeline.estimator
        changed = self.pipeline.reconfigure(cfg)
        if self.pipeline.estimator is not old:
            self.offer_frame_pool(self.pipeline, cfg)
            closer = getattr(old, "close", None)
            if closer is not None:
                closer()
        return changed

    async def reconfigure(self, cfg: CompanionConfig) -> None:
        """Swap ``cfg`` into the pipeline between two frames (never racing one); nothing before it is built.

        Raises:
            CompanionError: (or any error) the new pipeline could not be built; the old one stays.
        """
        if self._thread is None:
            return
        if self.pipeline is not None:
            await asyncio.wrap_future(self._thread.submit(self._reconfigure, cfg))
        self._thread.skip_late_frames = cfg.service.skip_late_frames

    def reset(self) -> None:
        """Forget the release filter's memory (a new camera stream), between two frames."""
        if self.pipeline is not None and self._thread is not None:
            self._thread.submit(self.pipeline.reset)

    # ------------------------------------------------------------------------------ frames

    def _process(self, frame: Frame) -> Any:
        """In the pipeline thread: one frame -> FrameResult (FrameError etc. go to _on_result)."""
        key = (frame.seq, frame.timestamp_s)
        if key == self._last_processed_key:
            # Cannot happen with the mailbox; counted (and refused) to prove it. (A sequence number
            # that goes back is not this: a source may restart its count when it is reopened.)
            self._processed_twice += 1
            raise FrameError(f"frame {frame.seq} handed over twice")
        self._last_processed_key = key
        view = self._view()
        want = view is not None and view.wants_frame()  # a viewer watches and a preview is due
        pipeline = self.pipeline
        estimator = pipeline.estimator
        try:
            result = pipeline.process(frame.image, frame.timestamp_s, want_disparity=want)
        finally:
            if pipeline.estimator is not estimator:  # the device was lost: the fallback has no pinned pool
                self.offer_frame_pool(pipeline, pipeline.config)
        if want:
            view.offer(frame, result, self.pipeline)  # references only; drawn in the preview thread
        return result

    def _on_result_threadsafe(self, frame: Frame, result: Any, err: BaseException | None) -> None:
        call_on_loop(self._loop, self._on_result, frame, result, err, self._clock())

    def _on_result(self, frame: Frame, result: Any, err: BaseException | None, done_s: float) -> None:
        """On the loop: record a frame's outcome and wake the control loop."""
        if err is not None:
            self._frame_errors += 1
            if isinstance(err, FrameError):
                self._on_error(f"frame {frame.seq} rejected: {err}")
                log.warning("frame %d rejected: %s", frame.seq, err)
            elif isinstance(err, CompanionError):
                self._on_error(f"frame {frame.seq}: {err}")
                log.error("frame %d: %s", frame.seq, err)
            else:  # a bug in a stage: keep flying safely (frames age -> zero velocity -> Hold)
                self._on_error(f"frame {frame.seq}: internal error {type(err).__name__}: {err}")
                log.error("processing frame %d failed", frame.seq, exc_info=err)
            return
        self._processed += 1
        self._processed_times.append(done_s)
        if self.record_seqs:
            self.processed_seqs.append(frame.seq)
        self.latest = Processed(result=result, seq=frame.seq, done_s=done_s)
        if self.first_result is not None:
            self.first_result.set()
        self._on_new_result()

    def counts(self, now_s: float) -> FrameCounts:
        """The counters at ``now_s`` (monotonic seconds)."""
        recent = sum(1 for t in self._processed_times if now_s - t <= 1.0)
        pipeline = self.pipeline
        return FrameCounts(
            processed=self._processed,
            processed_twice=self._processed_twice,
            frame_errors=self._frame_errors,
            skipped=self._thread.skipped if self._thread is not None else 0,
            fps=float(recent),
            backend=pipeline.estimator.name if pipeline is not None else None,
            device_lost=pipeline.device_lost if pipeline is not None else None,
        )
