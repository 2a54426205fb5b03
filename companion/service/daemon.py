"""``companion run``: the asyncio daemon, a thin shell around the pipeline and the supervisor.

Threads and tasks::

    capture thread ──newest frame──▶ FrameMailbox (one slot) ──▶ pipeline thread (one frame at a time:
    (blocking read, reconnect                                     Pipeline.process; between frames the
     with back-off)                                               jobs: build, reconfigure, reset)
                                                                          │ newest FrameResult (posted to the loop)
                                                                          ▼
    control server task (ZeroMQ ROUTER) ──requests──▶ control loop task ──setpoint──▶ VehicleLink (MAVSDK)
    signal handlers (TERM/INT/HUP)                    (Supervisor.step at the setpoint rate and on every
                                                       new result or request; the ONLY place that feeds
                                                       the systemd watchdog)
    health task (ZeroMQ PUB, 10 Hz + every state change)     vehicle connector task (waits for the autopilot)
    detour histogram thread (one job at a time: the detour layer's polar histogram, asked for on a
    step's output, computed here, its result handed to a later step on the loop)

The control loop never waits for the pipeline: it steps on a fixed grid (``vehicle.setpoint_rate_hz``)
whatever the vision rate, and also as soon as a new result arrives, so a decision reaches the vehicle
without waiting for the next tick. Nor does it wait for the detour layer's histogram (tens of
milliseconds with a full obstacle memory): the supervisor asks for it (``StepOutput.histogram_request``),
one worker thread computes it from that immutable snapshot, and the result goes back into a later
step on the loop, so every change to the supervisor's state stays on the loop. If the control loop stalls, the watchdog is not fed and systemd kills
the process (MAVSDK's 20 Hz re-sending dies with it), and PX4's offboard-loss failsafe takes over.

Shutdown (first SIGTERM/SIGINT): the supervisor sends zero and, if we own offboard, Hold; then the
stream stops (no mode change), ZeroMQ closes, the camera and the pipeline (GPU) are released, each
within its budget (:data:`CLEANUP_BUDGET_S` in all). A second signal exits at once with
:data:`~companion.exitcodes.FORCED_EXIT`. SIGHUP reloads the config file. When the process ends, and
with which code, is the :class:`~companion.service.lifecycle.Lifecycle`'s; the presence plane and the
health loop are parts with their own state, ``start()`` and ``stop(budget_s)``
(:mod:`companion.service.parts`).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import functools
import gc
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any


from companion import exitcodes
from companion.backends import make_pipeline, resolve_backend
from companion.config import CompanionConfig, load_config
from companion.core.supervisor import (
    Action,
    ActionResult,
    Shutdown,
    State,
    Supervisor,
    SupervisorConfig,
)
from companion.core.detour import Histogram, HistogramRequest, HistogramResult, compute_histogram
from companion.core.safety import near_blindness
from companion.core.types import ZERO_SETPOINT, VelocitySetpoint
from companion.errors import (
    CompanionError,
    ConfigError,
    FrameError,
    VehicleError,
)
from companion.framepool import FrameBuffers
from companion.interfaces import CameraSource, Frame, VehicleLink
from companion.service.aio import wait_event
from companion.service.backoff import LogBackoff
from companion.service.capture import CaptureThread, FrameMailbox, ProcessingThread
from companion.service.control import (  # noqa: F401 (re-exported: the daemon's public names)
    ControlPlane,
    ControlServer,
    RequestRefused,
    keep_restart_fields,
    resolve_config_paths,
    restart_required,
)
from companion.service.health import HealthLoop, HealthReporter
from companion.service.lifecycle import Lifecycle, flush_logs
from companion.service.notify import Notifier, watchdog_interval_s
from companion.service.presence import Presence
from companion.service.runtime import raise_open_file_limit

if TYPE_CHECKING:
    from companion.service.camera import TelemetryPose

log = logging.getLogger(__name__)

Clock = Callable[[], float]


#: The longest the release of everything may take after the vehicle is safe (zero, Hold or its
#: timeout), seconds; each step has its own smaller budget (:data:`_STEP_BUDGET_S`).
CLEANUP_BUDGET_S = 1.5
_STEP_BUDGET_S = 0.5
#: After the event loop ends, how long threads still running get before the process exits without
#: them (a MAVSDK call blocked in its thread), seconds.
EXIT_JOIN_S = 0.3


class StartupError(CompanionError):
    """The service could not start; the process exits with STARTUP_FAILURE (78)."""


@dataclass(frozen=True)
class Processed:
    """A frame result with where it came from."""

    result: Any  # companion.core.pipeline.FrameResult
    seq: int
    done_s: float


class Service(ControlPlane, HealthReporter):
    """The daemon. Build it, then ``await run()`` (or :func:`run_service` from the CLI).

    Args:
        cfg: the configuration (validated).
        config_path: the file it came from (for ``reload`` and SIGHUP), or None.
        camera: the camera source; default: the one ``cfg.camera`` names.
        link: the vehicle link; default: MAVSDK on ``cfg.vehicle.connection``.
        clock: monotonic clock, seconds (the clock of frame timestamps).
        install_signals: handle SIGTERM/SIGINT/SIGHUP (only possible in the main thread).
        notifier: sd_notify sender; default: from ``$NOTIFY_SOCKET`` (None when not under systemd).
        histogram_fn: computes the detour layer's histogram in the worker thread (default
            :func:`~companion.core.detour.compute_histogram`; tests inject a slow or failing one).
    """

    def __init__(
        self,
        cfg: CompanionConfig,
        *,
        config_path: Path | None = None,
        camera: CameraSource | None = None,
        link: VehicleLink | None = None,
        clock: Clock = time.monotonic,
        install_signals: bool = True,
        notifier: Notifier | None = None,
        environ: dict[str, str] | None = None,
        histogram_fn: Callable[[HistogramRequest], Histogram] = compute_histogram,
    ) -> None:
        self.config_path = config_path
        self.config = resolve_config_paths(cfg, config_path.parent if config_path else None)
        self._camera = camera
        self._frame_buffers = FrameBuffers()  # the GPU backend's pinned buffers for the camera, or none
        self._telemetry_pose: TelemetryPose | None = None  # the sim camera's pose source, when it has one
        self.link = link
        self._clock = clock
        self._install_signals = install_signals
        self._environ = dict(os.environ) if environ is None else environ
        self._notifier = notifier if notifier is not None else Notifier.from_environment(self._environ)
        self._watchdog_s = watchdog_interval_s(self._environ)
        # The detour layer's histograms are computed off the control loop (_plan_off_loop).
        self.supervisor = Supervisor(SupervisorConfig.from_config(self.config), defer_histogram=True)
        self._histogram_fn = histogram_fn
        self._histogram_pool: concurrent.futures.ThreadPoolExecutor | None = None  # one worker, made on first use
        self._histogram_job: HistogramRequest | None = None  # the request being computed now
        self._histogram_asked: int | None = None  # seq of the last request handed to the worker
        self._histogram_done: HistogramResult | None = None  # computed, for the next step
        self.histogram_stats = {"computed": 0, "failed": 0}
        self.presence = Presence(
            config=lambda: self.config,
            link=lambda: self.link,
            connected=self._vehicle_connected,
            state=lambda: self.supervisor.state.value,
            engaged=lambda: self.supervisor.engaged,
            clock=self._clock,
            on_died=self._part_died,
        )
        # The parts with a task of their own (start() in _start, stop(budget) in _cleanup).
        self.health_loop = HealthLoop(self._publish_health, lambda: self.config.bus.health_rate_hz, on_died=self._part_died)
        self.config_version = 1
        # When the process ends and with which code (signals, should_exit, the forced exit).
        self.lifecycle = Lifecycle(on_reload=self._on_hup)
        self.ready = threading.Event()  # set once READY=1 was sent (for tests and embedding)
        self.stopped = threading.Event()
        self.bus = None
        self.view = None  # companion.service.preview.ViewPlane: the preview and the flight recording
        self._loop: asyncio.AbstractEventLoop | None = None
        self._processor: ProcessingThread | None = None
        self._pipeline = None
        self._mailbox = FrameMailbox()
        self._capture: CaptureThread | None = None
        self._tasks: list[asyncio.Task] = []
        self._action_tasks: set[asyncio.Task] = set()
        self._pending: list[tuple[Any, asyncio.Future | None]] = []
        self._latest: Processed | None = None
        self._last_stepped_seq: int | None = None
        self._last_processed_key: tuple[int, float] | None = None
        self._processed = 0
        self._processed_twice = 0
        self._frame_errors = 0
        self._processed_times: collections.deque = collections.deque(maxlen=256)
        self._latency_s: collections.deque = collections.deque(maxlen=500)
        self._last_latency_s: float | None = None
        self._last_setpoint: VelocitySetpoint | None = None
        self._last_setpoint_s: float | None = None
        self._setpoints_sent = 0
        self._last_error: str | None = None
        self._last_error_kind: str | None = None  # "config" for a rejected reload: a good one clears it
        self.control_server: ControlServer | None = None
        self._vehicle_status = "connecting"
        self._health_seq = 0
        self._last_watchdog_s = -1e9
        self._config_lock: asyncio.Lock | None = None
        # Events are created in run(), on the loop that uses them.
        self._wake: asyncio.Event | None = None
        self._first_result: asyncio.Event | None = None
        self.latencies_s: list[float] = []  # every frame-to-setpoint latency (bench); bounded by its user
        self.record_latencies = False
        self.processed_seqs: list[int] = []
        self.record_seqs = False

    # ================================================================================ lifecycle

    async def run(self) -> int:
        """Start, serve until a shutdown is requested, stop cleanly. Returns the process exit code."""
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._first_result = asyncio.Event()
        self.lifecycle.bind(self._loop)
        self._config_lock = asyncio.Lock()
        try:
            await self._start()
        except (CompanionError, OSError) as err:
            log.error("startup failed: %s", err)
            return await self._startup_failed(err)
        except Exception as err:  # a bug: logged with its traceback; a restart would only repeat it
            log.exception("startup failed")
            return await self._startup_failed(err)
        try:
            # What start-up built (modules, config, parts) lives as long as the process: out of the
            # garbage collector, so that a later full collection, which holds the interpreter lock
            # (every thread of the flight path waits), walks only what is newer. Of the start-up heap
            # it took 0.2-0.3 s on a loaded 2-core machine: half the stale-frame timeout.
            gc.collect()
            gc.freeze()
            self._notify("READY=1", f"STATUS={self.supervisor.state.value}: {self.supervisor.reason}")
            self.ready.set()
            log.info("ready: %s", self.supervisor.reason)
            await self.lifecycle.wait()
            await self._stop()
        finally:
            await self._cleanup()
            self.stopped.set()
        return self.exit_code

    async def _startup_failed(self, err: BaseException) -> int:
        self._notify(f"STATUS=startup failed: {err}")
        self._error(f"startup failed: {err}")
        await self._cleanup()
        self.exit_code = exitcodes.STARTUP_FAILURE
        self.stopped.set()
        return self.exit_code

    async def _start(self) -> None:
        cfg = self.config
        loop = self._loop
        assert loop is not None
        if self._install_signals:
            self._setup_signals()
        blind = near_blindness(cfg)
        if blind is not None:
            raise StartupError(f"config: {blind}")
        from companion.service.bus import Bus

        raise_open_file_limit()
        self.bus = Bus(cfg.bus, environ=self._environ)
        self.bus.open()
        from companion.service.preview import ViewPlane

        # Off the flight path (own threads); one that cannot start is reported, and the service flies on.
        self.view = ViewPlane(lambda: self.config, clock=self._clock, on_error=self._error, environ=self._environ)
        self.view.open(self.bus.health_endpoint)
        self._processor = ProcessingThread(
            self._mailbox,
            self._process,
            self._on_result_threadsafe,
            skip_late_frames=cfg.service.skip_late_frames,
            clock=self._clock,
        )
        self._processor.start()
        try:
            # Built in the thread that uses it (CuPy's current device is per thread).
            self._pipeline = await asyncio.wrap_future(self._processor.submit(self._build_pipeline, cfg))
        except CompanionError as err:
            raise StartupError(f"pipeline: {err}") from None
        self._processor.processing_enabled.set()
        # The link before the camera: a simulated camera may render from the vehicle's telemetry.
        if self.link is None:
            from companion.service.vehicle import make_vehicle_link

            self.link = make_vehicle_link(cfg.vehicle, clock=self._clock)
        opener = getattr(self.link, "open", None)  # MAVSDK: add the connection now, fail fast on a bad URL
        if opener is not None:
            try:
                await opener()
            except VehicleError as err:
                raise StartupError(str(err)) from None
        self._spawn(self._vehicle_connector(), "vehicle connector")
        self.presence.start()
        if self._camera is None:
            from companion.service.camera import TelemetryPose, make_camera, placement_from_config

            if cfg.camera.source == "sim" and cfg.camera.sim_pose == "telemetry":
                self._telemetry_pose = TelemetryPose(
                    self.link.state, placement_from_config(cfg), cfg.camera.sim_pose_max_age_s, self._clock
                )
            self._camera = make_camera(cfg, pose_provider=self._telemetry_pose, clock=self._clock)
        if hasattr(self._camera, "frame_buffers"):  # a UVC camera decodes into the GPU's pinned buffers
            self._camera.frame_buffers = self._frame_buffers
        eye = tuple(self._camera.eye_size_px)
        if eye != (cfg.camera.width_px, cfg.camera.height_px):
            raise StartupError(
                f"camera {self._camera.name} gives {eye[0]}x{eye[1]} eyes but camera.width_px/height_px say "
                f"{cfg.camera.width_px}x{cfg.camera.height_px}"
            )
        self._capture = CaptureThread(
            self._camera,
            self._mailbox,
            on_status=self._on_camera_status_threadsafe,
            reconnect_initial_s=cfg.camera.reconnect_initial_s,
            reconnect_max_s=cfg.camera.reconnect_max_s,
            clock=self._clock,
        )
        self._capture.start()
        # Ready means the whole chain works: a frame captured AND processed.
        await wait_event(self._first_result, cfg.camera.open_timeout_s)
        if self._processed == 0:
            status = self._capture.status()
            what = "no frame" if status.frames == 0 else "no frame processed"
            problem = self._last_error or status.last_error
            raise StartupError(
                f"camera {status.source}: {what} within camera.open_timeout_s = {cfg.camera.open_timeout_s:g} s"
                + (f" ({problem})" if problem else "")
            ) from None
        self._spawn(self._control_loop(), "control loop", critical=True)
        self.health_loop.start()
        # The control socket gets its own thread: no client can stall the flight loop.
        self.control_server = ControlServer(
            self.bus.control,
            cfg.bus,
            loop,
            self.handle_local,
            self.handle_request,
            on_internal_error=self._control_server_error,
            gatekeeper=self.bus.gatekeeper,
            clock=self._clock,
        )
        self.control_server.start()

    def _reconfigure_pipeline(self, cfg: CompanionConfig) -> list[str]:
        """In the pipeline thread: swap the config in; release a replaced estimator (GPU threads)."""
        old = self._pipeline.estimator
        changed = self._pipeline.reconfigure(cfg)
        if self._pipeline.estimator is not old:
            self._offer_frame_pool(self._pipeline, cfg)
            closer = getattr(old, "close", None)
            if closer is not None:
                closer()
        return changed

    def _offer_frame_pool(self, pipeline: Any, cfg: CompanionConfig) -> None:
        """In the pipeline thread: the camera decodes into the estimator's pinned buffers, when it has
        them (the GPU backend) and ``gpu.camera_frame_buffers`` > 0; else into memory of its own."""
        from companion.service.camera import frame_channels

        make_pool = getattr(pipeline.estimator, "frame_pool", None)
        count = cfg.gpu.camera_frame_buffers
        self._frame_buffers.pool = (
            make_pool(count, channels=frame_channels(cfg.camera)) if make_pool is not None and count > 0 else None
        )

    def _build_pipeline(self, cfg: CompanionConfig) -> Any:
        pipeline = make_pipeline(cfg, cfg.camera.width_px, cfg.camera.height_px, clock=time.perf_counter)
        flown = pipeline.config
        log.info(
            "disparity backend %s (matcher %s); memory.block_erode_px %s, detour.cone_from_start %s, "
            "detour.through_squeeze %s",
            resolve_backend(cfg), flown.stereo.matcher, flown.memory.block_erode_px,
            flown.detour.cone_from_start, flown.detour.through_squeeze,
        )
        self._offer_frame_pool(pipeline, cfg)
        return pipeline

    def _spawn(self, coro: Any, name: str, critical: bool = False) -> None:
        assert self._loop is not None
        task = self._loop.create_task(coro, name=name)
        task.add_done_callback(lambda t: self._task_done(t, name, critical))
        self._tasks.append(task)

    def _task_done(self, task: asyncio.Task, name: str, critical: bool) -> None:
        if task.cancelled():
            return
        err = task.exception()
        if err is not None:
            self._part_died(name, err)

    def _part_died(self, name: str, err: BaseException) -> None:
        """A task of the service (or a part's) ended with an error: stop cleanly."""
        log.error("task %s died: %r", name, err, exc_info=err)
        self._error(f"internal error in {name}: {type(err).__name__}: {err}")
        # Whatever died, stop cleanly (zero, Hold if ours) and let systemd restart us passive.
        self.request_shutdown(f"internal error in {name}", exit_code=exitcodes.INTERNAL_ERROR)

    @property
    def exit_code(self) -> int:
        """The process's exit code (:class:`~companion.service.lifecycle.Lifecycle` keeps it)."""
        return self.lifecycle.exit_code

    @exit_code.setter
    def exit_code(self, code: int) -> None:
        self.lifecycle.exit_code = code

    def request_shutdown(self, reason: str = "requested", exit_code: int | None = None) -> None:
        """Begin a clean shutdown (call on the loop; see :meth:`request_shutdown_threadsafe`)."""
        self.lifecycle.request_exit(reason, exit_code)

    def request_shutdown_threadsafe(self, reason: str = "requested") -> None:
        self.lifecycle.request_exit_threadsafe(reason)

    async def _stop(self) -> None:
        """Zero, Hold if we own offboard, stop the stream; then everything else goes."""
        self._notify("STOPPING=1", "STATUS=stopping: zero setpoint, leaving offboard if ours")
        timeout_s = self.config.service.shutdown_timeout_s
        fut = self._submit(Shutdown())
        deadline = self._clock() + timeout_s
        control_alive = any(t.get_name() == "control loop" and not t.done() for t in self._tasks)
        while control_alive and not self.supervisor.finished and self._clock() < deadline:
            await asyncio.sleep(0.02)
            control_alive = any(t.get_name() == "control loop" and not t.done() for t in self._tasks)
        if fut is not None and not fut.done():
            fut.cancel()
        if not self.supervisor.finished:
            log.warning(
                "Hold not confirmed within %.1f s: stopping the setpoint stream anyway (PX4's offboard-loss "
                "failsafe takes over if it is still in offboard)",
                timeout_s,
            )
            await self._safe_link_call("stop_setpoints")
        await self._publish_health()

    async def _cleanup(self) -> None:
        """Release everything; safe after a failed start and safe twice.

        Bounded: every step gets its own budget, and all together at most :data:`CLEANUP_BUDGET_S`
        (a task that ignores its cancellation, a thread blocked in a call, a vehicle link that does
        not close are logged and left; :func:`run_service` then ends the process anyway).
        """
        deadline = time.monotonic() + CLEANUP_BUDGET_S

        def budget(own_s: float) -> float:
            return max(0.05, min(own_s, deadline - time.monotonic()))

        loop = asyncio.get_running_loop()

        async def in_thread(what: str, fn: Callable[[], Any], own_s: float) -> None:
            try:
                await asyncio.wait_for(asyncio.shield(loop.run_in_executor(None, fn)), budget(own_s))
            except asyncio.TimeoutError:
                log.error("%s did not finish within its %.1f s; leaving it", what, own_s)

        for part in (self.presence, self.health_loop):
            await part.stop(budget(_STEP_BUDGET_S))
        tasks = list(self._tasks) + list(self._action_tasks)
        for task in tasks:
            task.cancel()
        if tasks:
            # Their errors were logged by _task_done / the action runners; a task that ignores its
            # cancellation must not hang the shutdown.
            _, stuck = await asyncio.wait(tasks, timeout=budget(_STEP_BUDGET_S))
            for task in stuck:
                log.error("task %s did not stop within %.1f s; leaving it", task.get_name(), _STEP_BUDGET_S)
        self._tasks = []
        self._action_tasks.clear()
        if self.view is not None:
            await in_thread("the preview", self.view.close, _STEP_BUDGET_S)
            self.view = None
        if self.control_server is not None:
            await in_thread("the control server", functools.partial(self.control_server.stop, budget(_STEP_BUDGET_S)), 2 * _STEP_BUDGET_S)
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        if self._capture is not None:
            await in_thread("the capture thread", functools.partial(self._capture.stop, budget(_STEP_BUDGET_S)), 2 * _STEP_BUDGET_S)
        if self._processor is not None:
            await in_thread("the pipeline thread", functools.partial(self._processor.stop, budget(_STEP_BUDGET_S)), 2 * _STEP_BUDGET_S)
            self._processor = None
        if self._histogram_pool is not None:
            # A job under way finishes (tens of milliseconds); its result is not wanted any more.
            pool, self._histogram_pool = self._histogram_pool, None
            await in_thread("the detour histogram", functools.partial(pool.shutdown, wait=True, cancel_futures=True), _STEP_BUDGET_S)
        if self._pipeline is not None:
            closer = getattr(self._pipeline.estimator, "close", None)  # the GPU backend frees its memory
            if closer is not None:
                try:
                    closer()
                except Exception:
                    log.exception("releasing the disparity backend failed")
            self._pipeline = None
        if self.link is not None:
            try:
                # MAVSDK's calls run in threads; one that blocks must not hold the exit.
                await asyncio.wait_for(self.link.close(), budget(_STEP_BUDGET_S))
            except asyncio.TimeoutError:
                log.error("the vehicle link did not close within %.1f s; leaving it", _STEP_BUDGET_S)
            except Exception:
                log.exception("closing the vehicle link failed")
        if self._notifier is not None:
            self._notifier.close()
            self._notifier = None

    # ================================================================================ signals

    def _setup_signals(self) -> None:
        self.lifecycle.install_signals()

    def _on_hup(self) -> None:
        log.info("SIGHUP: reloading %s", self.config_path or "(no config file)")
        assert self._loop is not None
        task = self._loop.create_task(self._reload_logged())
        self._action_tasks.add(task)
        task.add_done_callback(self._action_tasks.discard)

    async def _reload_logged(self) -> None:
        try:
            result = await self.reload()
            log.info("reload applied: %s", result)
        except CompanionError as err:
            log.error("reload rejected, the old config stays: %s", err)  # reload() recorded it in health
        except Exception as err:  # a bug: the old config stays, and health says so
            log.exception("reload failed, the old config stays")
            self._error(f"reload failed, the old config stays: {type(err).__name__}: {err}", kind="config")

    # ================================================================================ frames

    def _call_on_loop(self, fn: Callable[..., None], *args: Any) -> None:
        """From another thread: run ``fn(*args)`` on the event loop (dropped once the loop is gone)."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:
            pass  # the loop closed between the check and the call: we are shutting down

    def _on_camera_status_threadsafe(self, state: str) -> None:
        self._call_on_loop(self._on_camera_status, state)

    def _on_camera_status(self, state: str) -> None:
        if state in ("reconnecting", "ended") and self._capture is not None:
            self._error(f"camera: {self._capture.status().last_error}")
        if state == "streaming" and self._pipeline is not None and self._processor is not None:
            # A new stream: the release filter's memory is of the old one.
            self._processor.submit(self._pipeline.reset)
        self._wake_control()
        self._kick_health()

    def _process(self, frame: Frame) -> Any:
        """In the pipeline thread: one frame -> FrameResult (FrameError etc. go to _on_result)."""
        key = (frame.seq, frame.timestamp_s)
        if key == self._last_processed_key:
            # Cannot happen with the mailbox; counted (and refused) to prove it. (A sequence number
            # that goes back is not this: a source may restart its count when it is reopened.)
            self._processed_twice += 1
            raise FrameError(f"frame {frame.seq} handed over twice")
        self._last_processed_key = key
        view = self.view
        want = view is not None and view.wants_frame()  # a viewer watches and a preview is due
        result = self._pipeline.process(frame.image, frame.timestamp_s, want_disparity=want)
        if want:
            view.offer(frame, result, self._pipeline)  # references only; drawn in the preview thread
        return result

    def _on_result_threadsafe(self, frame: Frame, result: Any, err: BaseException | None) -> None:
        self._call_on_loop(self._on_result, frame, result, err, self._clock())

    def _on_result(self, frame: Frame, result: Any, err: BaseException | None, done_s: float) -> None:
        """On the loop: record a frame's outcome and wake the control loop."""
        if err is not None:
            self._frame_errors += 1
            if isinstance(err, FrameError):
                self._error(f"frame {frame.seq} rejected: {err}")
                log.warning("frame %d rejected: %s", frame.seq, err)
            elif isinstance(err, CompanionError):
                self._error(f"frame {frame.seq}: {err}")
                log.error("frame %d: %s", frame.seq, err)
            else:  # a bug in a stage: keep flying safely (frames age -> zero velocity -> Hold)
                self._error(f"frame {frame.seq}: internal error {type(err).__name__}: {err}")
                log.error("processing frame %d failed", frame.seq, exc_info=err)
            return
        self._processed += 1
        self._processed_times.append(done_s)
        if self.record_seqs:
            self.processed_seqs.append(frame.seq)
        self._latest = Processed(result=result, seq=frame.seq, done_s=done_s)
        if self._first_result is not None:
            self._first_result.set()
        self._wake_control()

    # ================================================================================ control loop

    def _wake_control(self) -> None:
        if self._wake is not None:
            self._wake.set()

    def _kick_health(self) -> None:
        self.health_loop.kick()

    def _submit(self, request: Any) -> asyncio.Future | None:
        """Queue a supervisor request for the next step; the future gets its :class:`Reply`."""
        if self._loop is None:
            return None
        fut = None if isinstance(request, ActionResult) else self._loop.create_future()
        self._pending.append((request, fut))
        self._wake_control()
        return fut

    async def _control_loop(self) -> None:
        assert self._wake is not None
        next_tick = self._clock()
        while True:
            period = 1.0 / self.config.vehicle.setpoint_rate_hz
            wake_at = next_tick
            stale_at = self._stale_deadline()
            if stale_at is not None and self._clock() < stale_at < wake_at:
                # The zero for stale frames goes out when the newest frame turns stale, not up to a
                # setpoint period later (the promise is 0.5 s, not 0.5 s plus a tick).
                wake_at = stale_at
            timeout = wake_at - self._clock()
            if timeout > 0:
                await wait_event(self._wake, timeout)
            self._wake.clear()
            now = self._clock()
            ticked = now >= next_tick
            if ticked:
                next_tick += period
                if next_tick <= now:
                    next_tick = now + period  # we were late: no burst of catch-up steps
            try:
                await self._control_step(now, ticked)
            except asyncio.CancelledError:
                raise
            except Exception as err:
                # A bug here must not leave MAVSDK re-sending a stale setpoint: zero now, then a clean
                # shutdown (Hold if ours) and a restart by systemd, passive.
                log.exception("control step failed")
                self._error(f"internal error in the control loop: {type(err).__name__}: {err}")
                await self._safe_link_call("send_setpoint", ZERO_SETPOINT)
                raise
            self._feed_watchdog(now)

    def _stale_deadline(self) -> float | None:
        """Clock time (s) just past the moment the newest frame turns stale, or None without one."""
        latest = self._latest
        if latest is None:
            return None
        # Just past: the supervisor counts a frame exactly ``stale_frame_timeout_s`` old as fresh.
        return latest.result.timestamp_s + self.config.command.stale_frame_timeout_s + 1e-3

    async def _control_step(self, now: float, ticked: bool) -> None:
        latest = self._latest
        new_frame = latest is not None and latest.seq != self._last_stepped_seq
        pending, self._pending = self._pending, []
        capture = self._capture.status() if self._capture is not None else None
        vehicle = self.link.state() if self.link is not None else None
        if vehicle is None:
            from companion.interfaces import VehicleState

            vehicle = VehicleState()
        camera_ok = capture.ok if capture is not None else False
        histogram, self._histogram_done = self._histogram_done, None
        out = self.supervisor.step(
            now,
            latest.result if latest is not None else None,
            vehicle,
            [r for r, _ in pending],
            camera_ok=camera_ok,
            histogram=histogram,
        )
        self._plan_off_loop(out.histogram_request)
        replies = iter(out.replies)
        for _, fut in pending:
            if fut is None:
                continue
            reply = next(replies)
            if not fut.done():
                fut.set_result(reply)
        if out.setpoint is not None:
            sent = await self._safe_link_call("send_setpoint", out.setpoint)
            if sent:
                t_sent = self._clock()
                self._last_setpoint = out.setpoint
                self._last_setpoint_s = t_sent
                self._setpoints_sent += 1
                if new_frame and self.supervisor.engaged and latest is not None:
                    latency = t_sent - latest.result.timestamp_s
                    self._last_latency_s = latency
                    self._latency_s.append(latency)
                    if self.record_latencies:
                        self.latencies_s.append(latency)
        self.presence.step(now, out, latest, new_frame, camera_ok)
        if new_frame and latest is not None:
            self._last_stepped_seq = latest.seq
        for action in out.actions:
            if action is Action.STOP_SETPOINTS:
                # Right after the final zero, on the loop: nothing non-zero is ever left to re-send.
                await self._safe_link_call("stop_setpoints")
            else:
                self._run_action(action)
        if out.changed:
            log.info("state %s: %s", out.state.value, out.reason)
            self._notify(f"STATUS={out.state.value}: {out.reason}")
            self._kick_health()

    def _plan_off_loop(self, request: HistogramRequest | None) -> None:
        """Hand the detour layer's histogram request to the worker thread (one job at a time; a request
        already handed over is not computed again). Its result is offered at the next step."""
        if request is None or self._histogram_job is not None or request.seq == self._histogram_asked:
            return
        loop = self._loop
        assert loop is not None
        if self._histogram_pool is None:
            self._histogram_pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="detour-histogram")
        self._histogram_job = request
        self._histogram_asked = request.seq
        fut = loop.run_in_executor(self._histogram_pool, self._histogram_fn, request)
        fut.add_done_callback(functools.partial(self._on_histogram, request))

    def _on_histogram(self, request: HistogramRequest, fut: asyncio.Future) -> None:
        """On the loop: the worker finished ``request``; keep the result (or the failure) for the next
        step, which hands it to the supervisor (a stale one is dropped there)."""
        self._histogram_job = None
        if fut.cancelled():
            return
        err = fut.exception()
        if err is None:
            self.histogram_stats["computed"] += 1
            self._histogram_done = HistogramResult(request.seq, fut.result())
        else:
            # Not swallowed: logged with its context, and the detour ends in a hold that says why.
            self.histogram_stats["failed"] += 1
            log.error(
                "detour histogram failed (request %d asked at %.3f s, %d map points, goal bearing %.1f deg)",
                request.seq,
                request.asked_s,
                len(request.points_ne_m),
                math.degrees(request.goal_bearing_rad),
                exc_info=err,
            )
            self._error(f"detour histogram: {type(err).__name__}: {err}")
            self._histogram_done = HistogramResult(request.seq, None, f"{type(err).__name__}: {err}")
        self._wake_control()

    def _run_action(self, action: Action) -> None:
        """START_OFFBOARD / HOLD wait for the autopilot's ack (seconds): run them beside the loop and
        report the outcome to the supervisor."""

        async def runner() -> None:
            assert self.link is not None
            try:
                if action is Action.START_OFFBOARD:
                    await self.link.start_offboard()
                else:
                    await self.link.hold()
                self._submit(ActionResult(action, True))
                log.info("%s accepted", action.value)
            except VehicleError as err:
                log.warning("%s failed: %s", action.value, err)
                self._error(f"{action.value}: {err}")
                self._submit(ActionResult(action, False, str(err)))
            except asyncio.CancelledError:
                raise
            except Exception as err:
                log.exception("%s failed", action.value)
                self._error(f"{action.value}: {type(err).__name__}: {err}")
                self._submit(ActionResult(action, False, f"{type(err).__name__}: {err}"))

        assert self._loop is not None
        task = self._loop.create_task(runner(), name=action.value)
        self._action_tasks.add(task)
        task.add_done_callback(self._action_tasks.discard)

    async def _safe_link_call(self, name: str, *args: Any) -> bool:
        if self.link is None:
            return False
        try:
            await getattr(self.link, name)(*args)
            return True
        except VehicleError as err:
            self._error(f"vehicle: {err}")
            log.debug("%s: %s", name, err)
        except asyncio.CancelledError:
            raise
        except Exception as err:
            log.exception("vehicle link %s failed", name)
            self._error(f"vehicle link {name}: {type(err).__name__}: {err}")
        return False

    def _feed_watchdog(self, now: float) -> None:
        # Only here: a stalled control loop starves the watchdog and systemd kills the process.
        if self._watchdog_s is None or self._notifier is None:
            return
        if now - self._last_watchdog_s >= self._watchdog_s / 4.0:
            self._last_watchdog_s = now
            self._notifier.notify("WATCHDOG=1")

    def _notify(self, *fields: str) -> None:
        if self._notifier is not None:
            self._notifier.notify(*fields)

    def _error(self, message: str, kind: str = "fault") -> None:
        """Record ``message`` as health's ``last_error``; ``kind`` "config" marks a rejected config change."""
        self._last_error = message
        self._last_error_kind = kind

    def _clear_error(self, kind: str) -> None:
        """Forget ``last_error`` when it is of ``kind`` (a good reload clears an earlier rejection)."""
        if self._last_error_kind == kind:
            self._last_error = None
            self._last_error_kind = None

    def _control_server_error(self, message: str) -> None:
        """From the control server's thread: a request failed with a bug, or the thread itself died."""
        self._call_on_loop(self._error, message)
        if self.control_server is not None and self.control_server.error is not None:
            # Nobody could command or stop the service any more: stop cleanly (zero, Hold if ours).
            self._call_on_loop(self.request_shutdown, "control server failed", exitcodes.INTERNAL_ERROR)

    @property
    def engaged_or_engaging(self) -> bool:
        """True from an accepted engage until the service stops commanding (live changes are limited then)."""
        return self.supervisor.state in (State.ENGAGING, State.ENGAGED, State.DEGRADED, State.PAUSED, State.OVERRIDE)

    def _vehicle_connected(self) -> bool:
        """Whether the autopilot is connected now (the link has heard it and says so)."""
        link = self.link
        return link is not None and self._vehicle_status == "connected" and link.state().connected

    async def _vehicle_connector(self) -> None:
        assert self.link is not None
        timeout_s = self.config.vehicle.connect_timeout_s
        # "still waiting": the first at once, then less and less often (up to every 10 min).
        backoff = LogBackoff(first_interval_s=timeout_s, max_interval_s=max(timeout_s, 600.0))
        while True:
            try:
                await self.link.connect(timeout_s)
            except VehicleError as err:
                if err.context.get("kind") == "connection":
                    self._error(str(err))
                    self.request_shutdown(str(err), exit_code=exitcodes.STARTUP_FAILURE)
                    return
                self._vehicle_status = "waiting"
                now = self._clock()
                if backoff.due(now):
                    log.warning("%s; still waiting (%.0f s so far; next report in %.0f s)",
                                err, backoff.elapsed_s(now) + timeout_s, backoff.interval_s)
                else:
                    log.debug("%s; still waiting", err)
                continue
            self._vehicle_status = "connected"
            self._kick_health()
            return



def run_service(config_path: Path | None) -> int:
    """``companion run``: load the config, run the daemon, return the exit code (78 on startup failure)."""
    try:
        cfg = load_config(config_path)
    except ConfigError as err:
        log.error("startup failed: %s", err)
        notifier = Notifier.from_environment()
        if notifier is not None:
            notifier.notify(f"STATUS=startup failed: {err}")
            notifier.close()
        return exitcodes.STARTUP_FAILURE
    service = Service(cfg, config_path=config_path.resolve() if config_path is not None else None)
    return run_to_exit(service.run())


def run_to_exit(main: Any) -> int:
    """Run coroutine ``main`` (returning an exit code) on a new event loop, and make sure nothing
    holds the process afterwards.

    Unlike ``asyncio.run``, it does not wait without limit for the default executor's threads: a
    MAVSDK call blocked in one (its calls run there) would hold the exit for ever. Leftover tasks get
    :data:`_STEP_BUDGET_S`, threads :data:`EXIT_JOIN_S`; a thread still running then is logged by name
    and the process ends at once with the exit code (the vehicle is already safe: zero, Hold or the
    autopilot's offboard-loss failsafe).
    """
    loop = asyncio.new_event_loop()
    executor = concurrent.futures.ThreadPoolExecutor(thread_name_prefix="service-io")
    loop.set_default_executor(executor)
    try:
        code = loop.run_until_complete(main)
        leftovers = [t for t in asyncio.all_tasks(loop) if not t.done()]
        for task in leftovers:
            task.cancel()
        if leftovers:
            loop.run_until_complete(asyncio.wait(leftovers, timeout=_STEP_BUDGET_S))
        loop.run_until_complete(loop.shutdown_asyncgens())
    finally:
        executor.shutdown(wait=False, cancel_futures=True)
        loop.close()
    deadline = time.monotonic() + EXIT_JOIN_S
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join(max(0.0, deadline - time.monotonic()))
    stuck = [t.name for t in threading.enumerate() if t is not threading.current_thread() and not t.daemon and t.is_alive()]
    if stuck:
        log.error("exiting with threads still blocked (%s): not waiting for them", ", ".join(stuck))
        flush_logs()
        os._exit(code)
    return code
