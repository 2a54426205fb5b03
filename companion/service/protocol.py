"""The control protocol: JSON requests and replies over the ZeroMQ ROUTER socket.

A request is one JSON object with a ``cmd`` (the discriminator) and that command's fields; an optional
``id`` (string or integer) is echoed in the reply. Unknown fields are errors. Replies::

    {"ok": true,  "cmd": "ping", "id": 7, "result": {...}}
    {"ok": false, "cmd": "override", "id": 7, "error": {"type": "ProtocolError", "message": "..."}}

Commands: ``ping``, ``status``, ``get_config`` (optional ``section``), ``set_config`` (``patch``: a
partial config), ``reload``, ``engage`` (optional ``goal``), ``goto`` (``goal``), ``disengage``,
``pause``, ``resume``, ``override`` (``yaw`` and ``pitch`` in [-1, 1], ``speed`` in [0, 1] as a share
of the cruise speed, ``duration_s`` > 0 and at most ``service.override_max_duration_s``).

A ``goal`` (:class:`Goal`) is one of ``{"kind": "course"}`` (the heading and line at engagement),
``{"kind": "point", "north_m": 12.0, "east_m": -3.0}`` (local NED frame) or
``{"kind": "bearing", "bearing_deg": 30.0, "distance_m": 10.0, "from_heading": true}``.
"""

from __future__ import annotations

import json
import math
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from companion.core.goal import GoalSpec
from companion.errors import ProtocolError

RequestId = Union[Annotated[str, Field(max_length=128)], Annotated[int, Field(ge=-(2**53), le=2**53)], None]


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)

    id: RequestId = Field(default=None, description="Echoed in the reply, to match replies to requests.")


class PingRequest(_Request):
    """Liveness check; replies with the service's clock and state."""

    cmd: Literal["ping"]


class StatusRequest(_Request):
    """The current health message."""

    cmd: Literal["status"]


class GetConfigRequest(_Request):
    """The configuration in force (the whole of it, or one section)."""

    cmd: Literal["get_config"]
    section: str | None = Field(default=None, max_length=64, description="A top-level section, e.g. 'controller'.")


class SetConfigRequest(_Request):
    """A partial configuration, deep-merged into the one in force, validated whole before it applies."""

    cmd: Literal["set_config"]
    patch: dict[str, Any] = Field(min_length=1, description="e.g. {'planner': {'cruise_speed_m_s': 1.5}}.")


class ReloadRequest(_Request):
    """Re-read the config file, validate it whole and apply it (as SIGHUP does)."""

    cmd: Literal["reload"]


class Goal(BaseModel):
    """Where to fly (:class:`~companion.core.goal.GoalSpec`; see the module doc)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)

    kind: Literal["course", "point", "bearing"] = Field(description="course, point or bearing.")
    north_m: float = Field(default=0.0, ge=-1e5, le=1e5, description="point: north, local NED metres.")
    east_m: float = Field(default=0.0, ge=-1e5, le=1e5, description="point: east, local NED metres.")
    bearing_deg: float = Field(default=0.0, ge=-360.0, le=360.0, description="bearing: degrees clockwise.")
    distance_m: float = Field(default=0.0, ge=0.0, le=1e5, description="bearing: how far, metres (> 0).")
    from_heading: bool = Field(default=False, description="bearing: from the vehicle's heading, not north.")

    def spec(self) -> Any:
        """The core's :class:`~companion.core.goal.GoalSpec` (raises ValueError for a bearing of 0 m)."""
        return GoalSpec(
            kind=self.kind,
            north_m=self.north_m,
            east_m=self.east_m,
            bearing_deg=self.bearing_deg,
            distance_m=self.distance_m,
            from_heading=self.from_heading,
        )


class EngageRequest(_Request):
    """Enter offboard and start avoiding, toward ``goal`` (default: the heading and line at engagement)."""

    cmd: Literal["engage"]
    goal: Goal | None = Field(default=None, description="Where to fly; none: the course at engagement.")


class GotoRequest(_Request):
    """While engaged: a new goal, from where the vehicle is now (ends a hold at a goal or a dead end)."""

    cmd: Literal["goto"]
    goal: Goal


class DisengageRequest(_Request):
    """Leave offboard to Hold (if we are in it) and stop commanding."""

    cmd: Literal["disengage"]


class PauseRequest(_Request):
    """Hover (zero velocity) in offboard until resume."""

    cmd: Literal["pause"]


class ResumeRequest(_Request):
    """Back to automatic (ends a pause or an override)."""

    cmd: Literal["resume"]


class OverrideRequest(_Request):
    """Fly manual values for a bounded time, then automatic again."""

    cmd: Literal["override"]
    yaw: float = Field(ge=-1.0, le=1.0, description="-1 hard left .. +1 hard right (times planner.max_yaw_rate_deg_s).")
    pitch: float = Field(ge=-1.0, le=1.0, description="-1 down .. +1 up (times planner.max_vertical_speed_m_s).")
    speed: float = Field(ge=0.0, le=1.0, description="Forward speed as a share of planner.cruise_speed_m_s.")
    duration_s: float = Field(gt=0.0, le=3600.0, description="How long, seconds (at most service.override_max_duration_s).")


Request = Annotated[
    Union[
        PingRequest,
        StatusRequest,
        GetConfigRequest,
        SetConfigRequest,
        ReloadRequest,
        EngageRequest,
        GotoRequest,
        DisengageRequest,
        PauseRequest,
        ResumeRequest,
        OverrideRequest,
    ],
    Field(discriminator="cmd"),
]

COMMANDS: tuple[str, ...] = (
    "ping",
    "status",
    "get_config",
    "set_config",
    "reload",
    "engage",
    "goto",
    "disengage",
    "pause",
    "resume",
    "override",
)


#: Objects and arrays nested deeper than this are refused: no request needs more than a few levels.
MAX_NESTING = 32


class _DuplicateKey(ValueError):
    """A JSON object names a key twice (JSON leaves the meaning open; a request must be unambiguous)."""


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not valid JSON")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def _nesting(value: Any, limit: int) -> int:
    """How deep objects and arrays nest in ``value`` (a scalar: 0), counted up to ``limit + 1``."""
    depth, level = 0, [(value, 1)]
    while level:
        item, d = level.pop()
        if isinstance(item, (dict, list)):
            depth = max(depth, d)
            if depth > limit:
                return depth
            level.extend((v, d + 1) for v in (item.values() if isinstance(item, dict) else item))
    return depth


def request_adapter() -> TypeAdapter:
    """The validator of :data:`Request` (build once and keep: it is not free)."""
    return TypeAdapter(Request)


def one_line(text: str, limit: int = 300) -> str:
    """``text`` with control characters escaped and cut to ``limit``: an error message stays one line."""
    out = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return out if len(out) <= limit else out[: limit - 3] + "..."


def _format_error(err: ValidationError) -> str:
    parts = []
    for e in err.errors(include_url=False):
        loc = [str(x) for x in e["loc"]]
        # The discriminated union puts the command's name first in the path: drop it.
        if loc and loc[0] in COMMANDS:
            loc = loc[1:]
        where = ".".join(repr(x) if not x.isidentifier() else x for x in loc) or "(message)"
        got = "" if e["type"] in ("missing", "extra_forbidden") else f" (got {repr(e.get('input'))[:60]})"
        parts.append(f"{where}: {e['msg']}{got}")
    return "; ".join(parts)


def parse_request(raw: bytes, adapter: TypeAdapter, max_bytes: int = 65536) -> Any:
    """Decode and validate one request.

    Raises:
        ProtocolError: one line saying what is wrong (size, encoding, JSON, missing or unknown cmd,
            the bad field and value). Its context carries ``cmd`` and ``id`` when they could be read.
    """
    if len(raw) > max_bytes:
        raise ProtocolError(f"request is {len(raw)} bytes, more than bus.max_request_bytes ({max_bytes})")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ProtocolError(f"request is not UTF-8 text: {err.reason} at byte {err.start}") from None
    too_deep = f"request is nested too deeply: objects and arrays at most {MAX_NESTING} levels deep"
    try:
        data = json.loads(text, parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
    except _DuplicateKey as err:
        raise ProtocolError(one_line(f"request names the key {str(err)[:40]!r} twice; each key once")) from None
    except RecursionError:
        raise ProtocolError(too_deep) from None
    except (json.JSONDecodeError, ValueError) as err:
        raise ProtocolError(one_line(f"request is not JSON: {err}", 160)) from None
    if _nesting(data, MAX_NESTING) > MAX_NESTING:
        raise ProtocolError(too_deep)
    if not isinstance(data, dict):
        raise ProtocolError(f"request must be a JSON object with a 'cmd', got {type(data).__name__}")
    rid = data.get("id")
    cmd = data.get("cmd")
    if not (rid is None or isinstance(rid, (str, int)) and not isinstance(rid, bool)):
        rid = None
    ctx = {"cmd": cmd if isinstance(cmd, str) and cmd in COMMANDS else None, "id": rid}
    if "cmd" not in data:
        raise ProtocolError(f"request has no 'cmd'; commands are: {', '.join(COMMANDS)}", **ctx)
    if not isinstance(cmd, str) or cmd not in COMMANDS:
        raise ProtocolError(one_line(f"unknown cmd {str(cmd)[:40]!r}; commands are: {', '.join(COMMANDS)}"), **ctx)
    try:
        return adapter.validate_python(data)
    except ValidationError as err:
        raise ProtocolError(one_line(f"{cmd}: {_format_error(err)}"), **ctx) from None
    except RecursionError:
        raise ProtocolError(f"{cmd}: request is nested too deeply", **ctx) from None


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats replaced by None (JSON has no NaN/inf), recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def encode(message: dict[str, Any]) -> bytes:
    """A reply or health message as compact UTF-8 JSON (strict: no NaN)."""
    return json.dumps(json_safe(message), separators=(",", ":"), allow_nan=False, default=str).encode("utf-8")


def ok_reply(cmd: str | None, rid: Any, result: dict[str, Any]) -> dict[str, Any]:
    return {"ok": True, "cmd": cmd, "id": rid, "result": result}


def error_reply(cmd: str | None, rid: Any, kind: str, message: str) -> dict[str, Any]:
    return {"ok": False, "cmd": cmd, "id": rid, "error": {"type": kind, "message": one_line(message, 1000)}}
