"""The control-plane client behind ``companion ctl`` and ``companion watch`` (synchronous pyzmq).

Usable from Python too::

    from companion.service.client import ControlClient
    with ControlClient("tcp://127.0.0.1:5561") as c:
        print(c.call({"cmd": "status"}))
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import zmq

from companion.errors import CompanionError, ConfigError, InputError
from companion.service.runtime import check_listening, permission_denied, validate_endpoint, validate_timeout


class ClientError(CompanionError):
    """The service did not answer (not running, wrong endpoint, CURVE keys refused)."""


def curve_client_options(server_key: Path | None, client_key: Path | None) -> dict[str, bytes] | None:
    """Socket options for a CURVE client, from the server's public certificate and the client's
    secret certificate (zmq.auth files); None when neither is given.

    Raises:
        InputError: only one of the two given, or a file that is not a certificate.
    """
    if server_key is None and client_key is None:
        return None
    if server_key is None or client_key is None:
        raise InputError("CURVE needs both --server-key (the server's .key) and --client-key (your .key_secret)")
    import zmq.auth

    try:
        server_public, _ = zmq.auth.load_certificate(str(server_key))
        client_public, client_secret = zmq.auth.load_certificate(str(client_key))
    except (OSError, ValueError) as err:
        raise InputError(f"cannot read a CURVE certificate: {err}") from None
    if not client_secret:
        raise InputError(f"{client_key}: has no secret key (use the .key_secret file)")
    return {"curve_serverkey": server_public, "curve_publickey": client_public, "curve_secretkey": client_secret}


def check_ipc_access(endpoint: str) -> None:
    """For an ``ipc://`` endpoint whose socket file exists: raise ClientError when this user may not
    open it, or when no service listens on it (ZeroMQ would only retry in silence).

    Raises:
        ClientError: permission denied or no running service, naming the file and what to do.
    """
    if not endpoint.startswith("ipc://") or endpoint.startswith("ipc://@"):
        return
    path = Path(endpoint.removeprefix("ipc://"))
    try:
        exists = path.exists()
    except PermissionError:
        exists = True  # the folder itself is closed to us
    if exists and not os.access(path, os.R_OK | os.W_OK):
        raise ClientError(permission_denied(path))
    try:
        check_listening(endpoint)
    except ConfigError as err:
        raise ClientError(str(err)) from None


class ControlClient:
    """One DEALER connection to the control socket; ``call`` sends a request and waits for its reply."""

    def __init__(self, endpoint: str, timeout_s: float = 3.0, curve: dict[str, bytes] | None = None) -> None:
        validate_endpoint(endpoint, "endpoint")
        validate_timeout(timeout_s)
        check_ipc_access(endpoint)
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.DEALER)
        self._sock.setsockopt(zmq.LINGER, 0)
        # A connection the service refused (bus.max_connections, CURVE) can leave the socket with no
        # pipe, where a blocking send would wait forever: bound it by the same timeout.
        self._sock.setsockopt(zmq.SNDTIMEO, max(1, int(timeout_s * 1000)))
        for name, value in (curve or {}).items():
            setattr(self._sock, name, value)
        try:
            self._sock.connect(endpoint)
        except zmq.ZMQError as err:
            self.close()
            raise ClientError(f"cannot connect to {endpoint}: {err}") from None
        self._next_id = 1

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def call(self, request: dict[str, Any]) -> dict[str, Any]:
        """Send ``request`` (an ``id`` is added if missing) and return the reply object.

        Raises:
            ClientError: the request could not be sent, or no reply came, within the timeout.
        """
        request = dict(request)
        if request.get("id") is None:
            request["id"] = self._next_id
            self._next_id += 1
        try:
            self._sock.send(json.dumps(request).encode("utf-8"))
        except zmq.Again:
            raise ClientError(
                f"could not send to {self.endpoint} within {self.timeout_s:g} s: no running service there, "
                "or it refused the connection (bus.max_connections, CURVE keys)"
            ) from None
        deadline_ms = int(self.timeout_s * 1000)
        while self._sock.poll(deadline_ms):
            reply = json.loads(self._sock.recv())
            if reply.get("id") == request["id"]:
                return reply
        raise ClientError(
            f"no reply from {self.endpoint} within {self.timeout_s:g} s: no running service there, "
            "or it refused the connection (CURVE keys)"
        )

    def close(self) -> None:
        self._ctx.destroy(linger=0)


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """``["planner.cruise_speed_m_s=1.5", "controller.preferred_yaw_side=left"]`` -> a nested patch.

    A value is read as JSON when it parses (numbers, true/false, lists, objects), else as a string.

    Raises:
        InputError: an item without '=' or with an empty key part.
    """
    patch: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        parts = key.strip().split(".")
        if not sep or not all(parts):
            raise InputError(f"expected KEY=VALUE with a dotted key (e.g. planner.cruise_speed_m_s=1.5), got {item!r}")
        try:
            value: Any = json.loads(text)
        except json.JSONDecodeError:
            value = text
        node = patch
        for p in parts[:-1]:
            child = node.setdefault(p, {})
            if not isinstance(child, dict):
                raise InputError(f"{key}: {p} is set to a value and used as a table")
            node = child
        node[parts[-1]] = value
    return patch


def _fmt(value: Any, unit: str = "", digits: int = 2) -> str:
    if value is None:
        return "--"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "--"
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def _words(h: dict[str, Any], dec: dict[str, Any]) -> str:
    """The decision in a pilot's words: the service's own, else made from the message."""
    if dec.get("words"):
        return str(dec["words"])
    if not dec:
        return "no decision yet"
    from companion.core.words import decision_words

    return decision_words(dec.get("kind"), h.get("yaw") or 0.0, h.get("pitch") or 0.0, h.get("regions_m"),
                          dec.get("speed_fraction"))


def render_health(h: dict[str, Any], verbose: bool = False) -> str:
    """A health message as a small terminal screen (``verbose``: with the controller's reason)."""
    r = h.get("regions_m") or {}
    filtered = h.get("regions_filtered") or {}
    # "~": the value came out of the release filter: a blend, no frame's measurement.
    cell = lambda name: f"{('~' if filtered.get(name) else '') + _fmt(r.get(name), ' m'):>9}"  # noqa: E731
    lat = h.get("frame_to_setpoint_ms") or {}
    sp = h.get("setpoint") or {}
    cam = h.get("camera") or {}
    veh = h.get("vehicle") or {}
    dec = h.get("decision") or {}
    stages = h.get("stages_ms") or {}
    lines = [
        f"state {h.get('state')}  engaged={h.get('engaged')}  ({h.get('reason')})",
        f"fps {_fmt(h.get('fps'), '', 1)}  frame age {_fmt(h.get('frame_age_ms'), ' ms', 0)}  "
        f"frame->setpoint last {_fmt(lat.get('last'), ' ms', 1)} median {_fmt(lat.get('median'), ' ms', 1)} "
        f"p99 {_fmt(lat.get('p99'), ' ms', 1)}",
        "stages " + "  ".join(f"{k.removesuffix('_ms')} {v:.1f}" for k, v in stages.items()),
        "regions (m):  -- unknown, ~ filtered (the release filter's, not measured)",
        f"  {cell('up_left')} {cell('up')} {cell('up_right')}",
        f"  {cell('left')} {cell('center')} {cell('right')}",
        f"  {cell('down_left')} {cell('down')} {cell('down_right')}",
        f"decision {dec.get('kind', '--')}: {_words(h, dec)}  yaw {_fmt(h.get('yaw'))}  pitch {_fmt(h.get('pitch'))}"
        + (f"  [{dec.get('reason', '')}]" if verbose else ""),
        f"setpoint fwd {_fmt(sp.get('forward_m_s'), ' m/s')}  down {_fmt(sp.get('down_m_s'), ' m/s')}  "
        f"yaw rate {_fmt(sp.get('yaw_rate_deg_s'), ' deg/s', 1)}",
        f"camera {cam.get('source')} {cam.get('status')} {_fmt(cam.get('fps'), ' fps', 1)}  "
        f"dropped {h.get('dropped_frames')}  reconnects {cam.get('reconnects')}"
        + (f"  skew {_fmt((cam.get('skew_ms') or {}).get('median'), ' ms', 1)} median, "
           f"{_fmt((cam.get('skew_ms') or {}).get('max'), ' ms', 1)} max" if cam.get("skew_ms") else ""),
        f"vehicle {veh.get('link')}  mode {veh.get('flight_mode')}  armed {veh.get('armed')}",
    ]
    goal = h.get("goal") or {}
    if goal:
        plan = h.get("planner") or {}
        lines.append(
            f"goal {goal.get('description')}  distance {_fmt(goal.get('distance_m'), ' m', 1)}  "
            f"bearing {_fmt(goal.get('bearing_deg'), ' deg', 0)}  planner {plan.get('mode')} ({plan.get('reason')})"
        )
    if h.get("override"):
        o = h["override"]
        lines.append(f"override yaw {o['yaw']:.2f} pitch {o['pitch']:.2f} speed {o['speed_fraction']:.2f} "
                     f"({o['remaining_s']:.1f} s left)")
    if h.get("last_error"):
        lines.append(f"last error: {h['last_error']}")
    return "\n".join(lines)
