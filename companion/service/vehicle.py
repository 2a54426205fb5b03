"""The vehicle link over MAVSDK (``mavsdk`` >= 4.1, the native binding's ``mavsdk.asyncio`` API), for
PX4 and ArduPilot.

:class:`MavsdkVehicleLink` is what the service builds (:func:`make_vehicle_link`): it opens MAVSDK on
``vehicle.connection``, waits for the autopilot's heartbeat, and hands the rest to one link per
autopilot (``vehicle.autopilot``: ``px4``, ``ardupilot``, or ``auto``: whichever the heartbeat's
``autopilot`` field names): :class:`Px4VehicleLink` here, and
:class:`~companion.service.ardupilot.ArduPilotVehicleLink`. Both implement the same
:class:`~companion.interfaces.VehicleLink`; the supervisor above them never sees which one it drives.

What MAVSDK does that matters here (read in MAVSDK's ``cpp/src/mavsdk/plugins/offboard/offboard_impl.cpp``):

* ``set_velocity_body`` stores the setpoint, sends it at once, and registers a ``call_every`` that
  **re-sends the last setpoint every 50 ms (20 Hz) by itself**, whether or not we call again. So a
  stalled service would keep PX4's offboard-loss failsafe (and ArduCopter's ``GUID_TIMEOUT``) from
  ever firing: the supervisor watches frame age itself, and the systemd watchdog kills the whole
  process (MAVSDK with it) if the control loop stalls.
* The re-sending stops by itself only when a HEARTBEAT says the vehicle is not in OFFBOARD (MAVSDK
  reads ArduCopter's GUIDED as OFFBOARD) **and** more than 3 s have passed since offboard was started
  or setpoints began (a grace period). Until then it keeps re-sending the last value after a pilot's
  mode change.
* ``offboard.stop()`` stops the re-sending **and commands Hold** (``set_flight_mode(FlightMode::Hold)``:
  PX4's AUTO.LOITER, ArduCopter's BRAKE). Called after a pilot switched to Position mode (or LOITER) it
  would take the vehicle away from the pilot. No link here calls it.
* Destroying the Offboard plugin (its destructor -> ``deinit`` -> ``stop_sending_setpoints``) stops the
  re-sending **without** any mode change. ``stop_setpoints`` does that (after the supervisor has sent a
  final zero, so nothing non-zero is ever left to re-send) and the next ``send_setpoint`` creates a
  fresh plugin.
* Leaving offboard to Hold is only ever requested while we own offboard: on PX4 ``action.hold()``
  (the same DO_SET_MODE), on ArduPilot LOITER by its own mode number.

The service's presence on the ground station, through the same MAVSDK:

* MAVSDK is configured as a companion computer with ``vehicle.system_id`` (the vehicle's) and
  ``vehicle.component_id`` (196, MAV_COMP_ID_OBSTACLE_AVOIDANCE), so everything the service sends comes
  from that component of the vehicle's system.
* MAVSDK heartbeats that component by itself at 1 Hz with ``system_status`` 0 (MAV_STATE_UNINIT: MAVSDK
  4.1 offers no way to set it). The service's own HEARTBEAT (:meth:`MavsdkLinkBase.send_heartbeat`,
  ``mavlink_direct``) carries its state (standby / active / critical) at ``vehicle.heartbeat_rate_hz``.
* STATUSTEXT through ``server_utility`` (:meth:`MavsdkLinkBase.send_status_text`), OBSTACLE_DISTANCE
  through ``mavlink_direct`` (:meth:`MavsdkLinkBase.send_obstacle_distance`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from companion.core.obstacle import ObstacleDistance
from companion.core.types import VelocitySetpoint
from companion.errors import VehicleError
from companion.interfaces import VehicleState
from companion.service.ardupilot import ArduPilotVehicleLink
from companion.service.link_base import (
    AUTOPILOTS,
    MAV_COMP_ID_OBSTACLE_AVOIDANCE,
    MavsdkLinkBase,
    MavsdkSession,
    _check_autopilot,
    autopilot_of,
)

if TYPE_CHECKING:
    from companion.config.service import VehicleConfig

log = logging.getLogger(__name__)


class Px4VehicleLink(MavsdkLinkBase):
    """:class:`~companion.interfaces.VehicleLink` for PX4: its flight modes as MAVSDK names them,
    offboard by ``offboard.start()``, Hold by ``action.hold()`` (AUTO.LOITER)."""

    AUTOPILOT = "px4"

    def _watchers(self) -> list[tuple[Any, str]]:
        return [
            (self._watch_flight_mode(), "MAVSDK flight mode subscription"),
            (self._watch_armed(), "MAVSDK armed subscription"),
        ]

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


class MavsdkVehicleLink:
    """:class:`~companion.interfaces.VehicleLink` over MAVSDK for the autopilot that answers.

    It opens MAVSDK, waits for the autopilot's heartbeat, picks :class:`Px4VehicleLink` or
    :class:`~companion.service.ardupilot.ArduPilotVehicleLink` (``autopilot``, or the heartbeat's
    ``autopilot`` field for ``"auto"``), and passes every call to it.

    Args:
        connection: MAVSDK connection URL.
        clock: the consumer's monotonic clock (stamps :class:`VehicleState`), seconds.
        autopilot: ``"auto"``, ``"px4"`` or ``"ardupilot"`` (``vehicle.autopilot``).
        telemetry_rate_hz: ArduPilot: the rate asked for position, velocity and attitude, Hz
            (``vehicle.telemetry_rate_hz``).
        component_id: the MAVLink component id the service sends from (``vehicle.component_id``).
        system_id: the MAVLink system id it sends as, the vehicle's (``vehicle.system_id``).
    """

    def __init__(
        self,
        connection: str,
        clock: Callable[[], float] = time.monotonic,
        autopilot: str = "auto",
        telemetry_rate_hz: float = 30.0,
        component_id: int = MAV_COMP_ID_OBSTACLE_AVOIDANCE,
        system_id: int = 1,
    ) -> None:
        if autopilot not in ("auto", *AUTOPILOTS):
            raise VehicleError(f"vehicle.autopilot {autopilot!r}: must be auto, {', '.join(AUTOPILOTS)}", kind="connection")
        self.connection = connection
        self.autopilot = autopilot
        self.telemetry_rate_hz = telemetry_rate_hz
        self._clock = clock
        self._session = MavsdkSession(connection, component_id, system_id)
        self._link: MavsdkLinkBase | None = None
        self._closed = False

    @property
    def link(self) -> MavsdkLinkBase | None:
        """The autopilot's own link once connected, else None."""
        return self._link

    async def open(self) -> None:
        """Add the connection now (fails fast on a bad URL). Raises VehicleError ``kind="connection"``."""
        await self._session.open()

    async def connect(self, timeout_s: float) -> None:
        """Wait for the autopilot's heartbeat and attach the link for it.

        Raises:
            VehicleError: ``kind="connection"`` (bad URL, no such serial device, an autopilot other
                than ``vehicle.autopilot``, or one the service has no link for) or ``kind="timeout"``.
        """
        if self._link is not None:
            return
        system = await self._session.first_autopilot(timeout_s)
        found = await autopilot_of(system)
        kind = self.autopilot
        if kind == "auto":
            if found is None:
                raise VehicleError(
                    f"the autopilot on {self.connection} is neither PX4 nor ArduPilot (its heartbeat's "
                    "MAV_AUTOPILOT); the service flies only those two",
                    kind="connection",
                )
            kind = found
        else:
            _check_autopilot(kind, found, self.connection)
        link: MavsdkLinkBase
        if kind == "ardupilot":
            link = ArduPilotVehicleLink(self._session, clock=self._clock, telemetry_rate_hz=self.telemetry_rate_hz)
        else:
            link = Px4VehicleLink(self._session, clock=self._clock)
        await link.attach(system)
        self._link = link

    def state(self) -> VehicleState:
        return self._link.state() if self._link is not None else VehicleState()

    def _require_link(self, what: str) -> MavsdkLinkBase:
        if self._link is None:
            raise VehicleError(f"{what}: no autopilot connected")
        return self._link

    async def send_setpoint(self, setpoint: VelocitySetpoint) -> None:
        await self._require_link("send_setpoint").send_setpoint(setpoint)

    async def start_offboard(self) -> None:
        await self._require_link("start_offboard").start_offboard()

    async def hold(self) -> None:
        await self._require_link("hold").hold()

    async def stop_setpoints(self) -> None:
        if self._link is not None:
            await self._link.stop_setpoints()

    async def send_heartbeat(self, mav_state: int) -> None:
        await self._require_link("send HEARTBEAT").send_heartbeat(mav_state)

    async def send_status_text(self, severity: int, text: str) -> None:
        await self._require_link("send STATUSTEXT").send_status_text(severity, text)

    async def send_obstacle_distance(self, obstacle: ObstacleDistance, time_usec: int) -> None:
        await self._require_link("send OBSTACLE_DISTANCE").send_obstacle_distance(obstacle, time_usec)

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._link is not None:
            await self._link.close()  # destroys the session too
        else:
            self._session.destroy()
            log.info("vehicle link closed")


def make_vehicle_link(cfg: VehicleConfig, clock: Callable[[], float] = time.monotonic) -> MavsdkVehicleLink:
    """The service's vehicle link for the ``[vehicle]`` config (connection, autopilot, telemetry rate)."""
    return MavsdkVehicleLink(
        cfg.connection,
        clock=clock,
        autopilot=cfg.autopilot,
        telemetry_rate_hz=cfg.telemetry_rate_hz,
        component_id=cfg.component_id,
        system_id=cfg.system_id,
    )
