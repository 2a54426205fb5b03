"""What every autopilot's link over MAVSDK shares: the MAVSDK session (one ``System`` configured as the
vehicle's companion computer) and :class:`MavsdkLinkBase`, the telemetry, setpoints, heartbeat, status
text and obstacle distances common to PX4 (:mod:`companion.service.vehicle`) and ArduPilot
(:mod:`companion.service.ardupilot`). See :mod:`companion.service.vehicle` for what MAVSDK does that
matters here.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from companion.core.obstacle import ObstacleDistance
from companion.core.types import VelocitySetpoint
from companion.errors import VehicleError
from companion.interfaces import VehicleState
from companion.service.aio import cancel_and_wait, logged

if TYPE_CHECKING:
    from companion.config.service import VehicleConfig

log = logging.getLogger(__name__)
_mavsdk_log = logging.getLogger(__name__ + ".mavsdk")

#: The autopilots a link exists for (``vehicle.autopilot`` adds ``auto``).
AUTOPILOTS: tuple[str, ...] = ("px4", "ardupilot")

MAV_COMP_ID_OBSTACLE_AVOIDANCE = 196
_MAV_TYPE_ONBOARD_CONTROLLER = 18
_MAV_AUTOPILOT_INVALID = 8


def _forward_mavsdk_log(level: Any, message: str, file: str | None, line: int) -> bool:
    """MAVSDK's own log lines into Python logging (True: suppress MAVSDK's printing to stdout)."""
    py_level = {0: logging.DEBUG, 1: logging.INFO, 2: logging.WARNING, 3: logging.ERROR}.get(int(level), logging.INFO)
    _mavsdk_log.log(py_level, "%s", message)
    return True


def check_mavsdk_cache(environ: Mapping[str, str] | None = None) -> Path:
    """Make sure MAVSDK can write its cache folder, ``$HOME/.cache/mavsdk`` (it keeps the autopilot's
    component metadata there once one is heard), before MAVSDK starts: MAVSDK cannot report a folder
    it may not write to Python, and depending on its version it logs and goes on or aborts the process.
    Returns the folder.

    Raises:
        VehicleError: ``kind="connection"``: HOME is not set, or the folder cannot be made or written
            (naming the folder and HOME, the variable that moves it).
    """
    env = os.environ if environ is None else environ
    home = env.get("HOME")
    if not home:
        raise VehicleError(
            "HOME is not set: MAVSDK keeps its cache in $HOME/.cache/mavsdk; set HOME to a folder the "
            "service's user may write",
            kind="connection",
        )
    cache = Path(home) / ".cache" / "mavsdk"
    try:
        cache.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=cache):
            pass
    except OSError as err:
        raise VehicleError(
            f"{cache}: MAVSDK's cache folder cannot be written ({err.strerror or err}); set HOME (now "
            f"{home}) to a folder the service's user may write, or let it write this one",
            kind="connection",
        ) from None
    return cache


class MavsdkSession:
    """One MAVSDK instance with one connection, shared by the link that flies through it.

    Args:
        connection: MAVSDK connection URL (``udpin://0.0.0.0:14540``, ``tcpout://127.0.0.1:5762``,
            ``serial:///dev/ttyTHS1:921600``).
        component_id: the MAVLink component id the service sends from (``vehicle.component_id``;
            196 = MAV_COMP_ID_OBSTACLE_AVOIDANCE), 1..254.
        system_id: its MAVLink system id, the vehicle's (``vehicle.system_id``), 1..254.
    """

    def __init__(self, connection: str, component_id: int = MAV_COMP_ID_OBSTACLE_AVOIDANCE, system_id: int = 1) -> None:
        self.connection = connection
        self.component_id = int(component_id)
        self.system_id = int(system_id)
        self.mavsdk: Any = None
        self._connection_added = False

    async def open(self) -> None:
        """Create MAVSDK and add the connection (fails fast on a bad URL or a missing serial port).

        Raises:
            VehicleError: with ``kind="connection"`` in its context.
        """
        if self._connection_added:
            return
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkConnectionError
        from mavsdk.logging import log_subscribe

        log_subscribe(_forward_mavsdk_log)
        if self.mavsdk is None:
            check_mavsdk_cache()
            # A companion computer (MAV_TYPE_ONBOARD_CONTROLLER in MAVSDK's heartbeat), as the
            # obstacle-avoidance component unless configured otherwise.
            config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
            config.component_id = self.component_id
            config.system_id = self.system_id
            self.mavsdk = Mavsdk(config)
        try:
            await self.mavsdk.add_any_connection(self.connection)
        except MavsdkConnectionError as err:
            raise VehicleError(
                f"vehicle.connection {self.connection!r}: MAVSDK cannot open it: {err}", kind="connection"
            ) from None
        self._connection_added = True
        log.info("MAVSDK listening on %s", self.connection)

    async def first_autopilot(self, timeout_s: float) -> Any:
        """Open if needed and wait for an autopilot's heartbeat; returns MAVSDK's system.

        Raises:
            VehicleError: ``kind="connection"`` (see :meth:`open`) or ``kind="timeout"`` (no autopilot
                heard within ``timeout_s`` seconds).
        """
        await self.open()
        system = await self.mavsdk.first_autopilot(timeout_s)
        if system is None:
            raise VehicleError(f"no autopilot heard on {self.connection} within {timeout_s:g} s", kind="timeout")
        return system

    def destroy(self) -> None:
        """Release MAVSDK (safe to call twice)."""
        if self.mavsdk is not None:
            self.mavsdk.destroy()
            self.mavsdk = None
        self._connection_added = False


async def autopilot_of(system: Any) -> str | None:
    """``"px4"`` or ``"ardupilot"`` as the system's heartbeat names it (MAV_AUTOPILOT_PX4,
    MAV_AUTOPILOT_ARDUPILOTMEGA), None for anything else."""
    from mavsdk.autopilot import Autopilot

    kind = await system.autopilot_type()
    return {Autopilot.PX4: "px4", Autopilot.ARDUPILOT: "ardupilot"}.get(kind)


def _check_autopilot(wanted: str, found: str | None, connection: str) -> None:
    """Raise when the heartbeat names another autopilot than the configured one (an unknown one is
    let through: the link's own checks decide).

    Raises:
        VehicleError: ``kind="connection"`` (a config error: the service must not guess modes).
    """
    if found is not None and found != wanted:
        raise VehicleError(
            f"vehicle.autopilot is {wanted!r} but the autopilot on {connection} is {found}; "
            "set vehicle.autopilot to 'auto' or to the one flying",
            kind="connection",
        )


class MavsdkLinkBase:
    """What the PX4 and the ArduPilot link share: the session, the autopilot's system, position and
    attitude telemetry, the setpoint stream and its release. Subclasses add how modes are read and
    changed (:meth:`_watchers`, :meth:`start_offboard`, :meth:`hold`).

    Args:
        connection: a MAVSDK connection URL, or a :class:`MavsdkSession` already open (the
            :class:`MavsdkVehicleLink` that found the autopilot hands its own over).
        clock: the consumer's monotonic clock (stamps :class:`VehicleState`), seconds.
    """

    #: The autopilot this link flies (``"px4"``, ``"ardupilot"``).
    AUTOPILOT: ClassVar[str] = ""

    def __init__(self, connection: str | MavsdkSession, clock: Callable[[], float] = time.monotonic) -> None:
        self._session = connection if isinstance(connection, MavsdkSession) else MavsdkSession(connection)
        self.connection = self._session.connection
        self._clock = clock
        self._system: Any = None
        self._offboard: Any = None
        self._action: Any = None
        self._telemetry: Any = None
        self._direct: Any = None  # MAVSDK's mavlink_direct: any message to the autopilot
        self._utility: Any = None  # MAVSDK's server_utility: STATUSTEXT
        self._tasks: list[asyncio.Task] = []
        self._state = VehicleState()
        self._closed = False

    # ------------------------------------------------------------------ connection

    async def open(self) -> None:
        """Add the connection now (fails fast on a bad URL). Raises VehicleError ``kind="connection"``."""
        await self._session.open()

    async def connect(self, timeout_s: float) -> None:
        """Open the connection if needed, wait for the autopilot's heartbeat and attach to it.

        Raises:
            VehicleError: ``kind="connection"`` (bad URL, port busy, no such serial device, or the
                heartbeat names another autopilot than this link's) or ``kind="timeout"`` (no
                autopilot heard within ``timeout_s`` seconds).
        """
        system = await self._session.first_autopilot(timeout_s)
        _check_autopilot(self.AUTOPILOT, await autopilot_of(system), self.connection)
        await self.attach(system)

    async def attach(self, system: Any) -> None:
        """Start using ``system`` (an autopilot MAVSDK has heard): plugins and telemetry subscriptions.

        Raises:
            VehicleError: ``kind="connection"`` when this link cannot fly that vehicle.
        """
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.asyncio.plugins.server_utility import ServerUtilityAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        self._system = system
        self._telemetry = TelemetryAsync(system)
        self._action = ActionAsync(system)
        if self._direct is None:
            self._direct = MavlinkDirectAsync(system)
        self._utility = ServerUtilityAsync(system)
        self._state = replace(self._state, connected=True, autopilot=self.AUTOPILOT, timestamp_s=self._clock())
        loop = asyncio.get_running_loop()
        # A telemetry stream failing must not take the service down (logged, not raised): the state
        # keeps its last values and `connected` tells the truth through the connection stream.
        watchers = [
            (self._watch_connection(system), "MAVSDK connection subscription"),
            (self._watch_position(), "MAVSDK position subscription"),
            (self._watch_attitude(), "MAVSDK attitude subscription"),
            *self._watchers(),
        ]
        self._tasks = [loop.create_task(logged(coro, what, log)) for coro, what in watchers]
        log.info(
            "%s autopilot found on %s (system id %d)", self.AUTOPILOT, self.connection, await system.get_system_id()
        )

    def _watchers(self) -> list[tuple[Any, str]]:
        """The subclass's own subscriptions: (coroutine, what it is, for the log)."""
        return []

    def _update(self, **changes: Any) -> None:
        self._state = replace(self._state, timestamp_s=self._clock(), **changes)

    async def _watch_connection(self, system: Any) -> None:
        async for connected in system.is_connected_state():
            if connected != self._state.connected:
                log.warning("vehicle link %s", "back" if connected else "LOST (no heartbeat)")
            self._update(connected=bool(connected))

    async def _watch_position(self) -> None:
        assert self._telemetry is not None
        async for pv in self._telemetry.subscribe_position_velocity_ned():
            p, vel = pv.position, pv.velocity
            self._update(
                position_ned_m=np.array([p.north_m, p.east_m, p.down_m], dtype=np.float64),
                position_timestamp_s=self._clock(),
                velocity_ned_m_s=np.array([vel.north_m_s, vel.east_m_s, vel.down_m_s], dtype=np.float64),
            )

    async def _watch_attitude(self) -> None:
        assert self._telemetry is not None
        async for e in self._telemetry.subscribe_attitude_euler():
            self._update(
                attitude_rad=np.radians(np.array([e.roll_deg, e.pitch_deg, e.yaw_deg], dtype=np.float64))
            )

    # ------------------------------------------------------------------ commands

    def state(self) -> VehicleState:
        return self._state

    def _require_system(self, what: str) -> Any:
        if self._system is None:
            raise VehicleError(f"{what}: no autopilot connected")
        return self._system

    async def send_setpoint(self, setpoint: VelocitySetpoint) -> None:
        """Hand one body-frame velocity setpoint to MAVSDK (sent now, and re-sent by MAVSDK at 20 Hz)."""
        from mavsdk.asyncio.plugins.offboard import (
            OffboardAsync,
            OffboardError,
            VelocityBodyYawspeed,
        )

        system = self._require_system("send_setpoint")
        values = (setpoint.forward_m_s, setpoint.right_m_s, setpoint.down_m_s, setpoint.yaw_rate_deg_s)
        if not all(math.isfinite(v) for v in values):
            raise VehicleError(f"send_setpoint: non-finite setpoint {setpoint}")
        if self._offboard is None:
            self._offboard = OffboardAsync(system)
        try:
            await self._offboard.set_velocity_body(VelocityBodyYawspeed(*values))
        except OffboardError as err:
            raise VehicleError(f"offboard setpoint rejected: {err}") from None

    async def start_offboard(self) -> None:
        raise NotImplementedError

    async def hold(self) -> None:
        raise NotImplementedError

    async def stop_setpoints(self) -> None:
        """Stop MAVSDK's re-sending without a mode change: destroy the Offboard plugin (never
        ``offboard.stop()``, which commands Hold, or BRAKE on ArduCopter)."""
        offboard, self._offboard = self._offboard, None
        if offboard is not None:
            offboard.destroy()
            log.info("setpoint stream stopped (no mode change)")

    def _plugins(self) -> list[Any]:
        """Every plugin to destroy on close (subclasses add theirs)."""
        plugins = [self._telemetry, self._action, self._direct, self._utility]
        self._direct = self._utility = None
        return plugins

    # ------------------------------------------------------------------ presence

    async def _send_direct(self, name: str, fields: dict[str, Any]) -> None:
        """Send MAVLink message ``name`` with ``fields`` (broadcast) through ``mavlink_direct``.

        Raises:
            VehicleError: no autopilot connected, or MAVSDK refused the message.
        """
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

        self._require_system(f"send {name}")
        if self._direct is None:
            raise VehicleError(f"send {name}: the link is closed")
        message = MavlinkMessage(
            message_name=name,
            system_id=0,
            component_id=0,
            target_system_id=0,
            target_component_id=0,
            fields_json=json.dumps(fields),
        )
        try:
            await self._direct.send_message(message)
        except MavlinkDirectError as err:
            raise VehicleError(f"send {name}: {err}") from None

    async def send_heartbeat(self, mav_state: int) -> None:
        """The service's HEARTBEAT: an onboard controller (MAV_TYPE 18, no autopilot) whose
        ``system_status`` is ``mav_state`` (MAV_STATE: 3 standby, 4 active, 5 critical)."""
        await self._send_direct(
            "HEARTBEAT",
            {
                "type": _MAV_TYPE_ONBOARD_CONTROLLER,
                "autopilot": _MAV_AUTOPILOT_INVALID,
                "base_mode": 0,
                "custom_mode": 0,
                "system_status": int(mav_state),
                "mavlink_version": 3,
            },
        )

    async def send_status_text(self, severity: int, text: str) -> None:
        """One STATUSTEXT (``severity``: MAV_SEVERITY, 0 emergency .. 7 debug; ``text`` <= 50 ASCII
        characters) through MAVSDK's ``server_utility``.

        Raises:
            VehicleError: no autopilot connected, or MAVSDK refused it.
        """
        from mavsdk.plugins.server_utility import ServerUtilityError, StatusTextType

        self._require_system("send STATUSTEXT")
        if self._utility is None:
            raise VehicleError("send STATUSTEXT: the link is closed")
        # MAVSDK's StatusTextType counts the other way round: DEBUG 0 .. EMERGENCY 7.
        kind = StatusTextType(7 - min(7, max(0, int(severity))))
        try:
            await self._utility.send_status_text(kind, text)
        except ServerUtilityError as err:
            raise VehicleError(f"send STATUSTEXT: {err}") from None

    async def send_obstacle_distance(self, obstacle: ObstacleDistance, time_usec: int) -> None:
        """One OBSTACLE_DISTANCE: 72 uint16 distances (cm), ``increment`` 5 (and ``increment_f`` 5.0),
        ``angle_offset`` 0, MAV_FRAME_BODY_FRD; ``time_usec`` the frame's capture time on the
        monotonic clock, microseconds."""
        await self._send_direct(
            "OBSTACLE_DISTANCE",
            {
                "time_usec": int(time_usec),
                "sensor_type": int(obstacle.sensor_type),
                "distances": [int(x) for x in obstacle.distances_cm],
                "increment": int(obstacle.increment_deg),
                "min_distance": int(obstacle.min_distance_cm),
                "max_distance": int(obstacle.max_distance_cm),
                "increment_f": float(obstacle.increment_deg),
                "angle_offset": float(obstacle.angle_offset_deg),
                "frame": int(obstacle.frame),
            },
        )

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        await cancel_and_wait(self._tasks)
        self._tasks = []
        await self.stop_setpoints()
        for plugin in self._plugins():
            if plugin is not None:
                plugin.destroy()
        self._telemetry = self._action = None
        self._system = None
        self._session.destroy()
        log.info("vehicle link closed")


