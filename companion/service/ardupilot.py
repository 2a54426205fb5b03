"""The vehicle link for ArduCopter (ArduPilot) over MAVSDK: GUIDED with body velocity targets.

What differs from PX4, and what this link does about it (measured with MAVSDK 4.1 against ArduCopter
SITL, upstream master of 2025-07; docs/ardupilot.md has the parameters):

* **Telemetry.** ArduCopter streams almost nothing on a link until asked (its ``SRn_*`` rates are 0
  on most ports). The link asks for position/velocity (LOCAL_POSITION_NED) and attitude (ATTITUDE)
  at ``vehicle.telemetry_rate_hz`` with MAV_CMD_SET_MESSAGE_INTERVAL (per link), and asks again
  whenever position telemetry stops for a while (ArduPilot forgets the rates when it reboots). It
  sends that command itself, with every unused parameter 0: MAVSDK's ``telemetry.set_rate_*`` sends
  params 3-7 as NaN, which ArduPilot refuses (``param3`` must be 0, and NaN is not) and which crashed
  ArduCopter SITL (its floating-point traps: SIGFPE in ``handle_command_set_message_interval``).
* **Modes.** MAVSDK reports ArduPilot's modes under PX4's names: GUIDED reads OFFBOARD, LOITER and
  BRAKE both read HOLD, so a pilot's switch from GUIDED to BRAKE or LOITER would be invisible. The
  link reads the heartbeat itself (MAVSDK's ``mavlink_direct``) and names the mode by ArduCopter's
  own number (``ArduCopter/mode.h``). "In offboard" means GUIDED, and any other mode means the
  pilot (or ArduPilot's failsafe) took over.
* **Engaging** is a DO_SET_MODE to GUIDED by its number; **Hold** is LOITER (position hold, and the
  pilot's sticks still work), or BRAKE where no position estimate exists (ArduPilot's
  EKF_STATUS_REPORT, asked for at 2 Hz, says no horizontal position; without those reports: no
  LOCAL_POSITION_NED within :data:`POSITION_FRESH_S`); when ArduPilot refuses one, the other is
  tried. Both need a position estimate in ArduCopter (``requires_GPS``), like GUIDED itself, so
  without one both are refused: the service keeps zero velocity in GUIDED, and after
  ``vehicle.leave_timeout_s`` stops the stream, and GUIDED brakes after ``GUID_TIMEOUT``.
* **Never BRAKE behind a pilot.** MAVSDK's ``offboard.stop()`` and ``action.hold()`` select BRAKE on
  ArduCopter; this link calls neither, and stops the setpoint stream by releasing MAVSDK's Offboard
  plugin (no mode change), as the PX4 link does. Hold is only requested by the supervisor while the
  vehicle is in GUIDED because the service put it there.
* **No companion-loss failsafe.** When setpoints stop, ArduCopter flies the last velocity for
  ``GUID_TIMEOUT`` (3 s by default), then brakes and hovers in GUIDED indefinitely. MAVSDK re-sends
  the last setpoint at 20 Hz while the process lives, so the service's own watch (stale frames ->
  zero velocity -> LOITER) and the systemd watchdog are what stop a stalled service.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

from companion.errors import VehicleError
from companion.service.link_base import MavsdkLinkBase, MavsdkSession

log = logging.getLogger(__name__)

#: ArduCopter's flight modes by number (``ArduCopter/mode.h``, ``Mode::Number``).
COPTER_MODES: Mapping[int, str] = MappingProxyType(
    {
        0: "STABILIZE",
        1: "ACRO",
        2: "ALT_HOLD",
        3: "AUTO",
        4: "GUIDED",
        5: "LOITER",
        6: "RTL",
        7: "CIRCLE",
        9: "LAND",
        11: "DRIFT",
        13: "SPORT",
        14: "FLIP",
        15: "AUTOTUNE",
        16: "POSHOLD",
        17: "BRAKE",
        18: "THROW",
        19: "AVOID_ADSB",
        20: "GUIDED_NOGPS",
        21: "SMART_RTL",
        22: "FLOWHOLD",
        23: "FOLLOW",
        24: "ZIGZAG",
        25: "SYSTEMID",
        26: "AUTOROTATE",
        27: "AUTO_RTL",
        28: "TURTLE",
    }
)
GUIDED = 4
LOITER = 5
BRAKE = 17

#: A position report older than this means "no position estimate" when choosing LOITER or BRAKE
#: (used only without EKF status reports), s.
POSITION_FRESH_S = 1.0
#: An EKF_STATUS_REPORT older than this is not used, s.
EKF_REPORT_FRESH_S = 3.0
#: The rate asked for EKF_STATUS_REPORT, Hz.
EKF_REPORT_RATE_HZ = 2.0
#: Position telemetry missing this long (while the heartbeat is heard) -> the rates are asked again, s.
TELEMETRY_STALE_S = 3.0
#: Shortest time between two rate requests, s.
RATE_RETRY_S = 5.0

_MAV_AUTOPILOT_ARDUPILOTMEGA = 3
_MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
_MAV_MODE_FLAG_SAFETY_ARMED = 128
_MAV_CMD_DO_SET_MODE = 176
_MAV_CMD_SET_MESSAGE_INTERVAL = 511
_MAVLINK_MSG_ID_EKF_STATUS_REPORT = 193
_MAVLINK_MSG_ID_LOCAL_POSITION_NED = 32
_MAVLINK_MSG_ID_ATTITUDE = 30
_EKF_POS_HORIZ_REL = 8
_EKF_POS_HORIZ_ABS = 16
_EKF_CONST_POS_MODE = 128
_MAV_COMP_ID_AUTOPILOT1 = 1
_MAV_RESULTS = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED", 4: "FAILED", 5: "IN_PROGRESS", 6: "CANCELLED"}


def copter_mode_name(number: int) -> str:
    """ArduCopter's name for mode ``number`` (``MODE_<n>`` for one it does not have)."""
    return COPTER_MODES.get(int(number), f"MODE_{int(number)}")


class ArduPilotVehicleLink(MavsdkLinkBase):
    """:class:`~companion.interfaces.VehicleLink` for ArduCopter: GUIDED, body velocity and yaw rate.

    Args:
        connection: a MAVSDK connection URL (SITL: ``tcpout://127.0.0.1:5762``, its SERIAL1), or an
            open :class:`~companion.service.vehicle.MavsdkSession`.
        clock: the consumer's monotonic clock, seconds.
        telemetry_rate_hz: the rate asked for LOCAL_POSITION_NED and ATTITUDE, Hz.
    """

    AUTOPILOT = "ardupilot"

    def __init__(
        self,
        connection: str | MavsdkSession,
        clock: Callable[[], float] = time.monotonic,
        telemetry_rate_hz: float = 30.0,
    ) -> None:
        super().__init__(connection, clock)
        if not (math.isfinite(telemetry_rate_hz) and telemetry_rate_hz > 0.0):
            raise VehicleError(f"telemetry_rate_hz must be a positive number, got {telemetry_rate_hz}")
        self.telemetry_rate_hz = telemetry_rate_hz
        self._direct: Any = None
        self._system_id: int | None = None
        self._rates_asked_s: float | None = None  # when the rates were last asked for
        self._rates_ok = False  # ArduPilot accepted the last request
        self._ekf_position_ok = False  # the newest EKF_STATUS_REPORT has a horizontal position
        self._ekf_at_s: float | None = None  # when it arrived

    async def attach(self, system: Any) -> None:
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.vehicle import Vehicle

        vehicle = await system.vehicle_type()
        if vehicle not in (Vehicle.MULTICOPTER, Vehicle.UNKNOWN):
            raise VehicleError(
                f"the ArduPilot vehicle on {self.connection} is a {getattr(vehicle, 'name', vehicle)}: the service "
                "knows ArduCopter's modes only",
                kind="connection",
            )
        self._system_id = int(await system.get_system_id())
        self._direct = MavlinkDirectAsync(system)
        await super().attach(system)

    def _watchers(self) -> list[tuple[Any, str]]:
        return [
            (self._watch_heartbeat(), "ArduPilot heartbeat subscription"),
            (self._watch_ekf_status(), "ArduPilot EKF status subscription"),
            (self._keep_telemetry_rates(), "ArduPilot telemetry rates"),
        ]

    # ------------------------------------------------------------------ telemetry

    async def _watch_heartbeat(self) -> None:
        """Mode and armed state from the autopilot's own HEARTBEAT (not MAVSDK's PX4-named mode)."""
        assert self._direct is not None
        async for msg in self._direct.subscribe_message("HEARTBEAT"):
            if msg.system_id != self._system_id or msg.component_id != _MAV_COMP_ID_AUTOPILOT1:
                continue  # a ground station's or another component's heartbeat, routed by ArduPilot
            try:
                fields = json.loads(msg.fields_json)
                if int(fields["autopilot"]) != _MAV_AUTOPILOT_ARDUPILOTMEGA:
                    continue
                base_mode, custom_mode = int(fields["base_mode"]), int(fields["custom_mode"])
            except (ValueError, KeyError, TypeError):
                log.warning("ArduPilot heartbeat not understood: %.200s", msg.fields_json)
                continue
            name = copter_mode_name(custom_mode) if base_mode & _MAV_MODE_FLAG_CUSTOM_MODE_ENABLED else "UNKNOWN"
            if name != self._state.flight_mode:
                log.info("flight mode: %s", name)
            self._update(
                flight_mode=name,
                in_offboard=name == "GUIDED",
                armed=bool(base_mode & _MAV_MODE_FLAG_SAFETY_ARMED),
            )

    async def _watch_ekf_status(self) -> None:
        """Whether ArduPilot's EKF has a horizontal position (LOITER and BRAKE need one)."""
        assert self._direct is not None
        async for msg in self._direct.subscribe_message("EKF_STATUS_REPORT"):
            if msg.system_id != self._system_id or msg.component_id != _MAV_COMP_ID_AUTOPILOT1:
                continue
            try:
                flags = int(json.loads(msg.fields_json)["flags"])
            except (ValueError, KeyError, TypeError):
                log.warning("ArduPilot EKF status not understood: %.200s", msg.fields_json)
                continue
            ok = bool(flags & (_EKF_POS_HORIZ_ABS | _EKF_POS_HORIZ_REL)) and not flags & _EKF_CONST_POS_MODE
            if ok != self._ekf_position_ok:
                log.info("ArduPilot EKF: %s", "horizontal position estimate" if ok else "NO horizontal position estimate")
            self._ekf_position_ok, self._ekf_at_s = ok, self._clock()

    def note_ekf_status(self, position_ok: bool, now_s: float) -> None:
        """Record an EKF status (what :meth:`_watch_ekf_status` does; tests call it directly)."""
        self._ekf_position_ok, self._ekf_at_s = position_ok, now_s

    def rates_due(self, now_s: float) -> bool:
        """Whether to ask ArduPilot for the telemetry rates now: never asked, the last request not
        accepted, or position telemetry stopped for :data:`TELEMETRY_STALE_S` while the link is up
        (ArduPilot rebooted); never more often than every :data:`RATE_RETRY_S`.

        Args:
            now_s: the link's clock, seconds.
        """
        if not self._state.connected:
            return False
        if self._rates_asked_s is None:
            return True
        if now_s - self._rates_asked_s < RATE_RETRY_S:
            return False
        if not self._rates_ok:
            return True
        last = self._state.position_timestamp_s
        since = now_s - (last if last is not None else self._rates_asked_s)
        return since > TELEMETRY_STALE_S

    async def _keep_telemetry_rates(self) -> None:
        while True:
            if self.rates_due(self._clock()):
                await self.request_telemetry_rates()
            await asyncio.sleep(0.5)

    async def request_telemetry_rates(self) -> bool:
        """Ask for LOCAL_POSITION_NED and ATTITUDE at :attr:`telemetry_rate_hz`, and EKF_STATUS_REPORT
        at :data:`EKF_REPORT_RATE_HZ`; True when the first two were accepted."""
        self._rates_asked_s = self._clock()
        interval_us = 1e6 / self.telemetry_rate_hz
        results = [
            await self._command(_MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
            for msg_id in (_MAVLINK_MSG_ID_LOCAL_POSITION_NED, _MAVLINK_MSG_ID_ATTITUDE)
        ]
        if any(r != 0 for r in results):
            self._rates_ok = False
            log.warning(
                "ArduPilot refused the telemetry rates (%g Hz): %s; asking again later",
                self.telemetry_rate_hz,
                ", ".join(_MAV_RESULTS.get(r, "no answer") for r in results),
            )
            return False
        self._rates_ok = True
        result = await self._command(_MAV_CMD_SET_MESSAGE_INTERVAL, _MAVLINK_MSG_ID_EKF_STATUS_REPORT, 1e6 / EKF_REPORT_RATE_HZ)
        if result != 0:
            # Not fatal: without EKF reports, LOITER or BRAKE is chosen from the position telemetry.
            log.warning("ArduPilot: EKF_STATUS_REPORT not streamed (%s)", _MAV_RESULTS.get(result, result))
        log.info("ArduPilot streams position, velocity and attitude at %g Hz on this link", self.telemetry_rate_hz)
        return True

    # ------------------------------------------------------------------ modes

    async def _command(self, command: int, *params: float) -> int:
        """Send COMMAND_LONG ``command`` (params from param1) to the autopilot and wait for its
        acknowledgement; returns the MAV_RESULT (-1: no acknowledgement, or not understood)."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

        assert self._direct is not None and self._system_id is not None
        values = [float(p) for p in params] + [0.0] * (7 - len(params))
        fields = {
            "target_system": self._system_id,
            "target_component": _MAV_COMP_ID_AUTOPILOT1,
            "command": command,
            "confirmation": 0,
            **{f"param{i + 1}": v for i, v in enumerate(values)},
        }
        message = MavlinkMessage(
            message_name="COMMAND_LONG",
            target_system_id=self._system_id,
            target_component_id=_MAV_COMP_ID_AUTOPILOT1,
            fields_json=json.dumps(fields),
        )
        try:
            ack = await self._direct.send_command(message)
        except MavlinkDirectError as err:
            log.warning("ArduPilot: no acknowledgement of command %d (%s)", command, err)
            return -1
        try:
            return int(json.loads(ack.fields_json)["result"])
        except (ValueError, KeyError, TypeError):
            return -1

    async def set_mode(self, number: int) -> None:
        """Ask ArduCopter for mode ``number`` (MAV_CMD_DO_SET_MODE with the custom mode) and wait for
        its acknowledgement.

        Raises:
            VehicleError: refused (the MAV_RESULT named), or no acknowledgement.
        """
        name = copter_mode_name(number)
        self._require_system(f"set mode {name}")
        result = await self._command(_MAV_CMD_DO_SET_MODE, _MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number)
        if result != 0:
            if result == -1:
                raise VehicleError(f"ArduPilot mode {name}: no acknowledgement", mode=name)
            raise VehicleError(
                f"ArduPilot refused mode {name} ({_MAV_RESULTS.get(result, result)}; vehicle in {self._state.flight_mode})",
                mode=name,
                result=result,
            )
        log.info("ArduPilot mode %s accepted", name)

    async def start_offboard(self) -> None:
        """Engage: GUIDED by its mode number (ArduCopter needs no setpoint stream before it, but the
        supervisor's contract is kept: a setpoint first, so MAVSDK re-sends it)."""
        self._require_system("start_offboard")
        if self._offboard is None:
            raise VehicleError("start_offboard: no setpoint streamed yet")
        await self.set_mode(GUIDED)

    def has_position_estimate(self, now_s: float) -> bool:
        """Whether ArduPilot has a horizontal position estimate at ``now_s`` (seconds): its newest
        EKF_STATUS_REPORT (if one within :data:`EKF_REPORT_FRESH_S`) says so, or, without those
        reports, a LOCAL_POSITION_NED arrived within :data:`POSITION_FRESH_S`."""
        if self._ekf_at_s is not None and now_s - self._ekf_at_s <= EKF_REPORT_FRESH_S:
            return self._ekf_position_ok
        last = self._state.position_timestamp_s
        return last is not None and now_s - last <= POSITION_FRESH_S

    def hold_mode(self, now_s: float) -> int:
        """LOITER with a position estimate (:meth:`has_position_estimate` at ``now_s``, seconds), else BRAKE."""
        return LOITER if self.has_position_estimate(now_s) else BRAKE

    async def hold(self) -> None:
        """Leave GUIDED to LOITER (or BRAKE, :meth:`hold_mode`); the other one if ArduPilot refuses.

        Raises:
            VehicleError: both refused (the service retries, then stops the stream: GUIDED then
                brakes after ``GUID_TIMEOUT`` and hovers).
        """
        self._require_system("hold")
        first = self.hold_mode(self._clock())
        try:
            await self.set_mode(first)
            return
        except VehicleError as err:
            second = BRAKE if first == LOITER else LOITER
            log.warning("%s; trying %s", err, copter_mode_name(second))
        await self.set_mode(second)
