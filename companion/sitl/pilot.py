"""The ground station: what a pilot does with QGroundControl, done over MAVSDK on PX4's GCS link.

It arms, takes off, lands, switches modes and sets parameters, and records PX4's own telemetry
(position and velocity NED, attitude, body rates, flight mode, armed, in air) with the time each
sample arrived on the local monotonic clock. The harness judges flights and measures the service's
failsafes on this record, never on what the service says about itself.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.service.aio import cancel_and_wait, logged
from companion.sitl.px4 import SitlError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sample:
    """One position/velocity report from PX4, with the newest attitude and body rates at that time.

    Attributes:
        time_s: arrival time, local monotonic clock, seconds.
        position_ned_m: float64 ``(3,)`` PX4's local position, metres.
        velocity_ned_m_s: float64 ``(3,)`` m/s.
        attitude_rad: float64 ``(3,)`` roll, pitch, yaw, radians (yaw clockwise from north).
        yaw_rate_rad_s: body yaw rate, rad/s.
        flight_mode: the autopilot's mode: PX4's as MAVSDK names it (``OFFBOARD``, ``HOLD``, ``TAKEOFF``,
            ...), ArduCopter's by its own number (``GUIDED``, ``LOITER``, ``BRAKE``, ...).
    """

    time_s: float
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    attitude_rad: np.ndarray
    yaw_rate_rad_s: float
    flight_mode: str


class Pilot:
    """A ground station on PX4's GCS link (:class:`~companion.sitl.ardupilot.ArduPilotPilot` is the one
    for ArduCopter).

    Args:
        connection: MAVSDK URL where PX4's GCS link sends (``udpin://127.0.0.1:14550``).
        system_id: the PX4 instance's MAVLink system id (instance + 1).
        clock: monotonic clock, seconds.
    """

    #: The autopilot this pilot flies, and its mode the service commands in (as :attr:`flight_mode` names it).
    AUTOPILOT = "px4"
    NAME = "PX4"
    OFFBOARD_MODE = "OFFBOARD"

    def __init__(self, connection: str, system_id: int = 1, clock: Callable[[], float] = time.monotonic) -> None:
        self.connection = connection
        self.system_id = system_id
        self._clock = clock
        self._mavsdk: Any = None
        self._system: Any = None
        self.action: Any = None
        self.telemetry: Any = None
        self.param: Any = None
        self._tasks: list[asyncio.Task] = []
        self.samples: list[Sample] = []
        self.mode_changes: list[tuple[float, str]] = []
        self.flight_mode = "UNKNOWN"
        self.armed = False
        self.in_air = False
        self.armable = False
        self._attitude = np.zeros(3)
        self._yaw_rate = 0.0
        self.recording = True

    async def connect(self, timeout_s: float = 15.0) -> None:
        """Connect and wait for the autopilot with :attr:`system_id`, then start recording.

        Raises:
            SitlError: no such autopilot heard within ``timeout_s``.
        """
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.param import ParamAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        await self._mavsdk.add_any_connection(self.connection)
        deadline = self._clock() + timeout_s
        while self._system is None:
            for system in await self._mavsdk.get_systems():
                if await system.has_autopilot() and await system.get_system_id() == self.system_id:
                    self._system = system
            if self._system is None:
                if self._clock() > deadline:
                    raise SitlError(f"no {self.NAME} with system id {self.system_id} heard on {self.connection} within {timeout_s:g} s")
                await asyncio.sleep(0.1)
        self.action = ActionAsync(self._system)
        self.telemetry = TelemetryAsync(self._system)
        self.param = ParamAsync(self._system)
        await self._attached(self._system)
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(logged(coro, f"pilot: the {what} subscription", log)) for coro, what in self._watchers()]

    async def _attached(self, system: Any) -> None:
        """Called once the autopilot is found, before the subscriptions start (subclasses add plugins)."""

    def _watchers(self) -> list[tuple[Any, str]]:
        """The telemetry subscriptions: (coroutine, what it is)."""
        return [
            (self._watch_mode(), "mode"),
            (self._watch_armed(), "armed"),
            (self._watch_in_air(), "in air"),
            (self._watch_health(), "health"),
            (self._watch_attitude(), "attitude"),
            (self._watch_rates(), "rates"),
            (self._watch_position(), "position"),
        ]

    @property
    def in_offboard(self) -> bool:
        """The vehicle is in the mode the service commands it in (PX4's OFFBOARD, ArduCopter's GUIDED)."""
        return self.flight_mode == self.OFFBOARD_MODE

    def _mode_seen(self, name: str) -> None:
        if name != self.flight_mode:
            self.mode_changes.append((self._clock(), name))
            log.info("%s flight mode: %s", self.AUTOPILOT, name)
        self.flight_mode = name

    async def _watch_mode(self) -> None:
        async for mode in self.telemetry.subscribe_flight_mode():
            self._mode_seen(getattr(mode, "name", str(mode)))

    async def _watch_armed(self) -> None:
        async for armed in self.telemetry.subscribe_armed():
            self.armed = bool(armed)

    async def _watch_in_air(self) -> None:
        async for in_air in self.telemetry.subscribe_in_air():
            self.in_air = bool(in_air)

    async def _watch_health(self) -> None:
        async for h in self.telemetry.subscribe_health():
            self.armable = bool(h.is_armable and h.is_local_position_ok)

    async def _watch_attitude(self) -> None:
        async for e in self.telemetry.subscribe_attitude_euler():
            self._attitude = np.radians(np.array([e.roll_deg, e.pitch_deg, e.yaw_deg], dtype=np.float64))

    async def _watch_rates(self) -> None:
        async for w in self.telemetry.subscribe_attitude_angular_velocity_body():
            self._yaw_rate = float(w.yaw_rad_s)

    async def _watch_position(self) -> None:
        async for pv in self.telemetry.subscribe_position_velocity_ned():
            if not self.recording:
                continue
            p, v = pv.position, pv.velocity
            self.samples.append(
                Sample(
                    time_s=self._clock(),
                    position_ned_m=np.array([p.north_m, p.east_m, p.down_m], dtype=np.float64),
                    velocity_ned_m_s=np.array([v.north_m_s, v.east_m_s, v.down_m_s], dtype=np.float64),
                    attitude_rad=self._attitude.copy(),
                    yaw_rate_rad_s=self._yaw_rate,
                    flight_mode=self.flight_mode,
                )
            )

    # ------------------------------------------------------------------ state

    def latest(self) -> Sample:
        """The newest sample. Raises SitlError before the first."""
        if not self.samples:
            raise SitlError(f"pilot: no position telemetry from {self.NAME} yet")
        return self.samples[-1]

    def samples_since(self, time_s: float) -> list[Sample]:
        return [s for s in self.samples if s.time_s >= time_s]

    async def wait_for(self, what: str, predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.02) -> float:
        """Wait until ``predicate()``; returns the time it became true.

        Raises:
            SitlError: naming ``what``, on timeout.
        """
        deadline = self._clock() + timeout_s
        while not predicate():
            if self._clock() > deadline:
                raise SitlError(f"{self.NAME}: {what} not seen within {timeout_s:g} s (mode {self.flight_mode}, armed {self.armed})")
            await asyncio.sleep(poll_s)
        return self._clock()

    # ------------------------------------------------------------------ commands

    async def _do(self, what: str, call: Callable[[], Any]) -> Any:
        """Await one MAVSDK request; its refusal becomes a SitlError naming ``what``."""
        from mavsdk.asyncio.plugins.action import ActionError
        from mavsdk.asyncio.plugins.param import ParamError

        try:
            return await call()
        except (ActionError, ParamError) as err:
            raise SitlError(f"{self.NAME} refused {what}: {err} (mode {self.flight_mode}, armed {self.armed})") from None

    async def set_params(self, params: dict[str, float | int]) -> None:
        """Set PX4 parameters (ints as INT32, floats as FLOAT) and read each back."""
        for name, value in params.items():
            if isinstance(value, int):
                await self._do(f"setting {name}", lambda: self.param.set_param_int(name, value))
                got: float = await self._do(f"reading {name}", lambda: self.param.get_param_int(name))
            else:
                await self._do(f"setting {name}", lambda: self.param.set_param_float(name, float(value)))
                got = await self._do(f"reading {name}", lambda: self.param.get_param_float(name))
            if not math.isclose(float(got), float(value), rel_tol=1e-6, abs_tol=1e-6):
                raise SitlError(f"{self.NAME} parameter {name}: set {value}, reads back {got}")
            log.info("%s parameter %s = %s", self.NAME, name, value)

    async def make_ready(self, timeout_s: float = 60.0) -> None:
        """Bring the vehicle to the ground, disarmed, armable: land it if flying, and leave a mode
        PX4 refuses to arm in (after an offboard-loss landing it stays in OFFBOARD) for Hold."""
        await self.wait_for("position telemetry", lambda: bool(self.samples), 20.0)
        if self.in_air or self.armed:
            await self.land(timeout_s)
        if self.flight_mode not in ("HOLD", "POSCTL", "ALTCTL", "MANUAL", "STABILIZED"):
            await self._do("Hold", self.action.hold)
            await self.wait_for("Hold on the ground", lambda: self.flight_mode == "HOLD", 10.0)
        await self.wait_for("ready to arm (health checks)", lambda: self.armable, timeout_s)

    async def take_off(self, altitude_m: float, timeout_s: float = 30.0) -> None:
        """Arm, take off to ``altitude_m`` above the take-off point, and wait until PX4 has finished
        the take-off (it switches to Hold) and the vehicle is steady (:meth:`wait_steady`, 1 s)."""
        await self._do("the take-off altitude", lambda: self.action.set_takeoff_altitude(float(altitude_m)))
        await self._do("arming", self.action.arm)
        await self._do("take-off", self.action.takeoff)
        await self.wait_for("take-off", lambda: self.flight_mode == "TAKEOFF", 10.0)
        # Take-off ends in Hold (AUTO.LOITER): wait for it, so the service finds a pilot-chosen mode.
        await self.wait_for("Hold after take-off", lambda: self.flight_mode == "HOLD", timeout_s)
        await self.wait_steady(1.0, timeout_s)

    async def wait_steady(self, for_s: float, timeout_s: float = 30.0) -> None:
        """Wait until the vehicle has been slower than 0.3 m/s for ``for_s`` seconds (PX4 SIH hovers
        with a few cm/s of wander)."""
        steady_since: list[float] = []

        def steady() -> bool:
            s = self.latest()
            if float(np.linalg.norm(s.velocity_ned_m_s)) >= 0.3:
                steady_since.clear()
                return False
            if not steady_since:
                steady_since.append(s.time_s)
            return s.time_s - steady_since[0] >= for_s

        await self.wait_for("a steady hover", steady, timeout_s)

    async def hold(self) -> None:
        await self._do("Hold", self.action.hold)

    async def land(self, timeout_s: float = 60.0) -> None:
        """Land where it is and wait until disarmed (PX4 disarms after landing)."""
        if self.armed and self.in_air:
            for attempt in range(3):
                await self._do("Land", self.action.land)
                try:
                    await self.wait_for("Land mode", lambda: self.flight_mode == "LAND" or not self.armed, 3.0)
                    break
                except SitlError:
                    # Another component's mode command crossed ours (e.g. a Hold in flight): again.
                    log.warning("PX4 did not enter Land (mode %s); asking again", self.flight_mode)
            await self.wait_for("landed and disarmed", lambda: not self.armed, timeout_s)
        elif self.armed:
            await self._do("disarming", self.action.disarm)
            await self.wait_for("disarmed", lambda: not self.armed, 10.0)

    def _plugins(self) -> list[Any]:
        """Every plugin to destroy on close (subclasses add theirs)."""
        return [self.action, self.telemetry, self.param]

    async def close(self) -> None:
        """Stop the subscriptions and release MAVSDK, plugins first (safe to call twice). Every pilot
        must be closed: MAVSDK aborts the whole process when an instance is destroyed, by the garbage
        collector too, while a plugin it handed out is still alive, and a test run then ends without
        its report."""
        try:
            await cancel_and_wait(self._tasks)
        finally:
            self._tasks = []
            for plugin in self._plugins():
                if plugin is not None:
                    plugin.destroy()
            self.action = self.telemetry = self.param = None
            self._system = None
            if self._mavsdk is not None:
                self._mavsdk.destroy()
                self._mavsdk = None
