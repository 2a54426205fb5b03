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

The control loop never waits for the pipeline: it steps on a fixed grid (``vehicle.setpoint_rate_hz``)
whatever the vision rate, and also as soon as a new result arrives, so a decision reaches the vehicle
without waiting for the next tick. Every change to the supervisor's state happens on the loop. If the
control loop stalls, the watchdog is not fed and systemd kills
the process (MAVSDK's 20 Hz re-sending dies with it), and PX4's offboard-loss failsafe takes over.

Shutdown (first SIGTERM/SIGINT): the supervisor sends zero and, if we own offboard, Hold; then the
stream stops (no mode change), ZeroMQ closes, the camera and the pipeline (GPU) are released, each
within its budget (:data:`CLEANUP_BUDGET_S` in all). A second signal exits at once with
:data:`~companion.exitcodes.FORCED_EXIT`. SIGHUP reloads the config file. When the process ends, and
with which code, is the :class:`~companion.service.lifecycle.Lifecycle`'s.

:class:`Service` is a composition of parts, each with its own state, ``start`` and ``stop(budget_s)``
(:mod:`companion.service.parts`): the vehicle connection (:mod:`~companion.service.connection`), the
pipeline and capture (:mod:`~companion.service.frames`), presence, the control loop
(:mod:`~companion.service.control_loop`), health and the control plane with its server
(:mod:`~companion.service.control`). Service only wires them and keeps the order: it starts them one
after another and, at the end, stops the started ones in reverse, within one total budget.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import gc
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion import exitcodes
from companion.config import CompanionConfig, load_config
from companion.core.rig_check import check_rig_config
from companion.core.safety import near_blindness
from companion.core.supervisor import Shutdown, Supervisor, SupervisorConfig
from companion.errors import CompanionError, ConfigError
from companion.framepool import FrameBuffers
from companion.interfaces import CameraSource, VehicleLink
from companion.service import protocol
from companion.service.aio import wait_event
from companion.service.capture import FrameMailbox
from companion.service.connection import VehicleConnection
from companion.service.control import (  # noqa: F401 (re-exported: the daemon's public names)
    ControlPlane,
    ControlServer,
    RequestRefused,
    keep_restart_fields,
    resolve_config_paths,
    restart_required,
)
from companion.service.control_loop import ControlLoop
from companion.service.frames import CapturePart, PipelinePart, Processed  # noqa: F401 (Processed re-exported)
from companion.service.health import HealthLoop, HealthReporter, HealthSources
from companion.service.lifecycle import Lifecycle, flush_logs
from companion.service.notify import Notifier, watchdog_interval_s
from companion.service.parts import LastError, Parts, StartupError, call_on_loop  # noqa: F401 (StartupError re-exported)
from companion.service.presence import Presence
from companion.service.runtime import raise_open_file_limit

log = logging.getLogger(__name__)

Clock = Callable[[], float]


#: The longest the release of everything may take after the vehicle is safe (zero, Hold or its
#: timeout), seconds; each part has its own smaller budget (:data:`_STEP_BUDGET_S` unless it says).
CLEANUP_BUDGET_S = 1.5
_STEP_BUDGET_S = 0.5
#: After the event loop ends, how long threads still running get before the process exits without
#: them (a MAVSDK call blocked in its thread), seconds.
EXIT_JOIN_S = 0.3


class _Closing:
    """A part that is only closed (the bus, the preview plane): ``close`` on the loop or in a thread."""

    def __init__(self, name: str, close: Callable[[], None], in_thread: bool) -> None:
        self.name = name
        self._close = close
        self._in_thread = in_thread

    def start(self) -> None:
        """Opened by its owner; nothing to start."""

    async def stop(self, budget_s: float) -> bool:
        if not self._in_thread:
            self._close()
            return True
        loop = asyncio.get_running_loop()
        try:
            await asyncio.wait_for(asyncio.shield(loop.run_in_executor(None, self._close)), budget_s)
            return True
        except asyncio.TimeoutError:
            log.error("%s did not close within its %.1f s; leaving it", self.name, budget_s)
            return False


class Service:
    """The daemon: one small lifecycle object that owns the parts and the order of their start and stop.
    Build it, then ``await run()`` (or :func:`run_service` from the CLI).

    Args:
        cfg: the configuration (validated).
        config_path: the file it came from (for ``reload`` and SIGHUP), or None.
        camera: the camera source; default: the one ``cfg.camera`` names.
        link: the vehicle link; default: MAVSDK on ``cfg.vehicle.connection``.
        clock: monotonic clock, seconds (the clock of frame timestamps).
        install_signals: handle SIGTERM/SIGINT/SIGHUP (only possible in the main thread).
        notifier: sd_notify sender; default: from ``$NOTIFY_SOCKET`` (None when not under systemd).
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
    ) -> None:
        self._clock = clock
        self._install_signals = install_signals
        self._environ = dict(os.environ) if environ is None else environ
        self._notifier = notifier if notifier is not None else Notifier.from_environment(self._environ)
        self._watchdog_s = watchdog_interval_s(self._environ)
        self._last_watchdog_s = -1e9
        self._loop: asyncio.AbstractEventLoop | None = None
        self.errors = LastError()
        self.lifecycle = Lifecycle(on_reload=self._on_hup)
        self.ready = threading.Event()  # set once READY=1 was sent (for tests and embedding)
        self.stopped = threading.Event()
        self.bus: Any = None
        self.view: Any = None  # companion.service.preview.ViewPlane: the preview and the flight recording
        self.parts = Parts()
        config = lambda: self.control.config  # noqa: E731 (the config in force, read at each use)
        mailbox = FrameMailbox()
        frame_buffers = FrameBuffers()  # the GPU backend's pinned buffers for the camera, or none
        self.vehicle = VehicleConnection(
            link,
            config=config,
            clock=clock,
            on_error=self.errors.record,
            on_fatal=lambda reason: self.request_shutdown(reason, exit_code=exitcodes.STARTUP_FAILURE),
            on_connected=self._kick_health,
            on_died=self._part_died,
        )
        self.vision = PipelinePart(
            mailbox,
            frame_buffers,
            view=lambda: self.view,
            on_result=self._wake_control,
            on_error=self.errors.record,
            clock=clock,
        )
        self.capture = CapturePart(
            mailbox, frame_buffers, camera=camera, on_status=self._on_camera_status_threadsafe, clock=clock
        )
        cfg = resolve_config_paths(cfg, config_path.parent if config_path else None)
        supervisor = Supervisor(SupervisorConfig.from_config(cfg))
        self.control = ControlPlane(
            cfg,
            config_path=config_path,
            clock=clock,
            supervisor=supervisor,
            submit=lambda request: self.control_loop.submit(request),
            status=self.health_message,
            engaged=lambda: self.control_loop.engaged_or_engaging,
            pipeline=self.vision,
            capture=self.capture,
            errors=self.errors,
            on_applied=self._kick_health,
            on_server_failed=lambda what: self.request_shutdown(what, exitcodes.INTERNAL_ERROR),
        )
        self.presence = Presence(
            config=config,
            link=lambda: self.vehicle.link,
            connected=self.vehicle.connected,
            state=lambda: self.supervisor.state.value,
            engaged=lambda: self.supervisor.engaged,
            clock=clock,
            on_died=self._part_died,
        )
        self.control_loop = ControlLoop(
            supervisor,
            config=config,
            clock=clock,
            link=lambda: self.vehicle.link,
            latest=lambda: self.vision.latest,
            capture=self.capture.status,
            after_step=self.presence.step,
            on_changed=self._state_changed,
            on_error=self.errors.record,
            feed_watchdog=self._feed_watchdog,
            on_died=self._part_died,
        )
        self.health = HealthReporter(
            HealthSources(
                clock=clock,
                config=lambda: (self.control.config, self.control.config_version),
                supervisor=self.control_loop.supervisor,
                frames=self.vision.counts,
                latest=lambda: self.vision.latest,
                capture=self.capture.status,
                vehicle=self._vehicle_snapshot,
                setpoints=self.control_loop.counts,
                control=self.control.counts,
                mavlink=self.presence.status,
                preview=lambda: (
                    self.view.publisher.status() if self.view is not None and self.view.publisher is not None else None
                ),
                last_error=lambda: self.errors.message,
            )
        )
        self.health_loop = HealthLoop(self._publish_health, lambda: self.config.bus.health_rate_hz, on_died=self._part_died)

    # ================================================================================ what others read

    @property
    def config(self) -> CompanionConfig:
        """The config in force (the control plane's)."""
        return self.control.config

    @property
    def config_path(self) -> Path | None:
        return self.control.config_path

    @property
    def config_version(self) -> int:
        return self.control.config_version

    @property
    def supervisor(self) -> Any:
        """The control loop's supervisor (companion.core.supervisor.Supervisor)."""
        return self.control_loop.supervisor

    @property
    def link(self) -> Any:
        """The vehicle link (None before the start made one)."""
        return self.vehicle.link

    @property
    def control_server(self) -> ControlServer | None:
        return self.control.server

    @property
    def latencies_s(self) -> list[float]:
        """Every frame-to-setpoint latency while ``record_latencies`` (bench), seconds."""
        return self.control_loop.latencies_s

    @property
    def record_latencies(self) -> bool:
        return self.control_loop.record_latencies

    @record_latencies.setter
    def record_latencies(self, on: bool) -> None:
        self.control_loop.record_latencies = on

    @property
    def processed_seqs(self) -> list[int]:
        """Every processed frame's seq while ``record_seqs`` (bench)."""
        return self.vision.processed_seqs

    @property
    def record_seqs(self) -> bool:
        return self.vision.record_seqs

    @record_seqs.setter
    def record_seqs(self, on: bool) -> None:
        self.vision.record_seqs = on

    @property
    def engaged_or_engaging(self) -> bool:
        return self.control_loop.engaged_or_engaging

    def health_message(self) -> dict[str, Any]:
        """The health message (the field list: docs/service.md)."""
        return self.health.message()

    async def handle_request(self, request: Any) -> dict[str, Any]:
        """Carry out one validated control request (:meth:`ControlPlane.handle_request`)."""
        return await self.control.handle_request(request)

    async def apply_config(self, new: CompanionConfig, source: str, from_file: bool = False) -> dict[str, Any]:
        return await self.control.apply_config(new, source, from_file)

    async def reload(self) -> dict[str, Any]:
        return await self.control.reload()

    def _vehicle_snapshot(self) -> tuple[Any, str]:
        link = self.vehicle.link
        state = link.state() if link is not None else None
        return state, self.vehicle.link_status(state)

    # ================================================================================ lifecycle

    async def run(self) -> int:
        """Start, serve until a shutdown is requested, stop cleanly. Returns the process exit code."""
        self._loop = asyncio.get_running_loop()
        self.lifecycle.bind(self._loop)
        self.control_loop.bind(self._loop)
        self.control.bind(self._loop)
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
        self.errors.record(f"startup failed: {err}")
        await self._cleanup()
        self.exit_code = exitcodes.STARTUP_FAILURE
        self.stopped.set()
        return self.exit_code

    async def _start(self) -> None:
        """Start the parts in order; each one started is stopped (in reverse) by :meth:`_cleanup`."""
        cfg = self.config
        if self._install_signals:
            self.lifecycle.install_signals()
        check_rig_config(cfg, str(self.config_path or "config"))
        blind = near_blindness(cfg)
        if blind is not None:
            raise StartupError(f"config: {blind}")
        from companion.service.bus import Bus

        raise_open_file_limit()
        self.bus = Bus(cfg.bus, environ=self._environ)
        self.bus.open()
        self.parts.started(_Closing("the bus", self._close_bus, in_thread=False))
        from companion.service.preview import ViewPlane

        # Off the flight path (own threads); one that cannot start is reported, and the service flies on.
        self.view = ViewPlane(lambda: self.config, clock=self._clock, on_error=self.errors.record, environ=self._environ)
        self.parts.started(_Closing("the preview", self._close_view, in_thread=True))
        self.view.open(self.bus.health_endpoint)
        from companion.jitcache import use_cache_dir_or_memory

        # Before the pipeline is built (its map input's kernels bind their cache when first imported).
        use_cache_dir_or_memory(log)
        self.parts.started(self.vision)
        await self.vision.start(cfg)
        from companion.core.planner import compile_kernels

        # The local planner's compiled kernels now, not at the first tick of the first flight; loaded
        # from the cache folder after the first start.
        await asyncio.to_thread(compile_kernels)
        # The link before the camera: a simulated camera may render from the vehicle's telemetry.
        self.parts.started(self.vehicle)
        await self.vehicle.open()
        self.vehicle.start()
        self.parts.started(self.presence)
        self.presence.start()
        self.capture.open(cfg, self.vehicle.link)
        self.parts.started(self.capture)
        self.capture.start(cfg)
        # Ready means the whole chain works: a frame captured AND processed.
        assert self.vision.first_result is not None
        await wait_event(self.vision.first_result, cfg.camera.open_timeout_s)
        if self.vision.latest is None:
            status = self.capture.status()
            assert status is not None
            what = "no frame" if status.frames == 0 else "no frame processed"
            problem = self.errors.message or status.last_error
            raise StartupError(
                f"camera {status.source}: {what} within camera.open_timeout_s = {cfg.camera.open_timeout_s:g} s"
                + (f" ({problem})" if problem else "")
            ) from None
        self.parts.started(self.control_loop)
        self.control_loop.start()
        self.parts.started(self.health_loop)
        self.health_loop.start()
        self.parts.started(self.control)
        self.control.start(self.bus)

    def _close_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            bus.close()

    def _close_view(self) -> None:
        view, self.view = self.view, None
        if view is not None:
            view.close()

    def _part_died(self, name: str, err: BaseException) -> None:
        """A part's task ended with an error: stop cleanly."""
        log.error("task %s died: %r", name, err, exc_info=err)
        self.errors.record(f"internal error in {name}: {type(err).__name__}: {err}")
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
        fut = self.control_loop.submit(Shutdown())
        deadline = self._clock() + timeout_s
        while self.control_loop.running and not self.supervisor.finished and self._clock() < deadline:
            await asyncio.sleep(0.02)
        if fut is not None and not fut.done():
            fut.cancel()
        if not self.supervisor.finished:
            log.warning(
                "Hold not confirmed within %.1f s: stopping the setpoint stream anyway (PX4's offboard-loss "
                "failsafe takes over if it is still in offboard)",
                timeout_s,
            )
            await self.control_loop.link_call("stop_setpoints")
        await self._publish_health()

    async def _cleanup(self) -> None:
        """Stop the started parts in reverse order; safe after a failed start and safe twice.

        Bounded: every part gets its own budget, and all together at most :data:`CLEANUP_BUDGET_S`
        (a task that ignores its cancellation, a thread blocked in a call, a vehicle link that does
        not close are logged and left; :func:`run_service` then ends the process anyway).
        """
        await self.parts.stop_all(CLEANUP_BUDGET_S, _STEP_BUDGET_S)
        if self._notifier is not None:
            self._notifier.close()
            self._notifier = None

    # ================================================================================ wiring

    def _on_hup(self) -> None:
        log.info("SIGHUP: reloading %s", self.config_path or "(no config file)")
        self.control.reload_in_background()

    def _on_camera_status_threadsafe(self, state: str) -> None:
        call_on_loop(self._loop, self._on_camera_status, state)

    def _on_camera_status(self, state: str) -> None:
        status = self.capture.status()
        if state in ("reconnecting", "ended") and status is not None:
            self.errors.record(f"camera: {status.last_error}")
        if state == "streaming":
            # A new stream: the release filter's memory is of the old one.
            self.vision.reset()
        self._wake_control()
        self._kick_health()

    def _wake_control(self) -> None:
        self.control_loop.wake()

    def _kick_health(self) -> None:
        self.health_loop.kick()

    def _state_changed(self, out: Any) -> None:
        self._notify(f"STATUS={out.state.value}: {out.reason}")
        self._kick_health()

    async def _publish_health(self) -> None:
        if self.bus is None:
            return
        try:
            self.bus.publish(protocol.encode(self.health_message()))
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("publishing health failed")

    def _feed_watchdog(self, now: float) -> None:
        # Only after a control step: a stalled control loop starves the watchdog and systemd kills the process.
        if self._watchdog_s is None or self._notifier is None:
            return
        if now - self._last_watchdog_s >= self._watchdog_s / 4.0:
            self._last_watchdog_s = now
            self._notifier.notify("WATCHDOG=1")

    def _notify(self, *fields: str) -> None:
        if self._notifier is not None:
            self._notifier.notify(*fields)


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
