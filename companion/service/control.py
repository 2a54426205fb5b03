"""The service's control plane: the ZeroMQ request server, request dispatch and live config changes.

:class:`ControlPlane` is a part of :class:`~companion.service.daemon.Service` (a mixin): it answers the
control protocol (``companion/service/protocol.py``; docs/service.md), hands supervisor requests
(engage, disengage, pause, resume, override) to the control loop, and applies a config change or reload
as a whole new validated model, built before it is swapped in (a rejected one leaves the old in force).
The functions here say which fields a live change may apply and resolve a config file's relative paths.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig, apply_patch, load_config
from companion.config.service import LIVE_CAMERA_FIELDS, RESTART_FIELDS
from companion.config.view import VIEW_RESTART_FIELDS
from companion.core.supervisor import Disengage, Engage, Override, Pause, Reply, Resume, SupervisorConfig
from companion.errors import CompanionError, ConfigError, ProtocolError
from companion.service import protocol

log = logging.getLogger(__name__)


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
    vehicle = new.vehicle.model_copy(update={"connection": current.vehicle.connection})
    camera = current.camera.model_copy(update={f: getattr(new.camera, f) for f in LIVE_CAMERA_FIELDS})
    view = new.view.model_copy(update={f: getattr(current.view, f) for f in VIEW_RESTART_FIELDS})
    return new.model_copy(update={"camera": camera, "bus": current.bus, "vehicle": vehicle, "view": view})


class ControlPlane:
    """The control-plane part of the service (mixed into :class:`~companion.service.daemon.Service`)."""

    async def _control_server(self) -> None:
        import zmq

        assert self.bus is not None and self.bus.control is not None
        sock = self.bus.control
        while True:
            frames = await sock.recv_multipart()
            reply = await self.handle_frames(frames)
            if reply is None:
                continue
            try:
                await sock.send_multipart(reply)
            except zmq.ZMQError as err:  # the client went away before its reply: nothing to do
                log.debug("control reply not delivered: %s", err)

    async def handle_frames(self, frames: list[bytes]) -> list[bytes] | None:
        """One ROUTER message in, one reply out (the envelope mirrored). Never raises."""
        if len(frames) < 2:
            return None  # no identity and payload: nothing we could reply to
        identity, rest = frames[0], frames[1:]
        if len(rest) >= 2 and rest[0] == b"":
            envelope, parts = [identity, b""], rest[1:]  # REQ client
        else:
            envelope, parts = [identity], rest  # DEALER client
        if len(parts) != 1:
            message = protocol.error_reply(
                None, None, "ProtocolError", f"expected one JSON frame after the envelope, got {len(parts)} frames"
            )
        else:
            message = await self.handle_raw(parts[0])
        return envelope + [protocol.encode(message)]

    async def handle_raw(self, raw: bytes) -> dict[str, Any]:
        """One request's bytes -> the reply object. Never raises (errors become error replies)."""
        cmd = rid = None
        try:
            request = protocol.parse_request(raw, self._request_adapter(), self.config.bus.max_request_bytes)
            cmd, rid = request.cmd, request.id
            result = await self.handle_request(request)
            return protocol.ok_reply(cmd, rid, result)
        except ProtocolError as err:
            cmd = cmd or err.context.get("cmd")
            rid = rid if rid is not None else err.context.get("id")
            log.info("bad request: %s", err)
            return protocol.error_reply(cmd, rid, "ProtocolError", str(err))
        except CompanionError as err:
            log.info("%s request failed: %s", cmd, err)
            return protocol.error_reply(cmd, rid, type(err).__name__, str(err))
        except asyncio.CancelledError:
            raise
        except Exception as err:
            log.exception("request %s failed", cmd)
            self._error(f"internal error handling {cmd}: {type(err).__name__}: {err}")
            return protocol.error_reply(cmd, rid, "InternalError", f"{type(err).__name__}: {err}")

    def _request_adapter(self) -> Any:
        adapter = getattr(self, "_adapter", None)
        if adapter is None:
            adapter = self._adapter = protocol.request_adapter()
        return adapter

    async def handle_request(self, request: Any) -> dict[str, Any]:
        """Carry out one validated request; returns the reply's result, raises CompanionError."""
        cmd = request.cmd
        if cmd == "ping":
            return {"pong": True, "time_s": self._clock(), "state": self.supervisor.state.value}
        if cmd == "status":
            return self.health_message()
        if cmd == "get_config":
            data = self.config.model_dump(mode="json")
            if request.section is None:
                return {"config": data, "config_version": self.config_version, "path": str(self.config_path or "")}
            if request.section not in data:
                raise ProtocolError(
                    f"get_config: no section {request.section!r}; sections are {', '.join(data)}"
                )
            return {"section": request.section, "config": data[request.section], "config_version": self.config_version}
        if cmd == "set_config":
            new = apply_patch(self.config, request.patch)
            return await self.apply_config(new, "set_config")
        if cmd == "reload":
            return await self.reload()
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
        """Re-read the config file and apply it (validated whole first)."""
        if self.config_path is None:
            raise ConfigError("reload: the service was started without --config; there is no file to read")
        new = load_config(self.config_path)
        new = resolve_config_paths(new, self.config_path.parent)
        return await self.apply_config(new, f"reload of {self.config_path}")

    async def apply_config(self, new: CompanionConfig, source: str) -> dict[str, Any]:
        """Swap in a validated config: build first (in the pipeline thread), swap only on success.

        Fields that need a restart are reported in ``restart_required`` and not applied.
        """
        assert self._config_lock is not None
        async with self._config_lock:
            current = self.config
            later = restart_required(current, new)
            applied = keep_restart_fields(current, new)
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
            self._kick_health()
            return {"changed": changed, "restart_required": later, "config_version": self.config_version}
