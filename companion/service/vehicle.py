"""The vehicle link over MAVSDK (``mavsdk`` >= 4.1, the native binding's ``mavsdk.asyncio`` API).

What MAVSDK does that matters here (read in MAVSDK's ``cpp/src/mavsdk/plugins/offboard/offboard_impl.cpp``):

* ``set_velocity_body`` stores the setpoint, sends it at once, and registers a ``call_every`` that
  **re-sends the last setpoint every 50 ms (20 Hz) by itself**, whether or not we call again. So a
  stalled service would keep PX4's offboard-loss failsafe from ever firing: the supervisor watches
  frame age itself, and the systemd watchdog kills the whole process (MAVSDK with it) if the control
  loop stalls.
* The re-sending stops by itself only when a HEARTBEAT says the vehicle is not in OFFBOARD **and** more
  than 3 s have passed since offboard was started or setpoints began (a grace period). Until then it
  keeps re-sending the last value after a pilot's mode change.
* ``offboard.stop()`` stops the re-sending **and commands Hold** (``set_flight_mode(FlightMode::Hold)``,
  MAV_CMD_DO_SET_MODE AUTO.LOITER). Called after a pilot switched to Position mode it would take the
  vehicle away from the pilot. This link never calls it.
* Destroying the Offboard plugin (its destructor -> ``deinit`` -> ``stop_sending_setpoints``) stops the
  re-sending **without** any mode change. :meth:`MavsdkVehicleLink.stop_setpoints` does that (after the
  supervisor has sent a final zero, so nothing non-zero is ever left to re-send) and the next
  :meth:`send_setpoint` creates a fresh plugin.
* Leaving offboard to Hold is ``action.hold()`` (the same DO_SET_MODE), only ever called while we own
  offboard.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from companion.core.types import VelocitySetpoint
from companion.errors import VehicleError
from companion.interfaces import VehicleState
from companion.service.aio import cancel_and_wait, logged

log = logging.getLogger(__name__)
_mavsdk_log = logging.getLogger("companion.service.vehicle.mavsdk")


def _forward_mavsdk_log(level: Any, message: str, file: str | None, line: int) -> bool:
    """MAVSDK's own log lines into Python logging (True: suppress MAVSDK's printing to stdout)."""
    py_level = {0: logging.DEBUG, 1: logging.INFO, 2: logging.WARNING, 3: logging.ERROR}.get(int(level), logging.INFO)
    _mavsdk_log.log(py_level, "%s", message)
    return True


class MavsdkVehicleLink:
    """:class:`~companion.interfaces.VehicleLink` over MAVSDK.

    Args:
        connection: MAVSDK connection URL (``udpin://0.0.0.0:14540``, ``serial:///dev/ttyTHS1:921600``).
        clock: the consumer's monotonic clock (stamps :class:`VehicleState`), seconds.
    """

    def __init__(self, connection: str, clock: Callable[[], float] = time.monotonic) -> None:
        self.connection = connection
        self._clock = clock
        self._mavsdk = None
        self._system = None
        self._offboard = None
        self._action = None
        self._telemetry = None
        self._tasks: list[asyncio.Task] = []
        self._state = VehicleState()
        self._connection_added = False
        self._closed = False

    # ------------------------------------------------------------------ connection

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
        if self._mavsdk is None:
            config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
            self._mavsdk = Mavsdk(config)
        try:
            await self._mavsdk.add_any_connection(self.connection)
        except MavsdkConnectionError as err:
            raise VehicleError(
                f"vehicle.connection {self.connection!r}: MAVSDK cannot open it: {err}", kind="connection"
            ) from None
        self._connection_added = True
        log.info("MAVSDK listening on %s", self.connection)

    async def connect(self, timeout_s: float) -> None:
        """Open the connection if needed and wait for the autopilot's heartbeat.

        Raises:
            VehicleError: ``kind="connection"`` (bad URL, port busy, no such serial device) or
                ``kind="timeout"`` (no autopilot heard within ``timeout_s``).
        """
        await self.open()
        assert self._mavsdk is not None
        system = await self._mavsdk.first_autopilot(timeout_s)
        if system is None:
            raise VehicleError(
                f"no autopilot heard on {self.connection} within {timeout_s:g} s", kind="timeout"
            )
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        self._system = system
        self._telemetry = TelemetryAsync(system)
        self._action = ActionAsync(system)
        self._state = replace(self._state, connected=True, timestamp_s=self._clock())
        loop = asyncio.get_running_loop()
        # A telemetry stream failing must not take the service down (logged, not raised): the state
        # keeps its last values and `connected` tells the truth through the connection stream.
        self._tasks = [
            loop.create_task(logged(self._watch_connection(system), "MAVSDK connection subscription", log)),
            loop.create_task(logged(self._watch_flight_mode(), "MAVSDK flight mode subscription", log)),
            loop.create_task(logged(self._watch_armed(), "MAVSDK armed subscription", log)),
            loop.create_task(logged(self._watch_position(), "MAVSDK position subscription", log)),
            loop.create_task(logged(self._watch_attitude(), "MAVSDK attitude subscription", log)),
        ]
        log.info("autopilot found on %s (system id %d)", self.connection, await system.get_system_id())

    def _update(self, **changes: Any) -> None:
        self._state = replace(self._state, timestamp_s=self._clock(), **changes)

    async def _watch_connection(self, system: Any) -> None:
        async for connected in system.is_connected_state():
            if connected != self._state.connected:
                log.warning("vehicle link %s", "back" if connected else "LOST (no heartbeat)")
            self._update(connected=bool(connected))

    async def _watch_flight_mode(self) -> None:
        assert self._telemetry is not None
        async for mode in self._telemetry.subscribe_flight_mode():
            name = getattr(mode, "name", str(mode))
            if name != self._state.flight_mode:
                log.info("flight mode: %s", name)
            self._update(flight_mode=name, in_offboard=name == "OFFBOARD")

    async def _watch_armed(self) -> None:
        assert self._telemetry is not None
        async for armed in self._telemetry.subscribe_armed():
            self._update(armed=bool(armed))

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
        from mavsdk.asyncio.plugins.offboard import OffboardError

        self._require_system("start_offboard")
        if self._offboard is None:
            raise VehicleError("start_offboard: no setpoint streamed yet (PX4 would refuse)")
        try:
            await self._offboard.start()
        except OffboardError as err:
            raise VehicleError(f"offboard start refused: {err}") from None

    async def hold(self) -> None:
        from mavsdk.asyncio.plugins.action import ActionError

        self._require_system("hold")
        assert self._action is not None
        try:
            await self._action.hold()
        except ActionError as err:
            raise VehicleError(f"Hold refused: {err}") from None

    async def stop_setpoints(self) -> None:
        """Stop MAVSDK's re-sending without a mode change: destroy the Offboard plugin (never
        ``offboard.stop()``, which commands Hold)."""
        offboard, self._offboard = self._offboard, None
        if offboard is not None:
            offboard.destroy()
            log.info("setpoint stream stopped (no mode change)")

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        await cancel_and_wait(self._tasks)
        self._tasks = []
        await self.stop_setpoints()
        for plugin in (self._telemetry, self._action):
            if plugin is not None:
                plugin.destroy()
        self._telemetry = self._action = None
        self._system = None
        if self._mavsdk is not None:
            self._mavsdk.destroy()
            self._mavsdk = None
        log.info("vehicle link closed")
