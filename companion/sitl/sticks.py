"""The ground station's sticks: :class:`StickPilot` flies PX4 by MAVSDK's manual control, and
:func:`push_until_at_rest` watches a vehicle the stick pushes at a wall until its autopilot holds it
still (any :class:`~companion.sitl.pilot.Pilot`: PX4's or ArduPilot's).
"""

from __future__ import annotations

import asyncio
import json
import math
from typing import Any

import numpy as np

from companion.sitl.pilot import Pilot
from companion.sitl.px4 import SitlError

_MAV_CMD_DO_SET_MODE = 176
#: PX4's custom main modes, as DO_SET_MODE's param2 (QGroundControl's mode menu).
PX4_MAIN_POSCTL = 3
PX4_MAIN_OFFBOARD = 6


class StickPilot(Pilot):
    """The ground station with sticks: MAVSDK ``manual_control`` streamed at 20 Hz (x forward, y right,
    z throttle 0..1 with 0.5 = hold altitude, r yaw), and mode changes by DO_SET_MODE as
    QGroundControl's mode menu sends them."""

    async def _attached(self, system: Any) -> None:
        from mavsdk.asyncio.plugins.manual_control import ManualControlAsync
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync

        self.manual = ManualControlAsync(system)
        self.direct = MavlinkDirectAsync(system)
        self.sticks = [0.0, 0.0, 0.5, 0.0]
        self._stick_task: asyncio.Task | None = None

    async def _stream_sticks(self) -> None:
        while True:
            await self.manual.set_manual_control_input(*self.sticks)
            await asyncio.sleep(0.05)

    async def start_sticks(self) -> None:
        """Stream the sticks (centred) from now on; PX4 needs them before Position mode."""
        if self._stick_task is None:
            self._stick_task = asyncio.get_running_loop().create_task(self._stream_sticks())
            await asyncio.sleep(0.5)

    async def position_mode(self) -> float:
        """Switch to Position mode with the sticks (MAVSDK ``start_position_control``); returns when asked."""
        from mavsdk.asyncio.plugins.manual_control import ManualControlError

        await self.start_sticks()
        t = self._clock()
        try:
            await self.manual.start_position_control()
        except ManualControlError as err:
            raise SitlError(f"PX4 refused Position mode: {err} (mode {self.flight_mode})") from None
        return t

    async def altitude_mode(self) -> None:
        """Switch to Altitude mode with the sticks (MAVSDK ``start_altitude_control``)."""
        from mavsdk.asyncio.plugins.manual_control import ManualControlError

        await self.start_sticks()
        try:
            await self.manual.start_altitude_control()
        except ManualControlError as err:
            raise SitlError(f"PX4 refused Altitude mode: {err} (mode {self.flight_mode})") from None

    async def set_px4_mode(self, main_mode: int) -> int:
        """DO_SET_MODE with PX4's custom main mode (QGroundControl's mode menu); returns the MAV_RESULT."""
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        fields = {
            "target_system": self.system_id, "target_component": 1, "command": _MAV_CMD_DO_SET_MODE, "confirmation": 0,
            "param1": 1.0, "param2": float(main_mode), "param3": 0.0, "param4": 0.0, "param5": 0.0, "param6": 0.0,
            "param7": 0.0,
        }
        ack = await self.direct.send_command(
            MavlinkMessage(
                message_name="COMMAND_LONG", system_id=0, component_id=0, target_system_id=self.system_id,
                target_component_id=1, fields_json=json.dumps(fields),
            )
        )
        try:
            return int(json.loads(ack.fields_json)["result"])
        except (ValueError, KeyError, TypeError):
            return -1

    def _plugins(self) -> list[Any]:
        return [*super()._plugins(), getattr(self, "manual", None), getattr(self, "direct", None)]

    async def close(self) -> None:
        if getattr(self, "_stick_task", None) is not None:
            self._stick_task.cancel()
            try:
                await self._stick_task
            except (asyncio.CancelledError, Exception):  # noqa: BLE001 - ending the stream, whatever it raised
                pass
            self._stick_task = None
        await super().close()


def horizontal_speed(s: Any) -> float:
    """A telemetry sample's speed over the ground, m/s (its NED velocity's north and east)."""
    return float(np.linalg.norm(s.velocity_ned_m_s[:2]))


async def push_until_at_rest(
    pilot: Pilot, wall_distance: Any, collision_radius_m: float, what: str, timeout_s: float = 40.0
) -> tuple[float, float, float]:
    """With the stick already forward: watch until the autopilot holds the vehicle still. Returns the
    nearest distance to the wall, the top speed and the median distance of the last 2 s (metres, m/s).

    Raises:
        SitlError: the vehicle hit the wall (the pilot takes over first), or never came to rest.
    """
    t0 = pilot._clock()
    nearest, max_speed = math.inf, 0.0
    while pilot._clock() - t0 < timeout_s:
        await asyncio.sleep(0.05)
        s = pilot.latest()
        d = wall_distance(s)
        nearest, max_speed = min(nearest, d), max(max_speed, horizontal_speed(s))
        if d < collision_radius_m:
            await pilot.hold()
            raise SitlError(f"the vehicle hit the wall (distance {d:.2f} m): {pilot.NAME}'s {what} did not stop it")
        # At rest: every position of the last 2 s within 0.3 m of the newest (SITL hovers wander at up
        # to 0.2 m/s, too much for a speed threshold).
        recent = pilot.samples_since(s.time_s - 2.0)
        if s.time_s - t0 > 5.0 and max(float(np.linalg.norm(r.position_ned_m[:2] - s.position_ned_m[:2])) for r in recent) < 0.3:
            break
    else:
        raise SitlError(f"{pilot.NAME} did not bring the vehicle to rest within {timeout_s:g} s (nearest {nearest:.2f} m)")
    settled = float(np.median([wall_distance(r) for r in pilot.samples_since(pilot.latest().time_s - 2.0)]))
    return nearest, max_speed, settled
