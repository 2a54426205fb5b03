"""The service's control plane: the control server's thread, request dispatch and live config changes.

Two parts:

* :class:`ControlServer` owns the ZeroMQ ROUTER socket in a thread of its own, so that no client,
  however many messages it sends or however slowly it reads, can stall the flight loop (setpoints,
  the watchdog, signals). It enforces the budgets (per connection and in total, requests per second),
  bounds the requests in progress, parses and validates each request, answers ``ping`` and
  ``get_config`` itself from immutable snapshots, and hands everything else to the flight loop one
  request per task, bounded.
* :class:`ControlPlane`, a part of :class:`~companion.service.daemon.Service` (a mixin), carries a
  request out on the flight loop: supervisor requests (engage, disengage, pause, resume, override) go
  to the control loop; a config change or reload is validated whole, checked against the safety
  envelope (:mod:`companion.config.envelope`) and against what may change while engaged
  (:func:`live_change_refusal`), and the controller must still see a near obstacle as near
  (:func:`~companion.core.safety.near_blindness`); only then is it built (in the pipeline thread) and
  swapped in. A rejected one leaves the old in force.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zmq
from zmq.utils.monitor import recv_monitor_message

from companion.config import BusConfig, CompanionConfig, apply_patch, load_config
from companion.config.service import LIVE_CAMERA_FIELDS, RESTART_FIELDS
from companion.config.view import VIEW_RESTART_FIELDS
from companion.core.safety import near_blindness
from companion.core.supervisor import Disengage, Engage, Goto, Override, Pause, Reply, Resume, SupervisorConfig
from companion.errors import CompanionError, ConfigError, ProtocolError
from companion.service import protocol

log = logging.getLogger(__name__)

#: Requests carried out on the flight loop at once; a further one gets a "Busy" reply at once.
MAX_IN_FLIGHT = 8
#: Messages read from the socket per turn of the server's loop (then replies are sent, events read).
_RECV_BATCH = 64
#: After a full batch (more messages are waiting: a flood), the thread sleeps this long, seconds. It
#: bounds the share of the CPU and of the interpreter lock that clients can take from the flight loop
#: (at most ~13 000 messages a second); what waits meanwhile stays in ZeroMQ's small per-connection
#: queues, and a client that keeps flooding loses its surplus there.
_FLOOD_PAUSE_S = 0.005
#: The control thread's niceness above the process's (Linux): under load the flight loop's threads
#: come first.
_NICENESS = 5
#: Connections whose budgets are remembered; beyond this the idle ones are forgotten.
_MAX_TRACKED_PEERS = 1024
#: Requests that stop the vehicle: never refused by a request budget (one client's flood must not keep
#: another from stopping it), and they have places in progress of their own beyond :data:`MAX_IN_FLIGHT`.
STOP_COMMANDS = frozenset({"disengage", "pause"})
#: A stop request is at most this long (a longer message is not looked at before the budgets).
_MAX_STOP_BYTES = 256
#: What a live change may touch while engaged under ``envelope.live_changes_while_engaged = "tuning"``:
#: these sections, except the command fields below (timeouts, the brake hold, the progress watchdog).
_TUNING_SECTIONS = ("controller", "lut", "command", "sim")
_SAFETY_COMMAND_FIELDS = (
    "stale_frame_timeout_s",
    "failsafe_timeout_s",
    "brake_hold_gain_per_s",
    "no_progress_timeout_s",
    "progress_step_m",
)


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
      tuning (controller, lut, command except its timeouts, brake hold and watchdog), or any.
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
    safety = {f"command.{f}" for f in _SAFETY_COMMAND_FIELDS}
    refused = [
        f for f in changed if f not in live_camera and (f.split(".")[0] not in _TUNING_SECTIONS or f in safety)
    ]
    if refused:
        return (
            "while engaged only tuning may change (envelope.live_changes_while_engaged = tuning): "
            f"disengage first to change {', '.join(refused)}"
        )
    return None


class ControlPlane:
    """The control-plane part of the service that runs on the flight loop (mixed into
    :class:`~companion.service.daemon.Service`)."""

    def handle_local(self, request: Any) -> dict[str, Any] | None:
        """The answer to a request the control server's thread gives itself, from immutable snapshots
        (``ping``, ``get_config``); None for every other request (it goes to :meth:`handle_request`).

        Raises:
            ProtocolError: ``get_config`` of a section that does not exist.
        """
        cmd = request.cmd
        if cmd == "ping":
            return {"pong": True, "time_s": self._clock(), "state": self.supervisor.state.value}
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
            return self.health_message()
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
        return {"message": reply.message, "state": self.supervisor.state.value, "reason": self.supervisor.reason}

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
            self._error(f"reload rejected: {err}", kind="config")
            raise

    async def apply_config(self, new: CompanionConfig, source: str, from_file: bool = False) -> dict[str, Any]:
        """Swap in a validated config: check it, build it (in the pipeline thread), swap only on success.

        Refused, the old config staying in force, when it would change what may not change now
        (:func:`live_change_refusal`: the envelope, or non-tuning fields while engaged) or when its
        controller would not see a near obstacle as near (:func:`~companion.core.safety.near_blindness`).
        Fields that need a restart are reported in ``restart_required`` and not applied.
        ``from_file``: a reload of the config file (the only way the envelope changes).
        """
        assert self._config_lock is not None
        async with self._config_lock:
            current = self.config
            later = restart_required(current, new)
            applied = keep_restart_fields(current, new)
            refusal = live_change_refusal(current, applied, engaged=self.engaged_or_engaging, from_file=from_file)
            if refusal is None:
                refusal = near_blindness(applied)
            if refusal is not None:
                raise ConfigError(f"{source}: rejected, the old config stays: {refusal}")
            changed = [name for name in type(applied).model_fields if getattr(applied, name) != getattr(current, name)]
            if self._pipeline is not None and self._processor is not None:
                try:
                    # In the pipeline thread, between two frames: never racing one.
                    await asyncio.wrap_future(self._processor.submit(self._reconfigure_pipeline, applied))
                except CompanionError as err:
                    raise ConfigError(f"{source}: rejected, the old config stays: {err}") from None
                except Exception as err:
                    log.exception("%s: building the new pipeline failed", source)
                    raise ConfigError(
                        f"{source}: rejected, the old config stays: {type(err).__name__}: {err}"
                    ) from None
            self.supervisor.reconfigure(SupervisorConfig.from_config(applied))
            if self._telemetry_pose is not None:
                from companion.service.camera import placement_from_config

                self._telemetry_pose.placement = placement_from_config(applied)  # one reference swap
            if self._processor is not None:
                self._processor.skip_late_frames = applied.service.skip_late_frames
            self.config = applied
            if changed:
                self.config_version += 1
            if later:
                log.warning("%s: %s need a restart to take effect", source, ", ".join(later))
            log.info("%s applied (changed: %s)", source, ", ".join(changed) or "nothing")
            self._clear_error("config")  # an earlier rejected change is no longer what is in force
            self._kick_health()
            return {"changed": changed, "restart_required": later, "config_version": self.config_version}


# ---------------------------------------------------------------------------------------------- the server


@dataclass
class _Bucket:
    """A token bucket: ``tokens`` (requests) at ``t_s``, refilled at ``rate`` per second up to ``rate``."""

    tokens: float
    t_s: float

    def take(self, now_s: float, rate: float) -> bool:
        self.tokens = min(rate, self.tokens + (now_s - self.t_s) * rate)
        self.t_s = now_s
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


@dataclass
class ControlStats:
    """What the control server has seen (health's ``control``)."""

    received: int = 0
    rate_limited: int = 0
    busy: int = 0
    bad: int = 0
    replies_dropped: int = 0


def _envelope(frames: list[bytes]) -> tuple[list[bytes], list[bytes]] | None:
    """(the reply envelope, the payload frames) of one ROUTER message; None when it has no payload."""
    if len(frames) < 2:
        return None  # no identity and payload: nothing we could reply to
    identity, rest = frames[0], frames[1:]
    if len(rest) >= 2 and rest[0] == b"":
        return [identity, b""], rest[1:]  # REQ client
    return [identity], rest  # DEALER client


class ControlServer:
    """The control socket's own thread (see the module doc). Start with :meth:`start`, end with :meth:`stop`.

    Args:
        sock: the bound ROUTER socket; from :meth:`start` on only this thread uses it.
        cfg: the ``[bus]`` config (the budgets; a restart changes them).
        loop: the flight loop, where :meth:`ControlPlane.handle_request` runs.
        handle_local: answers the requests the thread gives itself, or returns None
            (:meth:`ControlPlane.handle_local`).
        handle: a request's coroutine on the flight loop (:meth:`ControlPlane.handle_request`).
        on_internal_error: called (from this thread) with a one-line message when a request failed
            with a bug.
        gatekeeper: told the live connection count (:class:`~companion.service.bus.Gatekeeper`), or None.
        clock: monotonic seconds, for the budgets.
    """

    def __init__(
        self,
        sock: zmq.Socket,
        cfg: BusConfig,
        loop: asyncio.AbstractEventLoop,
        handle_local: Callable[[Any], dict[str, Any] | None],
        handle: Callable[[Any], Coroutine[Any, Any, dict[str, Any]]],
        on_internal_error: Callable[[str], None],
        gatekeeper: Any = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._sock = sock
        self._cfg = cfg
        self._loop = loop
        self._handle_local = handle_local
        self._handle = handle
        self._on_internal_error = on_internal_error
        self._gatekeeper = gatekeeper
        self._clock = clock
        self._adapter = protocol.request_adapter()
        self._refusals = {
            "client": protocol.encode(
                protocol.error_reply(
                    None,
                    None,
                    "RateLimited",
                    f"more than bus.requests_per_s_per_client = {cfg.requests_per_s_per_client:g} requests "
                    "per second from this connection; not carried out",
                )
            ),
            "all": protocol.encode(
                protocol.error_reply(
                    None,
                    None,
                    "RateLimited",
                    f"more than bus.max_requests_per_s = {cfg.max_requests_per_s:g} requests per second "
                    "from all clients; not carried out",
                )
            ),
            "busy": protocol.encode(
                protocol.error_reply(
                    None, None, "Busy", f"{MAX_IN_FLIGHT} requests are in progress already; try again"
                )
            ),
        }
        self._done: queue.SimpleQueue[tuple[list[bytes], str, Any, concurrent.futures.Future]] = queue.SimpleQueue()
        self._pending: set[concurrent.futures.Future] = set()
        self._peers: dict[bytes, _Bucket] = {}
        self._all = _Bucket(cfg.max_requests_per_s, clock())
        self._reserve = _Bucket(cfg.max_requests_per_s, clock())  # the light users' share (_admit)
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="control server", daemon=True)
        self.stats = ControlStats()
        self.connections = 0
        self.error: BaseException | None = None  # what ended the thread, if it died

    # ------------------------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """End the thread: requests in progress are cancelled (their clients get no reply)."""
        self._stop.set()
        self._wake()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.error("the control server's thread did not stop within %.1f s", timeout_s)
        for fut in list(self._pending):
            fut.cancel()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass  # closed already

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except (BlockingIOError, OSError):
            pass  # the pipe is full (the thread wakes anyway) or closed (it has stopped)

    # ------------------------------------------------------------------------------------ the thread

    def _run(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + _NICENESS)
        except (AttributeError, OSError) as err:  # not Linux, or not allowed: the budgets still bound it
            log.debug("control thread niceness unchanged: %s", err)
        monitor = self._sock.get_monitor_socket(zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED)
        poller = zmq.Poller()
        poller.register(self._sock, zmq.POLLIN)
        poller.register(monitor, zmq.POLLIN)
        poller.register(self._wake_r, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                ready = dict(poller.poll(200))
                if monitor in ready:
                    self._read_monitor(monitor)
                if self._wake_r in ready:
                    try:
                        os.read(self._wake_r, 4096)
                    except BlockingIOError:
                        pass
                self._send_done()
                if self._sock in ready and self._receive() == _RECV_BATCH:
                    time.sleep(_FLOOD_PAUSE_S)
        except Exception as err:  # a bug: the service notices (health) and stops cleanly
            self.error = err
            log.exception("the control server's thread failed")
            self._on_internal_error(f"control server: {type(err).__name__}: {err}")
        finally:
            try:
                self._sock.disable_monitor()
            except zmq.ZMQError:
                pass  # the socket is already closed
            monitor.close(0)

    def _read_monitor(self, monitor: zmq.Socket) -> None:
        while True:
            try:
                event = recv_monitor_message(monitor, zmq.NOBLOCK)
            except zmq.Again:
                break
            if event["event"] == zmq.EVENT_ACCEPTED:
                self.connections += 1
            elif event["event"] == zmq.EVENT_DISCONNECTED:
                self.connections = max(0, self.connections - 1)
        if self._gatekeeper is not None:
            self._gatekeeper.live_connections = self.connections

    def _receive(self) -> int:
        """Read and handle up to :data:`_RECV_BATCH` messages; returns how many."""
        for n in range(_RECV_BATCH):
            try:
                frames = self._sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return n
            self.stats.received += 1
            split = _envelope(frames)
            if split is None:
                continue
            envelope, parts = split
            stop = len(parts) == 1 and self._is_stop(parts[0])
            refusal = self._admit(envelope[0], stop=stop)
            if refusal is not None:
                self._send(envelope, refusal)
                continue
            if len(parts) != 1:
                self.stats.bad += 1
                message = f"expected one JSON frame after the envelope, got {len(parts)} frames"
                self._reply(envelope, protocol.error_reply(None, None, "ProtocolError", message))
                continue
            self._dispatch(envelope, parts[0])
        return _RECV_BATCH

    def _admit(self, identity: bytes, now_s: float | None = None, stop: bool = False) -> bytes | None:
        """None when this connection, and all together, are within their request budgets; else the
        error reply, encoded (the same bytes for every refusal of a kind: a flood costs no JSON).

        Fair shares: when the budget of all connections is spent, a connection that has used less than
        half its own budget in the last second still gets in, from a reserve as large as that budget
        (the connections that spent it are refused; the total stays bounded at twice it). A ``stop``
        request (:data:`STOP_COMMANDS`) is never refused by a budget, only when even its own places in
        progress are taken.
        """
        now_s = self._clock() if now_s is None else now_s
        per = self._cfg.requests_per_s_per_client
        total = self._cfg.max_requests_per_s
        bucket = self._peers.get(identity)
        if bucket is None:
            if len(self._peers) >= _MAX_TRACKED_PEERS:
                self._forget_idle(now_s)
            bucket = self._peers[identity] = _Bucket(per, now_s)
        if stop:
            bucket.take(now_s, per)  # counted, never refused
            if len(self._pending) >= MAX_IN_FLIGHT + len(STOP_COMMANDS) * 2:
                self.stats.busy += 1
                return self._refusals["busy"]
            return None
        if not bucket.take(now_s, per):
            self.stats.rate_limited += 1
            return self._refusals["client"]
        if not self._all.take(now_s, total) and (bucket.tokens < per / 2.0 or not self._reserve.take(now_s, total)):
            self.stats.rate_limited += 1
            return self._refusals["all"]
        if len(self._pending) >= MAX_IN_FLIGHT:
            self.stats.busy += 1
            return self._refusals["busy"]
        return None

    def _is_stop(self, raw: bytes) -> bool:
        """Whether ``raw`` is a valid stop request (:data:`STOP_COMMANDS`); only a short message that
        names one is parsed here, so a flood of anything else costs no JSON."""
        if len(raw) > _MAX_STOP_BYTES or not any(cmd.encode() in raw for cmd in STOP_COMMANDS):
            return False
        try:
            return protocol.parse_request(raw, self._adapter, self._cfg.max_request_bytes).cmd in STOP_COMMANDS
        except ProtocolError:
            return False

    def _forget_idle(self, now_s: float) -> None:
        per = self._cfg.requests_per_s_per_client
        idle = [k for k, b in self._peers.items() if b.tokens + (now_s - b.t_s) * per >= per]
        for k in idle or list(self._peers)[: len(self._peers) // 2]:
            del self._peers[k]

    def _dispatch(self, envelope: list[bytes], raw: bytes) -> None:
        cmd = rid = None
        try:
            request = protocol.parse_request(raw, self._adapter, self._cfg.max_request_bytes)
            cmd, rid = request.cmd, request.id
            local = self._handle_local(request)
        except ProtocolError as err:
            self.stats.bad += 1
            cmd = cmd or err.context.get("cmd")
            rid = rid if rid is not None else err.context.get("id")
            log.info("bad request: %s", err)
            self._reply(envelope, protocol.error_reply(cmd, rid, "ProtocolError", str(err)))
            return
        except Exception as err:
            self._reply(envelope, self._internal_error(cmd, rid, err))
            return
        if local is not None:
            self._reply(envelope, protocol.ok_reply(cmd, rid, local))
            return
        fut = asyncio.run_coroutine_threadsafe(self._handle(request), self._loop)
        self._pending.add(fut)
        fut.add_done_callback(lambda f: (self._done.put((envelope, cmd, rid, f)), self._wake()))

    def _send_done(self) -> None:
        while True:
            try:
                envelope, cmd, rid, fut = self._done.get_nowait()
            except queue.Empty:
                return
            self._pending.discard(fut)
            if fut.cancelled():
                continue
            err = fut.exception()
            if err is None:
                message = protocol.ok_reply(cmd, rid, fut.result())
            elif isinstance(err, ProtocolError):
                log.info("bad request: %s", err)
                message = protocol.error_reply(cmd, rid, "ProtocolError", str(err))
            elif isinstance(err, CompanionError):
                log.info("%s request failed: %s", cmd, err)
                message = protocol.error_reply(cmd, rid, type(err).__name__, str(err))
            else:
                message = self._internal_error(cmd, rid, err)
            self._reply(envelope, message)

    def _internal_error(self, cmd: Any, rid: Any, err: BaseException) -> dict[str, Any]:
        log.error("request %s failed", cmd, exc_info=err)
        self._on_internal_error(f"internal error handling {cmd}: {type(err).__name__}: {err}")
        return protocol.error_reply(cmd, rid, "InternalError", f"{type(err).__name__}: {err}")

    def _reply(self, envelope: list[bytes], message: dict[str, Any]) -> None:
        self._send(envelope, protocol.encode(message))

    def _send(self, envelope: list[bytes], payload: bytes) -> None:
        try:
            self._sock.send_multipart(envelope + [payload], zmq.NOBLOCK)
        except zmq.ZMQError as err:  # the client went away, or does not read its replies: drop it
            self.stats.replies_dropped += 1
            log.debug("control reply not delivered: %s", err)
