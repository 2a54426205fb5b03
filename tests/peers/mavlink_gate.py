"""A TCP relay between the service and an autopilot's MAVLink port that sees (and can drop) what passes.

ArduPilot SITL has no shell to stop one stream on one link (the PX4 tests use ``mavlink stream -r 0``),
so the ArduPilot SITL tests put this gate on the service's link: dropping LOCAL_POSITION_NED towards
the service stops its telemetry-rendered camera as an unplugged camera would, and every setpoint and
mode command the service sends is recorded with the time it reached the gate, i.e. the wire.

MAVLink framing (v2: STX 0xFD, 10-byte header, 2-byte CRC, a 13-byte signature when flagged; v1: STX
0xFE, 6-byte header, CRC) is enough to cut the byte stream into messages; payloads are decoded only for
SET_POSITION_TARGET_LOCAL_NED and COMMAND_LONG (MAVLink 2 trims trailing zero bytes: padded back).
"""

from __future__ import annotations

import asyncio
import struct
import time
from dataclasses import dataclass, field

MSG_SET_POSITION_TARGET_LOCAL_NED = 84
MSG_COMMAND_LONG = 76
MSG_LOCAL_POSITION_NED = 32
MSG_ATTITUDE = 30
_SPT = struct.Struct("<I11fHBBB")  # time_boot_ms, x y z vx vy vz afx afy afz yaw yaw_rate, type_mask, target sys/comp, frame
_CMD = struct.Struct("<7fHBBB")  # param1..7, command, target sys/comp, confirmation


@dataclass(frozen=True)
class WireSetpoint:
    """A SET_POSITION_TARGET_LOCAL_NED from the service: when it reached the gate (monotonic s), frame,
    type mask, body velocity (m/s) and yaw rate (rad/s)."""

    t_s: float
    frame: int
    type_mask: int
    vx: float
    vy: float
    vz: float
    yaw_rate: float

    @property
    def is_zero(self) -> bool:
        return self.vx == 0.0 and self.vy == 0.0 and self.vz == 0.0 and self.yaw_rate == 0.0


@dataclass(frozen=True)
class WireCommand:
    """A COMMAND_LONG from the service: when (monotonic s), the command id and params 1-7."""

    t_s: float
    command: int
    params: tuple[float, ...]


def split_frames(buf: bytearray) -> list[tuple[int, bytes, bytes]]:
    """Cut whole MAVLink frames off the front of ``buf`` (consumed); returns (message id or -1 for bytes
    that are no frame, payload, raw bytes) for each, in order. An incomplete frame stays in ``buf``."""
    out: list[tuple[int, bytes, bytes]] = []
    while buf:
        stx = buf[0]
        if stx == 0xFD:
            if len(buf) < 10:
                break
            n = buf[1]
            total = 10 + n + 2 + (13 if buf[2] & 0x01 else 0)
            if len(buf) < total:
                break
            msg_id = buf[7] | (buf[8] << 8) | (buf[9] << 16)
            out.append((msg_id, bytes(buf[10 : 10 + n]), bytes(buf[:total])))
        elif stx == 0xFE:
            if len(buf) < 6:
                break
            n = buf[1]
            total = 6 + n + 2
            if len(buf) < total:
                break
            out.append((buf[5], bytes(buf[6 : 6 + n]), bytes(buf[:total])))
        else:
            nxt = [i for i in (buf.find(b"\xfd"), buf.find(b"\xfe")) if i > 0]
            total = min(nxt) if nxt else len(buf)
            out.append((-1, b"", bytes(buf[:total])))
        del buf[:total]
    return out


def decode_setpoint(t_s: float, payload: bytes) -> WireSetpoint:
    f = _SPT.unpack(payload.ljust(_SPT.size, b"\0")[: _SPT.size])
    return WireSetpoint(t_s, f[15], f[12], f[4], f[5], f[6], f[11])


def decode_command(t_s: float, payload: bytes) -> WireCommand:
    f = _CMD.unpack(payload.ljust(_CMD.size, b"\0")[: _CMD.size])
    return WireCommand(t_s, f[7], tuple(f[:7]))


@dataclass
class MavlinkGate:
    """Listens on a free localhost TCP port (:attr:`url` for the service's ``vehicle.connection``) and
    relays each connection to ``upstream_port``.

    Attributes:
        blocked: message ids not passed on towards the service (change at any time).
        setpoints, commands: what the service sent, in order.
    """

    upstream_port: int
    host: str = "127.0.0.1"
    blocked: set[int] = field(default_factory=set)
    setpoints: list[WireSetpoint] = field(default_factory=list)
    commands: list[WireCommand] = field(default_factory=list)
    port: int = 0
    _server: asyncio.AbstractServer | None = None
    _tasks: set[asyncio.Task] = field(default_factory=set)

    @property
    def url(self) -> str:
        return f"tcpout://{self.host}:{self.port}"

    async def start(self) -> MavlinkGate:
        self._server = await asyncio.start_server(self._serve, self.host, 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def _serve(self, down_r: asyncio.StreamReader, down_w: asyncio.StreamWriter) -> None:
        up_r, up_w = await asyncio.open_connection(self.host, self.upstream_port)
        tasks = [
            asyncio.ensure_future(self._pump(down_r, up_w, towards_autopilot=True)),
            asyncio.ensure_future(self._pump(up_r, down_w, towards_autopilot=False)),
        ]
        self._tasks.update(tasks)
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for t in tasks:
            t.cancel()
        for w in (up_w, down_w):
            w.close()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, towards_autopilot: bool) -> None:
        buf = bytearray()
        while True:
            data = await reader.read(65536)
            if not data:
                return
            buf += data
            now = time.monotonic()
            out = bytearray()
            for msg_id, payload, raw in split_frames(buf):
                if towards_autopilot:
                    if msg_id == MSG_SET_POSITION_TARGET_LOCAL_NED:
                        self.setpoints.append(decode_setpoint(now, payload))
                    elif msg_id == MSG_COMMAND_LONG:
                        self.commands.append(decode_command(now, payload))
                elif msg_id in self.blocked:
                    continue
                out += raw
            if out:
                writer.write(bytes(out))
                await writer.drain()

    def setpoints_since(self, t_s: float) -> list[WireSetpoint]:
        return [s for s in self.setpoints if s.t_s >= t_s]

    def mode_commands_since(self, t_s: float) -> list[WireCommand]:
        """DO_SET_MODE commands (176) sent since ``t_s``."""
        return [c for c in self.commands if c.t_s >= t_s and c.command == 176]

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        for t in list(self._tasks):
            t.cancel()
        self._tasks.clear()
