"""ArduPilot SITL in the loop: a headless ArduCopter SITL process with its built-in quad model, and the
ground station that flies it.

ArduPilot is not part of this project: a user builds it (``./waf configure --board sitl && ./waf copter``
in an ArduPilot checkout, see docs/sitl-ardupilot.md) and points :func:`find_ardupilot_build` at the
checkout. Instance ``N`` (``-I N``) serves MAVLink on TCP ports ``5760 + 10 N`` (SERIAL0, the ground
station's; ArduPilot waits for it before it boots) and ``5762 + 10 N`` (SERIAL1, the service's, as a
companion computer's UART), and reads its RC receiver on UDP ``5501 + 10 N``. Its system id is 1.

The pilot (:class:`ArduPilotPilot`) speaks to ArduCopter by its own mode numbers, as the service does
(MAVSDK names ArduPilot's modes with PX4's names: GUIDED reads OFFBOARD, LOITER and BRAKE both read
HOLD), and moves SITL's RC sticks as a pilot would: the throttle down to arm (ArduCopter refuses to
arm otherwise), centred once flying (SITL's receiver starts with the throttle at its lowest, and
LOITER then descends and lands).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import socket
import struct
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.service.ardupilot import COPTER_MODES, copter_mode_name
from companion.sitl.pilot import Pilot
from companion.sitl.px4 import SitlError, SitlProcess

log = logging.getLogger(__name__)

#: ArduPilot parameters the harness sets before every flight (what they do: docs/sitl-ardupilot.md and
#: docs/ardupilot.md).
SITL_PARAMS: dict[str, float | int] = {
    # Setpoints missing this long in GUIDED: ArduCopter brakes and hovers (still in GUIDED), seconds.
    # The default 3 s flies the last velocity ~2 m at the cruise speed after the service is gone; MAVSDK
    # re-sends at 20 Hz while the process lives, so this fires only when it (or the link) is gone.
    "GUID_TIMEOUT": 0.5,
}

#: Environment variable naming an ArduPilot checkout with a SITL build (``build/sitl/bin/arducopter``).
ARDUPILOT_BUILD_ENV = "COMPANION_ARDUPILOT_BUILD"
#: Where SITL's vehicle starts: latitude, longitude (degrees), altitude (m AMSL), heading (degrees).
DEFAULT_HOME = "47.397742,8.545594,488.0,0"

_MAV_CMD_DO_SET_MODE = 176
_MAV_CMD_COMPONENT_ARM_DISARM = 400
_MAV_CMD_NAV_TAKEOFF = 22
_MAV_CMD_SET_MESSAGE_INTERVAL = 511
_MSG_LOCAL_POSITION_NED = 32
_MSG_ATTITUDE = 30
_MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
_MAV_MODE_FLAG_SAFETY_ARMED = 128
_MAV_AUTOPILOT_ARDUPILOTMEGA = 3
_MAV_RESULTS = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED", 4: "FAILED", 5: "IN_PROGRESS", 6: "CANCELLED"}
_MODE_NUMBERS = {name: number for number, name in COPTER_MODES.items()}
#: SITL's RC receiver with the sticks centred (throttle too: LOITER holds its altitude) and the
#: mode switch (channel 5) where SITL puts it; PWM, microseconds, channels 1-8.
CENTRED_STICKS_US = (1500, 1500, 1500, 1500, 1800, 1000, 1000, 1800)
#: The throttle stick down (arming needs it), microseconds.
THROTTLE_DOWN_US = 1000
#: The pitch stick (channel 2) full forward: ArduCopter reads a low pulse as nose down, microseconds.
PITCH_FORWARD_US = 1100


@dataclass(frozen=True)
class ArduPilotBuild:
    """An ArduPilot checkout with a SITL build: the ArduCopter binary and its SITL defaults."""

    root: Path

    @property
    def binary(self) -> Path:
        return self.root / "build/sitl/bin/arducopter"

    @property
    def defaults(self) -> Path:
        return self.root / "Tools/autotest/default_params/copter.parm"


def find_ardupilot_build(
    path: str | os.PathLike[str] | None = None, environ: dict[str, str] | None = None
) -> ArduPilotBuild | None:
    """The ArduPilot checkout: ``path`` if given, else ``$COMPANION_ARDUPILOT_BUILD``; None when
    neither is set. Its ``build/sitl`` folder is accepted too.

    Raises:
        SitlError: the folder is named but has no ``build/sitl/bin/arducopter`` or no
            ``Tools/autotest/default_params/copter.parm``.
    """
    env = os.environ if environ is None else environ
    text = os.fspath(path) if path is not None else env.get(ARDUPILOT_BUILD_ENV)
    if not text:
        return None
    root = Path(text).expanduser().resolve()
    if root.name == "sitl" and root.parent.name == "build":
        root = root.parent.parent
    build = ArduPilotBuild(root)
    missing = [str(p.relative_to(root)) for p in (build.binary, build.defaults) if not p.exists()]
    if missing:
        raise SitlError(
            f"{root}: not an ArduPilot checkout with a SITL build (no {', '.join(missing)}); build one with "
            "`./waf configure --board sitl && ./waf copter` (docs/sitl-ardupilot.md)"
        )
    return build


@dataclass(frozen=True)
class ArduPilotPorts:
    """The ports of ArduPilot SITL instance ``instance`` (``-I N``)."""

    instance: int = 0

    @property
    def pilot_port(self) -> int:
        """SERIAL0, TCP: the ground station's link (SITL waits for it before booting)."""
        return 5760 + 10 * self.instance

    @property
    def api_port(self) -> int:
        """SERIAL1, TCP: the service's link."""
        return 5762 + 10 * self.instance

    @property
    def rc_port(self) -> int:
        """UDP: SITL's RC receiver (16-bit PWM values, channels 1-8 or 1-16)."""
        return 5501 + 10 * self.instance

    @property
    def system_id(self) -> int:
        """ArduPilot's MAVLink system id (``MAV_SYSID``, 1 for every instance)."""
        return 1

    @property
    def service_url(self) -> str:
        """The service's ``vehicle.connection``."""
        return f"tcpout://127.0.0.1:{self.api_port}"

    @property
    def pilot_url(self) -> str:
        """The ground station's MAVSDK connection."""
        return f"tcpout://127.0.0.1:{self.pilot_port}"


class ArduPilotSitl(SitlProcess):
    """One ArduCopter SITL process (``arducopter --model quad --home ... --defaults copter.parm -I N -w``,
    real time), in its own working folder (``eeprom.bin``, ``logs/``, and ``arducopter.log``, the
    console output).

    Args:
        build: the checkout (:func:`find_ardupilot_build`).
        workdir: SITL's working folder (created).
        instance: the instance number (ports, :class:`ArduPilotPorts`).
        home: where the vehicle starts, ``LAT,LNG,ALT,HDG``.
        boot_params: parameters loaded at boot after copter.parm (a defaults file in ``workdir``): those
            that take effect only at boot, such as ``PRX1_TYPE``.
    """

    NAME = "ArduPilot SITL"

    def __init__(
        self,
        build: ArduPilotBuild,
        workdir: Path,
        instance: int = 0,
        home: str = DEFAULT_HOME,
        boot_params: dict[str, float] | None = None,
    ) -> None:
        self.build = build
        self.workdir = workdir
        self.ports = ArduPilotPorts(instance)
        self.home = home
        self.boot_params = dict(boot_params or {})
        super().__init__()

    @property
    def log_path(self) -> Path:
        return self.workdir / "arducopter.log"

    def start(self, fresh: bool = True, timeout_s: float = 30.0) -> None:
        """Start SITL and wait until it listens for the ground station (it boots once that connects).

        Args:
            fresh: wipe the stored parameters first (``-w``: a clean vehicle with copter.parm's defaults).
            timeout_s: seconds to wait.

        Raises:
            SitlError: it exited or did not listen in time (the log's tail is in the message).
        """
        self.workdir.mkdir(parents=True, exist_ok=True)
        defaults = str(self.build.defaults)
        if self.boot_params:
            extra = self.workdir / "companion.parm"
            extra.write_text("".join(f"{name} {value:g}\n" for name, value in self.boot_params.items()))
            defaults += f",{extra}"
        cmd = [
            str(self.build.binary), "--model", "quad", "--home", self.home, "--defaults", defaults,
            "-I", str(self.ports.instance),
        ]  # fmt: skip
        if fresh:
            cmd.append("-w")
        log.info("starting ArduPilot SITL instance %d: %s", self.ports.instance, " ".join(cmd))
        with self.log_path.open("wb") as out:
            self._proc = subprocess.Popen(
                cmd, cwd=self.workdir, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
            )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                raise SitlError(f"ArduPilot SITL exited with {self._proc.returncode} while starting:\n{self.log_tail()}")
            if b"Waiting for connection" in self.log_path.read_bytes():
                return
            time.sleep(0.1)
        self.stop()
        raise SitlError(f"ArduPilot SITL did not listen within {timeout_s:g} s:\n{self.log_tail()}")


def centre_sticks(
    rc_port: int, throttle_us: int = CENTRED_STICKS_US[2], host: str = "127.0.0.1", pitch_us: int = CENTRED_STICKS_US[1]
) -> None:
    """Put SITL's RC receiver at :data:`CENTRED_STICKS_US` (it keeps the last values it received),
    as a pilot's transmitter with the sticks centred, the throttle at ``throttle_us`` (microseconds:
    :data:`THROTTLE_DOWN_US` to arm) and the pitch stick at ``pitch_us`` (:data:`PITCH_FORWARD_US`: full
    forward)."""
    values = list(CENTRED_STICKS_US)
    values[2] = int(throttle_us)
    values[1] = int(pitch_us)
    packet = struct.pack("<8H", *values)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(packet, (host, rc_port))


class ArduPilotPilot(Pilot):
    """A ground station on ArduCopter SITL's SERIAL0: by ArduCopter's mode numbers, with the RC
    sticks centred.

    Args:
        connection: MAVSDK URL of SITL's SERIAL0 (``tcpout://127.0.0.1:5760``).
        system_id: ArduPilot's system id (1).
        clock: monotonic clock, seconds.
        rc_port: SITL's RC input port (:attr:`ArduPilotPorts.rc_port`); None: leave the sticks alone.
        telemetry_rate_hz: the rate asked for position, velocity and attitude on this link, Hz.
    """

    AUTOPILOT = "ardupilot"
    NAME = "ArduPilot"
    OFFBOARD_MODE = "GUIDED"

    def __init__(
        self,
        connection: str,
        system_id: int = 1,
        clock: Callable[[], float] = time.monotonic,
        rc_port: int | None = None,
        telemetry_rate_hz: float = 50.0,
    ) -> None:
        super().__init__(connection, system_id, clock)
        self.rc_port = rc_port
        self.telemetry_rate_hz = telemetry_rate_hz
        self.direct: Any = None

    async def _attached(self, system: Any) -> None:
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync

        self.direct = MavlinkDirectAsync(system)

    def _watchers(self) -> list[tuple[Any, str]]:
        return [
            (self._watch_heartbeat(), "heartbeat"),
            (self._keep_rates(), "telemetry rates"),
            (self._watch_attitude(), "attitude"),
            (self._watch_rates(), "rates"),
            (self._watch_position(), "position"),
        ]

    async def _watch_heartbeat(self) -> None:
        async for msg in self.direct.subscribe_message("HEARTBEAT"):
            if msg.system_id != self.system_id or msg.component_id != 1:
                continue
            fields = json.loads(msg.fields_json)
            if int(fields.get("autopilot", -1)) != _MAV_AUTOPILOT_ARDUPILOTMEGA:
                continue
            base = int(fields["base_mode"])
            self.armed = bool(base & _MAV_MODE_FLAG_SAFETY_ARMED)
            self._mode_seen(copter_mode_name(int(fields["custom_mode"])) if base & _MAV_MODE_FLAG_CUSTOM_MODE_ENABLED else "UNKNOWN")

    async def _keep_rates(self) -> None:
        """Ask for position, velocity and attitude on this link (ArduCopter streams almost nothing
        unasked), and again while none arrives (the first requests can land before SITL has booted)."""
        while True:
            last = self.samples[-1].time_s if self.samples else None
            if last is None or self._clock() - last > 2.0:
                # By hand, every unused parameter 0 (MAVSDK's set_rate_* sends NaN: refused, and SIGFPE in SITL).
                for msg_id in (_MSG_LOCAL_POSITION_NED, _MSG_ATTITUDE):
                    try:
                        result = await self.command("a telemetry rate", _MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / self.telemetry_rate_hz)
                    except SitlError as err:
                        result = str(err)
                    if result != 0:
                        log.info("ArduPilot: telemetry rate of message %d not set yet (%s)", msg_id, _MAV_RESULTS.get(result, result))
            await asyncio.sleep(2.0)

    # ------------------------------------------------------------------ commands, by the numbers

    async def request_rate(self, msg_id: int, rate_hz: float) -> int:
        """Ask ArduPilot to stream message ``msg_id`` on this link at ``rate_hz``; returns the MAV_RESULT."""
        return await self.command(f"the rate of message {msg_id}", _MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate_hz)

    async def command(self, what: str, command: int, *params: float, timeout_s: float | None = None) -> int:
        """Send COMMAND_LONG ``command`` with ``params`` (param1...) and return ArduPilot's MAV_RESULT.

        Raises:
            SitlError: no acknowledgement.
        """
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

        values = [float(p) for p in params] + [0.0] * (7 - len(params))
        fields = {"target_system": self.system_id, "target_component": 1, "command": command, "confirmation": 0}
        fields.update({f"param{i + 1}": v for i, v in enumerate(values)})
        message = MavlinkMessage(
            message_name="COMMAND_LONG", target_system_id=self.system_id, target_component_id=1, fields_json=json.dumps(fields)
        )
        try:
            ack = await self.direct.send_command(message)
        except MavlinkDirectError as err:
            raise SitlError(f"ArduPilot: no answer to {what}: {err}") from None
        return int(json.loads(ack.fields_json).get("result", -1))

    async def _until_accepted(self, what: str, command: int, *params: float, timeout_s: float, retry_s: float = 1.0) -> None:
        """Repeat a command until ArduPilot accepts it (pre-arm checks pass, the position estimate is
        there), at most ``timeout_s`` seconds."""
        deadline = self._clock() + timeout_s
        while True:
            result = await self.command(what, command, *params)
            if result == 0:
                return
            if self._clock() > deadline:
                raise SitlError(
                    f"ArduPilot refused {what} for {timeout_s:g} s ({_MAV_RESULTS.get(result, result)}; "
                    f"mode {self.flight_mode}, armed {self.armed})"
                )
            await asyncio.sleep(retry_s)

    async def set_mode(self, name: str, timeout_s: float = 5.0) -> None:
        """Switch to ArduCopter mode ``name`` (by its number) and wait until the heartbeat says so.

        Raises:
            SitlError: refused for ``timeout_s`` seconds, or not seen.
        """
        number = _MODE_NUMBERS[name]
        await self._until_accepted(f"mode {name}", _MAV_CMD_DO_SET_MODE, _MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number, timeout_s=timeout_s)
        await self.wait_for(f"mode {name}", lambda: self.flight_mode == name, 5.0)

    def sticks(self, throttle_us: int, pitch_us: int = CENTRED_STICKS_US[1]) -> None:
        """SITL's RC sticks centred, the throttle at ``throttle_us`` and the pitch stick at ``pitch_us``
        (no RC port: nothing)."""
        if self.rc_port is not None:
            centre_sticks(self.rc_port, throttle_us, pitch_us=pitch_us)

    async def make_ready(self, timeout_s: float = 90.0) -> None:
        """Position telemetry arriving (ArduPilot has booted and its EKF has an origin), and the
        vehicle on the ground and disarmed (landed if it was flying), the throttle down."""
        await self.wait_for("position telemetry (ArduPilot booted, EKF origin set)", lambda: bool(self.samples), timeout_s)
        if self.armed:
            if self.flight_mode in ("LOITER", "GUIDED", "BRAKE", "POSHOLD", "ALT_HOLD"):
                self.sticks(CENTRED_STICKS_US[2])  # flying in a mode that reads the throttle: keep altitude
            await self.land(timeout_s)
        self.sticks(THROTTLE_DOWN_US)

    async def take_off(self, altitude_m: float, timeout_s: float = 90.0) -> None:
        """GUIDED, arm, take off to ``altitude_m`` above the ground (MAV_CMD_NAV_TAKEOFF), wait for the
        altitude and a steady hover, then hand the vehicle to LOITER (a pilot's mode: the service
        refuses to engage a vehicle already in GUIDED)."""
        # GUIDED needs a position estimate and arming the pre-arm checks (GPS, EKF): both come some
        # seconds after SITL boots, so they are asked again until accepted.
        await self._until_accepted("GUIDED", _MAV_CMD_DO_SET_MODE, _MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, _MODE_NUMBERS["GUIDED"], timeout_s=timeout_s)
        await self.wait_for("GUIDED", lambda: self.flight_mode == "GUIDED", 5.0)
        self.sticks(THROTTLE_DOWN_US)
        ground_down = float(self.latest().position_ned_m[2])
        await self._until_accepted("arming", _MAV_CMD_COMPONENT_ARM_DISARM, 1.0, timeout_s=timeout_s, retry_s=2.0)
        await self.wait_for("armed", lambda: self.armed, 5.0)
        await self._until_accepted("take-off", _MAV_CMD_NAV_TAKEOFF, *([0.0] * 6), float(altitude_m), timeout_s=5.0)
        await self.wait_for(
            f"take-off to {altitude_m:g} m",
            lambda: ground_down - float(self.latest().position_ned_m[2]) >= altitude_m - 0.1,
            30.0,
        )
        await self.wait_steady(1.0, timeout_s)
        self.sticks(CENTRED_STICKS_US[2])  # LOITER reads the throttle stick as a climb rate: centred holds
        await self.set_mode("LOITER")
        await self.wait_steady(1.0, timeout_s)

    async def hold(self) -> None:
        """The safety pilot takes over: LOITER."""
        result = await self.command("LOITER", _MAV_CMD_DO_SET_MODE, _MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, _MODE_NUMBERS["LOITER"])
        if result != 0:
            raise SitlError(f"ArduPilot refused LOITER ({_MAV_RESULTS.get(result, result)}; mode {self.flight_mode})")

    async def land(self, timeout_s: float = 60.0) -> None:
        """LAND where it is and wait until disarmed (ArduCopter disarms once landed)."""
        if not self.armed:
            return
        await self.set_mode("LAND", timeout_s=10.0)
        await self.wait_for("landed and disarmed", lambda: not self.armed, timeout_s)

    def _plugins(self) -> list[Any]:
        plugins = [*super()._plugins(), self.direct]
        self.direct = None
        return plugins

    def speed_m_s(self) -> float:
        """The newest horizontal speed ArduPilot reports, m/s."""
        return float(np.linalg.norm(self.latest().velocity_ned_m_s[:2]))
