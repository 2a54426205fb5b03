"""The service's control plane: the control server's thread, request dispatch and live config changes.

Two parts:

* :class:`~companion.service.control_server.ControlServer` (:mod:`companion.service.control_server`)
  owns the ZeroMQ ROUTER socket in a thread of its own, with the budgets.
* :class:`ControlPlane`, an object the daemon holds (a part with ``start`` and ``stop``), owns the
  config in force and the control server, and carries a request out on the flight loop: supervisor requests (engage, disengage, pause, resume, override) go
  to the control loop; a config change or reload is validated whole, checked against the safety
  envelope (:mod:`companion.config.envelope`) and against what may change while engaged
  (:func:`live_change_refusal`), and the controller must still see a near obstacle as near
  (:func:`~companion.core.safety.near_blindness`); only then is it built (in the pipeline thread) and
  swapped in. A rejected one leaves the old in force.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.config import CompanionConfig, apply_patch, load_config
from companion.config.service import LIVE_CAMERA_FIELDS, RESTART_FIELDS
from companion.config.view import VIEW_RESTART_FIELDS
from companion.core.rig_check import check_rig_config
from companion.core.safety import near_blindness
from companion.core.supervisor import Disengage, Engage, Goto, Override, Pause, Reply, Resume, SupervisorConfig
from companion.errors import CompanionError, ConfigError, ProtocolError
from companion.service.control_server import (  # noqa: F401 (re-exported)
    MAX_IN_FLIGHT,
    STOP_COMMANDS,
    ControlServer,
    ControlStats,
)
from companion.service.parts import LastError, call_on_loop, stop_in_thread

if TYPE_CHECKING:
    from companion.core.supervisor import Supervisor
    from companion.service.frames import CapturePart, PipelinePart

log = logging.getLogger(__name__)

#: What a live change may touch while engaged under ``envelope.live_changes_while_engaged = "tuning"``:
#: these sections only (not the planner's physics, the frame timeouts or the progress watchdog).
_TUNING_SECTIONS = ("controller", "lut", "sim")


class RequestRefused(CompanionError):
    """The supervisor refused an operator request (engage while disarmed, override when not engaged, ...)."""


def resolve_config_paths(cfg: CompanionConfig, base_dir: Path | None) -> CompanionConfig:
    """``cfg`` with relative file paths made absolute against ``base_dir`` (the config file's folder).

    A config file names files relative to itself, never to the working directory of whoever started
    the service. Without a file (``base_dir`` None) relative paths are left as given.
    """
    if base_dir is None:
        return cfg

    def fix(p: Path | None) -> Path | None:
        return None if p is None or p.is_absolute() else base_dir / p

    updates: dict[str, Any] = {}
    if cfg.calibration.file is not None and not cfg.calibration.file.is_absolute():
        updates["calibration"] = cfg.calibration.model_copy(update={"file": fix(cfg.calibration.file)})
    if cfg.camera.replay_path is not None and not cfg.camera.replay_path.is_absolute():
        updates["camera"] = cfg.camera.model_copy(update={"replay_path": fix(cfg.camera.replay_path)})
    bus_updates = {
        name: fix(getattr(cfg.bus, name))
        for name in ("curve_server_secret_key_file", "curve_authorized_keys_dir")
        if getattr(cfg.bus, name) is not None and not getattr(cfg.bus, name).is_absolute()
    }
    if bus_updates:
        updates["bus"] = cfg.bus.model_copy(update=bus_updates)
    return cfg.model_copy(update=updates) if updates else cfg


def restart_required(current: CompanionConfig, new: CompanionConfig) -> list[str]:
    """The dotted fields that differ and that only a restart applies (camera, bus, vehicle.connection)."""
    out = []
    for path in RESTART_FIELDS:
        section, _, name = path.partition(".")
        a, b = getattr(current, section), getattr(new, section)
        if name:
            if getattr(a, name) != getattr(b, name):
                out.append(path)
        else:
            live = LIVE_CAMERA_FIELDS if section == "camera" else ()
            out += [f"{section}.{f}" for f in type(a).model_fields if f not in live and getattr(a, f) != getattr(b, f)]
    return out


def keep_restart_fields(current: CompanionConfig, new: CompanionConfig) -> CompanionConfig:
    """``new`` with the restart-only fields of ``current`` (they are not applied until a restart)."""
    kept = [path.partition(".")[2] for path in RESTART_FIELDS if path.startswith("vehicle.")]
    vehicle = new.vehicle.model_copy(update={name: getattr(current.vehicle, name) for name in kept})
    camera = current.camera.model_copy(update={f: getattr(new.camera, f) for f in LIVE_CAMERA_FIELDS})
    view = new.view.model_copy(update={f: getattr(current.view, f) for f in VIEW_RESTART_FIELDS})
    return new.model_copy(update={"camera": camera, "bus": current.bus, "vehicle": vehicle, "view": view})


def changed_fields(current: CompanionConfig, new: CompanionConfig) -> list[str]:
    """Every ``section.field`` whose value differs between the two configs."""
    out = []
    for section in type(current).model_fields:
        a, b = getattr(current, section), getattr(new, section)
        if a != b:
            out += [f"{section}.{f}" for f in type(a).model_fields if getattr(a, f) != getattr(b, f)]
    return out


def live_change_refusal(current: CompanionConfig, new: CompanionConfig, *, engaged: bool, from_file: bool) -> str | None:
    """Why ``new`` may not replace ``current`` now (None: it may). ``new`` is what would apply (the
    restart-only fields already kept, :func:`keep_restart_fields`); ``from_file``: a reload, not a
    ``set_config``.

    * The envelope changes only from the file, and only while not engaged.
    * While engaged, ``current.envelope.live_changes_while_engaged`` says what else may change: none,
      tuning (the fuzzy controller, the lut and the simulated world), or any.
    """
    changed = changed_fields(current, new)
    envelope = [f for f in changed if f.startswith("envelope.")]
    if envelope and not from_file:
        return "set_config cannot change the safety envelope; edit the config file and reload while not engaged"
    if not engaged or not changed:
        return None
    if envelope:
        return f"the safety envelope changes only while not engaged ({', '.join(envelope)}): disengage first"
    policy = current.envelope.live_changes_while_engaged
    if policy == "any":
        return None
    if policy == "none":
        return f"no live changes while engaged (envelope.live_changes_while_engaged = none): {', '.join(changed)}"
    live_camera = {f"camera.{f}" for f in LIVE_CAMERA_FIELDS}  # they only move the simulated world
    refused = [f for f in changed if f not in live_camera and f.split(".")[0] not in _TUNING_SECTIONS]
    if refused:
        return (
            "while engaged only tuning may change (envelope.live_changes_while_engaged = tuning): "
            f"disengage first to change {', '.join(refused)}"
        )
    return None


@dataclass(frozen=True)
class ControlCounts:
    """The control server's counts (health's ``control``).

    Attributes:
        connections: live connections.
        received: messages received.
        rate_limited: requests refused by the request budgets.
        busy: requests refused by the bound on requests in progress.
        bad: malformed requests.
        replies_dropped: replies a client did not read.
        refused_connections: handshakes refused (too many connections).
    """

    connections: int
    received: int
    rate_limited: int
    busy: int
    bad: int
    replies_dropped: int
    refused_connections: int


class ControlPlane:
    """The control plane: the config in force (and its version), the requests carried out on the flight
    loop, and the control server part (:meth:`start`, :meth:`stop`) that reads the socket in its thread.

    Args:
        config: the validated config (relative paths already resolved against its file's folder).
        config_path: the file it came from (for ``reload``), or None.
        clock: monotonic seconds.
        supervisor: the control loop's supervisor (its state, for replies; its reconfigure).
        submit: queues a supervisor request for the control loop's next step; its future gets the reply.
        status: the health message now (the ``status`` request).
        engaged: whether the service commands now (live changes are limited then).
        pipeline: the pipeline part (a new config is built there before it is swapped in).
        capture: the capture part (a new config's camera placement).
        errors: health's ``last_error`` (a rejected reload stays there until a good change).
        on_applied: called after a change was applied (health publishes at once).
        on_server_failed: called on the loop with what failed when the control server's thread or the
            bus's gatekeeper died: no operator could command or stop the service any more, so it stops.
    """

    name = "control server"
    stop_budget_s = 1.0

    def __init__(
        self,
        config: CompanionConfig,
        *,
        config_path: Path | None,
        clock: Callable[[], float],
        supervisor: Supervisor,
        submit: Callable[[Any], asyncio.Future | None],
        status: Callable[[], dict[str, Any]],
        engaged: Callable[[], bool],
        pipeline: PipelinePart,
        capture: CapturePart,
        errors: LastError,
        on_applied: Callable[[], None],
        on_server_failed: Callable[[str], None],
    ) -> None:
        self.config = config
        self.config_version = 1
        self.config_path = config_path
        self._clock = clock
        self._supervisor = supervisor
        self._submit = submit
        self._status = status
        self._engaged = engaged
        self._pipeline = pipeline
        self._capture = capture
        self._errors = errors
        self._on_applied = on_applied
        self._on_server_failed = on_server_failed
        self._lock: asyncio.Lock | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._bus: Any = None
        self._reloads: set[asyncio.Task] = set()
        self.server: ControlServer | None = None

    # ------------------------------------------------------------------------------ the server part

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """The flight loop (before any request is carried out)."""
        self._loop = loop
        self._lock = asyncio.Lock()

    def start(self, bus: Any) -> None:
        """Serve ``bus.control`` in the control server's own thread: no client can stall the flight loop."""
        assert self._loop is not None
        self._bus = bus
        self.server = ControlServer(
            bus.control,
            self.config.bus,
            self._loop,
            self.handle_local,
            self.handle_request,
            on_internal_error=self._server_error,
            clock=self._clock,
        )
        self.server.start()
        gatekeeper = bus.gatekeeper
        gatekeeper.on_failure = self._gatekeeper_failed
        if gatekeeper.error is not None:  # it died before it had anyone to tell
            self._gatekeeper_failed(gatekeeper.error)

    async def stop(self, budget_s: float) -> bool:
        """Stop the server's thread (requests in progress get no reply) and any reload under way."""
        for task in list(self._reloads):
            task.cancel()
        if self._reloads:
            await asyncio.wait(list(self._reloads), timeout=budget_s / 2.0)
        self._reloads.clear()
        if self.server is None:
            return True
        return await stop_in_thread("the control server", self.server.stop, budget_s)

    def _server_error(self, message: str) -> None:
        """From the control server's thread: a request failed with a bug, or the thread itself died."""
        call_on_loop(self._loop, self._errors.record, message)
        if self.server is not None and self.server.error is not None:
            # Nobody could command or stop the service any more: stop cleanly (zero, Hold if ours).
            call_on_loop(self._loop, self._on_server_failed, "control server failed")

    def _gatekeeper_failed(self, err: BaseException) -> None:
        """From the gatekeeper's thread as it dies: no new connection is let in, so an operator
        without one open could no longer command or stop the service; it stops cleanly."""
        call_on_loop(self._loop, self._errors.record, f"the control socket's gatekeeper failed: {err!r}")
        call_on_loop(self._loop, self._on_server_failed, "control socket's gatekeeper failed")

    def counts(self) -> ControlCounts | None:
        """The control server's counts, or None before it started."""
        server = self.server
        if server is None:
            return None
        st = server.stats
        bus_stats = self._bus.stats()  # the bus is set before the server starts
        return ControlCounts(
            connections=bus_stats["connections"],
            received=st.received,
            rate_limited=st.rate_limited,
            busy=st.busy,
            bad=st.bad,
            replies_dropped=st.replies_dropped,
            refused_connections=bus_stats["refused_connections"],
        )

    # ------------------------------------------------------------------------------ requests

    def handle_local(self, request: Any) -> dict[str, Any] | None:
        """The answer to a request the control server's thread gives itself, from immutable snapshots
        (``ping``, ``get_config``); None for every other request (it goes to :meth:`handle_request`).

        Raises:
            ProtocolError: ``get_config`` of a section that does not exist.
        """
        cmd = request.cmd
        if cmd == "ping":
            return {"pong": True, "time_s": self._clock(), "state": self._supervisor.state.value}
        if cmd == "get_config":
            config, version = self.config, self.config_version  # one reference each: a consistent pair
            data = config.model_dump(mode="json")
            if request.section is None:
                return {"config": data, "config_version": version, "path": str(self.config_path or "")}
            if request.section not in data:
                raise ProtocolError(f"get_config: no section {request.section!r}; sections are {', '.join(data)}")
            return {"section": request.section, "config": data[request.section], "config_version": version}
        return None

    async def handle_request(self, request: Any) -> dict[str, Any]:
        """Carry out one validated request on the flight loop; returns the reply's result, raises CompanionError."""
        local = self.handle_local(request)
        if local is not None:
            return local
        cmd = request.cmd
        if cmd == "status":
            return self._status()
        if cmd == "set_config":
            new = apply_patch(self.config, request.patch)
            return await self.apply_config(new, "set_config")
        if cmd == "reload":
            return await self.reload()
        if cmd in ("engage", "goto") and request.goal is not None:
            try:
                spec = request.goal.spec()
            except ValueError as err:
                raise ProtocolError(f"{cmd}: goal: {err}") from None
            return await self._supervise(Engage(goal=spec) if cmd == "engage" else Goto(goal=spec))
        supervisor_request = {
            "engage": Engage,
            "disengage": Disengage,
            "pause": Pause,
            "resume": Resume,
        }.get(cmd)
        if supervisor_request is not None:
            return await self._supervise(supervisor_request())
        if cmd == "override":
            return await self._supervise(
                Override(yaw=request.yaw, pitch=request.pitch, speed_fraction=request.speed, duration_s=request.duration_s)
            )
        raise ProtocolError(f"unknown cmd {cmd!r}")

    async def _supervise(self, request: Any) -> dict[str, Any]:
        fut = self._submit(request)
        assert fut is not None
        try:
            reply: Reply = await asyncio.wait_for(fut, 2.0)
        except asyncio.TimeoutError:
            raise RequestRefused(f"{type(request).__name__.lower()}: the control loop did not answer within 2 s") from None
        if not reply.ok:
            raise RequestRefused(reply.message)
        return {"message": reply.message, "state": self._supervisor.state.value, "reason": self._supervisor.reason}

    async def reload(self) -> dict[str, Any]:
        """Re-read the config file and apply it (validated whole first). A rejection stays in health's
        ``last_error`` (the file on disk is wrong) until a reload or change is applied."""
        if self.config_path is None:
            raise ConfigError("reload: the service was started without --config; there is no file to read")
        try:
            new = load_config(self.config_path)
            new = resolve_config_paths(new, self.config_path.parent)
            return await self.apply_config(new, f"reload of {self.config_path}", from_file=True)
        except ConfigError as err:
            self._errors.record(f"reload rejected: {err}", kind="config")
            raise

    async def apply_config(self, new: CompanionConfig, source: str, from_file: bool = False) -> dict[str, Any]:
        """Swap in a validated config: check it, build it (in the pipeline thread), swap only on success.

        Refused, the old config staying in force, when it would change what may not change now
        (:func:`live_change_refusal`: the envelope, or non-tuning fields while engaged) or when its
        controller would not see a near obstacle as near (:func:`~companion.core.safety.near_blindness`).
        Fields that need a restart are reported in ``restart_required`` and not applied.
        ``from_file``: a reload of the config file (the only way the envelope changes).
        """
        assert self._lock is not None
        async with self._lock:
            current = self.config
            later = restart_required(current, new)
            applied = keep_restart_fields(current, new)
            refusal = live_change_refusal(current, applied, engaged=self._engaged(), from_file=from_file)
            if refusal is None:
                try:
                    check_rig_config(applied, source)
                except ConfigError as err:
                    refusal = str(err).removeprefix(f"{source}: ")
            if refusal is None:
                refusal = near_blindness(applied)
            if refusal is not None:
                raise ConfigError(f"{source}: rejected, the old config stays: {refusal}")
            changed = [name for name in type(applied).model_fields if getattr(applied, name) != getattr(current, name)]
            try:
                await self._pipeline.reconfigure(applied)
            except CompanionError as err:
                raise ConfigError(f"{source}: rejected, the old config stays: {err}") from None
            except Exception as err:
                log.exception("%s: building the new pipeline failed", source)
                raise ConfigError(
                    f"{source}: rejected, the old config stays: {type(err).__name__}: {err}"
                ) from None
            self._supervisor.reconfigure(SupervisorConfig.from_config(applied))
            self._capture.place(applied)
            self.config = applied
            if changed:
                self.config_version += 1
            if later:
                log.warning("%s: %s need a restart to take effect", source, ", ".join(later))
            log.info("%s applied (changed: %s)", source, ", ".join(changed) or "nothing")
            self._errors.clear("config")  # an earlier rejected change is no longer what is in force
            self._on_applied()
            return {"changed": changed, "restart_required": later, "config_version": self.config_version}

    def reload_in_background(self) -> None:
        """SIGHUP: reload the config file beside the loop; the outcome is logged (and kept in health)."""
        assert self._loop is not None
        task = self._loop.create_task(self._reload_logged(), name="reload")
        self._reloads.add(task)
        task.add_done_callback(self._reloads.discard)

    async def _reload_logged(self) -> None:
        try:
            result = await self.reload()
            log.info("reload applied: %s", result)
        except CompanionError as err:
            log.error("reload rejected, the old config stays: %s", err)  # reload() recorded it in health
        except Exception as err:  # a bug: the old config stays, and health says so
            log.exception("reload failed, the old config stays")
            self._errors.record(f"reload failed, the old config stays: {type(err).__name__}: {err}", kind="config")
