"""The ground-station scenarios with PX4 or ArduPilot SITL in the loop (``companion sitl --scenario ...``).

* **collision-prevention**: the service only feeds OBSTACLE_DISTANCE (never engaged). With ``CP_DIST``
  set, a ground-station pilot flies Position mode (MAVSDK ``manual_control``, stick full forward) at the
  ``wall`` course's wall; PX4's own Collision Prevention must stop the vehicle roughly ``CP_DIST`` short
  of it (measured against the true geometry). Then the pilot backs off, pushes forward again, and the
  service is stopped while the vehicle flies at the wall: with no fresh data (0.5 s) PX4 must go to
  zero velocity.
* **rc-engage**: ``vehicle.engage_on_offboard_switch`` on; the ground station switches PX4 to Offboard
  (a DO_SET_MODE, as QGroundControl's mode menu or an RC switch does) while the service is ready; the
  service must take over and avoid (judged on the course's true geometry); switching back to Position
  mode must hand the vehicle back at once, with no mode command from the service.
* **proximity** (ArduPilot): the same wall, ArduCopter in LOITER with its proximity library fed only by
  the service's OBSTACLE_DISTANCE (``PRX1_TYPE`` 2, simple avoidance stopping at ``AVOID_MARGIN``); the
  pilot's pitch stick full forward. ArduCopter must stop the vehicle about the margin short of the wall.
  Then the service stops while the vehicle stands there, stick still forward: what ArduCopter does is
  measured (its proximity data expires 0.5 s after the last message).
* **step-response** (PX4): the ground station flies offboard itself and steps its velocity and yaw-rate
  setpoints; the simulator's vehicle model is fitted to PX4's response
  (:mod:`companion.sitl.step_response`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import CompanionConfig
from companion.sim.courses import Course, make_course
from companion.sim.scoring import Outcome
from companion.sitl.ardupilot import CENTRED_STICKS_US, PITCH_FORWARD_US, ArduPilotPilot, ArduPilotSitl
from companion.sitl.flight import (
    PARAMS_BY_AUTOPILOT,
    SITL_PARAMS,
    _Recorder,
    place_course,
    placement_at,
    sitl_config,
    start_and_place,
)
from companion.sitl.pilot import Pilot
from companion.sitl.px4 import Px4Ports, Px4Sitl, SitlError
from companion.sitl.service import ServiceProcess

log = logging.getLogger(__name__)

SCENARIOS: tuple[str, ...] = ("collision-prevention", "rc-engage", "proximity", "step-response")

_MAV_CMD_DO_SET_MODE = 176
_PX4_MAIN_POSCTL = 3
_PX4_MAIN_OFFBOARD = 6


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


def _speed(s: Any) -> float:
    return float(np.linalg.norm(s.velocity_ned_m_s[:2]))


async def _push_until_at_rest(
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
        nearest, max_speed = min(nearest, d), max(max_speed, _speed(s))
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


@dataclass
class CollisionPreventionResult:
    """What the collision-prevention flight measured (distances to the wall's true surface, metres)."""

    cp_dist_m: float
    wall_m: float  # the wall's front face, north of the start, m
    stop_distance_m: float  # nearest the vehicle came to the wall while the service fed PX4
    settled_distance_m: float  # where it stood still, stick still forward
    max_speed_m_s: float
    obstacle_messages: int  # OBSTACLE_DISTANCE the service sent (its health)
    # After the service stopped (SIGTERM) with the vehicle flying at the wall:
    speed_at_stop_m_s: float = float("nan")
    distance_at_stop_m: float = float("nan")
    zero_after_s: float = float("nan")  # from the stop until PX4 below 0.15 m/s
    travel_after_stop_m: float = float("nan")
    min_distance_after_stop_m: float = float("nan")
    hold_after_s: float = float("nan")  # from the stop until PX4 reported Hold (its CP's TIMEOUT_HOLD: 5 s)

    @property
    def passed(self) -> bool:
        """Stopped within 1 m of ``CP_DIST`` (never nearer than half of it); after the service's stop,
        zero velocity (PX4's Hold) within 6.5 s, never nearer to the wall than half of ``CP_DIST``.

        What PX4 (main, 2026-03) does when the data stops: 0.5 s after the last OBSTACLE_DISTANCE its
        Collision Prevention zeroes the *acceleration* setpoint (Position mode's default, acceleration
        based, ``MPC_POS_MODE`` 4), so the vehicle coasts; after 5 s (``TIMEOUT_HOLD_US``) it commands
        Loiter (Hold): zero velocity."""
        return (
            abs(self.stop_distance_m - self.cp_dist_m) <= 1.0
            and self.stop_distance_m >= 0.5 * self.cp_dist_m
            and self.zero_after_s <= 6.5
            and self.min_distance_after_stop_m >= 0.5 * self.cp_dist_m
        )

    def lines(self) -> list[str]:
        return [
            f"CP_DIST {self.cp_dist_m:g} m; wall {self.wall_m:.1f} m ahead; stick full forward in Position mode",
            f"stopped:       {self.stop_distance_m:.2f} m from the wall at the nearest, {self.settled_distance_m:.2f} m "
            f"standing (CP_DIST {self.cp_dist_m:g} m: {self.stop_distance_m - self.cp_dist_m:+.2f} m); max speed "
            f"{self.max_speed_m_s:.2f} m/s; {self.obstacle_messages} OBSTACLE_DISTANCE sent",
            f"service stop:  at {self.speed_at_stop_m_s:.2f} m/s, {self.distance_at_stop_m:.2f} m from the wall; PX4 below "
            f"0.15 m/s {self.zero_after_s:.2f} s later after {self.travel_after_stop_m:.2f} m (Hold after "
            f"{self.hold_after_s:.2f} s); nearest afterwards {self.min_distance_after_stop_m:.2f} m",
        ]


async def _start_service(cfg: CompanionConfig, course: Course, pilot: Pilot, ports: Px4Ports, workdir: Path,
                         log_level: str) -> tuple[ServiceProcess, Any]:
    service_cfg = sitl_config(cfg, course, placement_at(pilot, course), ports.service_url, workdir, ports.system_id)
    service = ServiceProcess(service_cfg, workdir, log_level)
    placement = await start_and_place(service, pilot, course)
    return service, placement


async def fly_collision_prevention(
    cfg: CompanionConfig,
    pilot: StickPilot,
    ports: Px4Ports,
    workdir: Path,
    *,
    cp_dist_m: float = 2.0,
    manual_speed_m_s: float = 3.0,
    seed: int = 0,
    service_log_level: str = "INFO",
) -> CollisionPreventionResult:
    """The collision-prevention flight (module doc). PX4 must be running, ``pilot`` connected.

    Raises:
        SitlError: a step failed (named).
    """
    course = make_course("wall", seed)
    wall_m = float(course.goal_north_m - 2.0)
    cfg = cfg.model_copy(update={"obstacle_distance": cfg.obstacle_distance.model_copy(update={"send": "always"})})
    await pilot.make_ready()
    # CP_GUIDE_ANG 0: stop in front of the wall; PX4's default (30 deg) slides the vehicle along it
    # towards a free direction, which the first flight did, round the wall's end.
    await pilot.set_params(
        {**SITL_PARAMS, "CP_DIST": float(cp_dist_m), "CP_GUIDE_ANG": 0.0, "MPC_VEL_MANUAL": float(manual_speed_m_s)}
    )
    await pilot.take_off(-float(course.start.position_ned_m[2]))
    service, placement = await _start_service(cfg, course, pilot, ports, workdir, service_log_level)
    def wall_distance(s: Any) -> float:
        """The vehicle's centre (PX4's own position) to the wall's true front face, metres (the wall is
        30 m wide and flat; the ground is nearer than the wall until the last metre or so, so the
        course's nearest-surface field is not what is wanted here)."""
        return wall_m - float(placement.position_in_course(s.position_ned_m)[0])

    stopped = False
    try:
        await pilot.position_mode()
        await pilot.wait_for("Position mode", lambda: pilot.flight_mode == "POSCTL", 10.0)
        await asyncio.sleep(1.0)
        # Phase 1: stick full forward until PX4 holds the vehicle still.
        pilot.sticks[0] = 1.0
        nearest, max_speed, settled = await _push_until_at_rest(pilot, wall_distance, cfg.sim.collision_radius_m, "collision prevention")
        sent = int(((service.health or {}).get("mavlink") or {}).get("obstacle_distance_sent", 0))
        result = CollisionPreventionResult(cp_dist_m, wall_m, nearest, settled, max_speed, sent)
        # Phase 2: back off, push forward again, and stop the service while flying at the wall. Backing
        # off happens in Altitude mode: in Position mode Collision Prevention (CP_GO_NO_DATA 0) allows
        # no motion towards where the camera does not look, backwards included.
        pilot.sticks[0] = 0.0
        await pilot.altitude_mode()
        await pilot.wait_for("Altitude mode", lambda: pilot.flight_mode == "ALTCTL", 5.0)
        pilot.sticks[0] = -0.5
        await pilot.wait_for("backed off", lambda: wall_distance(pilot.latest()) > cp_dist_m + 4.0, 15.0)
        pilot.sticks[0] = 0.0
        await pilot.position_mode()
        await pilot.wait_for("Position mode again", lambda: pilot.flight_mode == "POSCTL", 5.0)
        await pilot.wait_steady(1.0)
        pilot.sticks[0] = 1.0
        await pilot.wait_for("speed towards the wall", lambda: _speed(pilot.latest()) > 0.6 * manual_speed_m_s
                             or wall_distance(pilot.latest()) < cp_dist_m + 1.5, 10.0)
        s_stop = pilot.latest()
        t_stop = pilot._clock()
        result.speed_at_stop_m_s, result.distance_at_stop_m = _speed(s_stop), wall_distance(s_stop)
        stopped = True
        modes_from = len(pilot.mode_changes)
        await service.stop()
        await asyncio.sleep(8.0)
        holds = [t for t, m in pilot.mode_changes[modes_from:] if m == "HOLD"]
        result.hold_after_s = (holds[0] - t_stop) if holds else math.inf
        after = pilot.samples_since(t_stop)
        dists = [wall_distance(s) for s in after]
        result.min_distance_after_stop_m = min(dists)
        result.travel_after_stop_m = float(np.linalg.norm(after[-1].position_ned_m[:2] - s_stop.position_ned_m[:2]))
        slow = [s.time_s for s in after if s.time_s > t_stop + 0.3 and _speed(s) < 0.15]
        result.zero_after_s = (slow[0] - t_stop) if slow else math.inf
        pilot.sticks[0] = 0.0
        await pilot.hold()
        await pilot.land()
        return result
    finally:
        pilot.sticks[0] = 0.0
        if not stopped:
            await service.stop()


@dataclass
class RcEngageResult:
    """What the RC-switch engage flight measured."""

    course: str
    ready_s: float  # from the service start until it streamed for the switch (health)
    engaged_after_s: float  # from the pilot's DO_SET_MODE (Offboard) to the service's "engaged"
    outcome: str
    min_clearance_m: float
    engaged_for_s: float
    released_after_s: float  # from the pilot's Position-mode request to the service's "disengaged"
    px4_offboard_after_s: float = float("nan")  # from the pilot's Offboard request to PX4 reporting it (the pilot's link)
    px4_position_after_s: float = float("nan")  # from the Position-mode request to PX4 reporting it
    modes_after_release: tuple[str, ...] = field(default=())
    status_texts: tuple[str, ...] = field(default=())

    @property
    def passed(self) -> bool:
        """Engaged within 1.5 s of the switch, no collision, let go within 1.5 s, and PX4 left in Position
        mode. (PX4 follows the pilot's switch at once; the service sees a mode only in PX4's heartbeat,
        1 Hz on the API link, hence up to a second before it knows.)"""
        return (
            self.engaged_after_s <= 1.5
            and self.outcome != Outcome.COLLISION.value
            and self.released_after_s <= 1.5
            and all(m == "POSCTL" for m in self.modes_after_release)
        )

    def lines(self) -> list[str]:
        return [
            f"course:        {self.course}; engage_on_offboard_switch on",
            f"switch:        Offboard from the ground station: PX4 in OFFBOARD {self.px4_offboard_after_s:.2f} s later "
            f"(the ground station's view), the service engaged {self.engaged_after_s:.2f} s later",
            f"flight:        {self.outcome}, min clearance {self.min_clearance_m:.2f} m over {self.engaged_for_s:.1f} s",
            f"release:       Position mode: PX4 in POSCTL {self.px4_position_after_s:.2f} s later, the service let go "
            f"{self.released_after_s:.2f} s later; PX4 modes "
            f"afterwards: {', '.join(self.modes_after_release) or 'none'}",
        ]


async def fly_rc_engage(
    cfg: CompanionConfig,
    pilot: StickPilot,
    ports: Px4Ports,
    workdir: Path,
    *,
    course_kind: str = "head-on",
    seed: int = 0,
    fly_s: float = 30.0,
    service_log_level: str = "INFO",
) -> RcEngageResult:
    """The RC-switch engage flight (module doc). PX4 must be running, ``pilot`` connected.

    Raises:
        SitlError: a step failed (named).
    """
    course = make_course(course_kind, seed)
    cfg = cfg.model_copy(update={"vehicle": cfg.vehicle.model_copy(update={"engage_on_offboard_switch": True})})
    await pilot.make_ready()
    await pilot.set_params(SITL_PARAMS)
    await pilot.take_off(-float(course.start.position_ned_m[2]))
    t_start = pilot._clock()
    service, placement = await _start_service(cfg, course, pilot, ports, workdir, service_log_level)
    try:
        await pilot.wait_for("the service ready for the switch", lambda: bool((service.health or {}).get("offboard_switch_ready")), 10.0)
        ready_s = pilot._clock() - t_start
        t_switch = pilot._clock()
        result = await pilot.set_px4_mode(_PX4_MAIN_OFFBOARD)
        if result != 0:
            raise SitlError(f"PX4 refused Offboard from the ground station (MAV_RESULT {result}) although the service streamed")
        t_px4_offboard = await pilot.wait_for("OFFBOARD", lambda: pilot.in_offboard, 5.0)
        t_engaged = await pilot.wait_for("the service engaged", lambda: service.state == "engaged", 5.0)
        recorder = _Recorder(course, cfg, placement, pilot.latest())
        seen = len(pilot.samples)
        outcome: Outcome | None = None
        while outcome is None and pilot._clock() - t_engaged < fly_s:
            await asyncio.sleep(0.05)
            fresh = pilot.samples[seen:]
            seen += len(fresh)
            for s in fresh:
                outcome = recorder.add(s, service.health)
                if outcome is not None:
                    break
        if outcome in (Outcome.COLLISION, Outcome.OUT_OF_BOUNDS):
            await pilot.hold()
        engaged_for = pilot._clock() - t_engaged
        modes_from = len(pilot.mode_changes)
        t_pos = await pilot.position_mode()
        t_px4_pos = await pilot.wait_for("Position mode", lambda: pilot.flight_mode == "POSCTL", 5.0)
        t_released = await pilot.wait_for(
            "the service let go", lambda: service.state in ("disengaged", "passive"), 5.0
        )
        await asyncio.sleep(3.0)  # nothing may take it back
        modes = tuple(m for _, m in pilot.mode_changes[modes_from:])
        texts = tuple(str(h.get("mavlink", {}).get("last_status_text")) for _, h in service.health_history[-1:])
        judge = recorder.judge
        res = RcEngageResult(
            course=course.name,
            ready_s=ready_s,
            engaged_after_s=t_engaged - t_switch,
            outcome=judge.outcome.value if judge.outcome is not None else f"still flying after {fly_s:g} s",
            min_clearance_m=judge.min_clearance_m,
            engaged_for_s=engaged_for,
            released_after_s=t_released - t_pos,
            px4_offboard_after_s=t_px4_offboard - t_switch,
            px4_position_after_s=t_px4_pos - t_pos,
            modes_after_release=modes,
            status_texts=texts,
        )
        await pilot.hold()
        await pilot.land()
        return res
    finally:
        await service.stop()


#: ArduCopter's parameters for the proximity flight, loaded at boot (``PRX1_TYPE`` takes effect only
#: then): the MAVLink proximity sensor, simple avoidance from it alone (no fence), stop (not slide) at a
#: 2 m margin, LOITER at most 3 m/s (PX4's scenario flies ``MPC_VEL_MANUAL`` 3 m/s).
PROXIMITY_BOOT_PARAMS: dict[str, float] = {
    "PRX1_TYPE": 2, "AVOID_ENABLE": 2, "AVOID_BEHAVE": 1, "AVOID_MARGIN": 2.0, "LOIT_SPEED": 300,
}  # fmt: skip
_MSG_DISTANCE_SENSOR = 132
_ORIENT_FORWARD = 0


@dataclass
class ProximityResult:
    """What the ArduPilot proximity flight measured (distances to the wall's true surface, metres)."""

    margin_m: float  # AVOID_MARGIN
    wall_m: float  # the wall's front face, north of the start
    stop_distance_m: float  # nearest the vehicle came to the wall while the service fed ArduPilot
    settled_distance_m: float  # where it stood still, stick still forward
    max_speed_m_s: float
    obstacle_messages: int  # OBSTACLE_DISTANCE the service sent (its health)
    ardupilot_ahead_m: float  # ArduPilot's own forward proximity reading (DISTANCE_SENSOR, orientation 0) while standing, median
    # After the service stopped (SIGTERM) with the vehicle standing at the margin, stick still forward:
    moved_after_s: float = float("nan")  # until it had moved 0.3 m towards the wall (inf: never within 8 s)
    min_distance_after_stop_m: float = float("nan")
    reached_wall_after_s: float = float("nan")  # until within the collision radius of the wall (inf: never)

    @property
    def passed(self) -> bool:
        """ArduPilot's simple avoidance, fed only by the service, stopped the vehicle short of the wall
        (never nearer than half the margin, at rest within 1 m of it) and its own forward reading agrees
        with the true distance within 0.5 m. What happens after the service stops is measured, not
        judged: the proximity library forgets the data 0.5 s after the last message, and the vehicle is
        then free to fly on (docs/ardupilot.md)."""
        return (
            self.stop_distance_m >= 0.5 * self.margin_m
            and abs(self.settled_distance_m - self.margin_m) <= 1.0
            and abs(self.ardupilot_ahead_m - self.settled_distance_m) <= 0.5
        )

    def lines(self) -> list[str]:
        after = (
            f"moved 0.3 m towards the wall {self.moved_after_s:.2f} s later; at the wall "
            f"{self.reached_wall_after_s:.2f} s later; nearest {self.min_distance_after_stop_m:.2f} m"
        )
        return [
            f"AVOID_MARGIN {self.margin_m:g} m (AVOID_BEHAVE stop); wall {self.wall_m:.1f} m ahead; pitch stick full forward in LOITER",
            f"stopped:       {self.stop_distance_m:.2f} m from the wall at the nearest, {self.settled_distance_m:.2f} m "
            f"standing (margin {self.margin_m:g} m: {self.settled_distance_m - self.margin_m:+.2f} m); max speed "
            f"{self.max_speed_m_s:.2f} m/s; {self.obstacle_messages} OBSTACLE_DISTANCE sent",
            f"ArduPilot:     its forward proximity reading {self.ardupilot_ahead_m:.2f} m while standing",
            f"service stop:  standing, stick forward: {after}",
        ]


async def fly_ardupilot_proximity(
    cfg: CompanionConfig,
    pilot: Any,
    ports: Any,
    workdir: Path,
    *,
    seed: int = 0,
    service_log_level: str = "INFO",
) -> ProximityResult:
    """ArduPilot's proximity library fed by the service: ArduCopter in LOITER, the pilot's pitch stick
    full forward at the ``wall`` course's wall, the service only sending OBSTACLE_DISTANCE (never
    engaged). ArduCopter must run with :data:`PROXIMITY_BOOT_PARAMS`; ``pilot`` an
    :class:`~companion.sitl.ardupilot.ArduPilotPilot` with SITL's RC port.

    Raises:
        SitlError: a step failed (named), or ArduPilot reported no proximity data.
    """
    course = make_course("wall", seed)
    wall_m = float(course.goal_north_m - 2.0)
    margin_m = float(PROXIMITY_BOOT_PARAMS["AVOID_MARGIN"])
    cfg = cfg.model_copy(update={"obstacle_distance": cfg.obstacle_distance.model_copy(update={"send": "always"})})
    throttle = CENTRED_STICKS_US[2]
    await pilot.make_ready()
    await pilot.set_params(PARAMS_BY_AUTOPILOT["ardupilot"])
    # ArduCopter with a proximity sensor refuses to arm without its data ("PRX1: No Data"): the service
    # runs from the ground, as on a vehicle, and the course is moved under the vehicle once it hovers.
    service = ServiceProcess(
        sitl_config(cfg, course, placement_at(pilot, course), ports.service_url, workdir, ports.system_id),
        workdir,
        service_log_level,
    )
    await service.start()
    readings: list[tuple[float, float]] = []

    async def watch_proximity() -> None:
        async for msg in pilot.direct.subscribe_message("DISTANCE_SENSOR"):
            fields = json.loads(msg.fields_json)
            if msg.system_id == pilot.system_id and int(fields.get("orientation", -1)) == _ORIENT_FORWARD:
                readings.append((pilot._clock(), float(fields["current_distance"]) / 100.0))

    watcher = asyncio.get_running_loop().create_task(watch_proximity())
    stopped = False
    try:
        await pilot.take_off(-float(course.start.position_ned_m[2]))  # ends in LOITER, sticks centred
        placement = await place_course(service, pilot, course)

        def wall_distance(s: Any) -> float:
            return wall_m - float(placement.position_in_course(s.position_ned_m)[0])

        result = await pilot.request_rate(_MSG_DISTANCE_SENSOR, 10.0)
        if result != 0:
            raise SitlError(f"ArduPilot refused to stream DISTANCE_SENSOR (MAV_RESULT {result})")
        await pilot.wait_for(
            "ArduPilot's proximity reading ahead (is PRX1_TYPE 2 set at boot?)", lambda: bool(readings), 10.0
        )
        # Phase 1: pitch stick full forward until ArduPilot holds the vehicle still.
        pilot.sticks(throttle, pitch_us=PITCH_FORWARD_US)
        nearest, max_speed, settled = await _push_until_at_rest(pilot, wall_distance, cfg.sim.collision_radius_m, "simple avoidance")
        t_now = pilot._clock()
        ahead = [d for t, d in readings if t >= t_now - 2.0]
        if not ahead:
            raise SitlError("ArduPilot's proximity readings stopped while the service ran")
        sent = int(((service.health or {}).get("mavlink") or {}).get("obstacle_distance_sent", 0))
        res = ProximityResult(margin_m, wall_m, nearest, settled, max_speed, sent, float(np.median(ahead)))
        # Phase 2: the service stops while the vehicle stands at the margin, stick still forward.
        s_stop = pilot.latest()
        d_stop = wall_distance(s_stop)
        t_stop = pilot._clock()
        stopped = True
        await service.stop()
        moved = reached = math.inf
        nearest_after = d_stop
        while pilot._clock() - t_stop < 8.0:
            await asyncio.sleep(0.05)
            d = wall_distance(pilot.latest())
            nearest_after = min(nearest_after, d)
            if math.isinf(moved) and d < d_stop - 0.3:
                moved = pilot._clock() - t_stop
            if d < cfg.sim.collision_radius_m:
                reached = pilot._clock() - t_stop
                break
        pilot.sticks(throttle)  # the pilot lets go of the stick
        res.moved_after_s, res.reached_wall_after_s, res.min_distance_after_stop_m = moved, reached, nearest_after
        await pilot.wait_steady(1.0)
        await pilot.land()
        return res
    finally:
        pilot.sticks(throttle)
        watcher.cancel()
        try:
            await watcher
        except (asyncio.CancelledError, Exception):  # noqa: BLE001 - ending the subscription, whatever it raised
            pass
        if not stopped:
            await service.stop()


async def run_scenario(
    name: str,
    cfg: CompanionConfig,
    *,
    ports: Px4Ports,
    pilot_url: str,
    workdir: Path,
    px4_build: Path | None = None,
    service_log_level: str = "INFO",
    **kw: Any,
) -> Any:
    """Fly scenario ``name`` (:data:`SCENARIOS`), starting PX4 from ``px4_build`` when given."""
    if name not in SCENARIOS:
        raise SitlError(f"unknown scenario {name!r}; scenarios are {', '.join(SCENARIOS)}")
    if name == "proximity":
        return await _run_ardupilot_proximity(cfg, ports=ports, pilot_url=pilot_url, workdir=workdir,
                                              service_log_level=service_log_level, **kw)
    sitl = Px4Sitl(px4_build, workdir / "px4", ports.instance) if px4_build is not None else None
    if name == "step-response":
        from companion.sitl.step_response import OffboardPilot, fly_step_response

        step_pilot = OffboardPilot(pilot_url, ports.system_id)
        try:
            if sitl is not None:
                await asyncio.to_thread(sitl.start)
            await step_pilot.connect()
            return await fly_step_response(step_pilot, workdir)
        finally:
            await step_pilot.close()
            if sitl is not None:
                await asyncio.to_thread(sitl.stop)
    pilot = StickPilot(pilot_url, ports.system_id)
    try:
        if sitl is not None:
            await asyncio.to_thread(sitl.start)
        await pilot.connect()
        fly = fly_collision_prevention if name == "collision-prevention" else fly_rc_engage
        return await fly(cfg, pilot, ports, workdir / "service", service_log_level=service_log_level, **kw)
    finally:
        await pilot.close()
        if sitl is not None:
            await asyncio.to_thread(sitl.stop)


async def _run_ardupilot_proximity(
    cfg: CompanionConfig,
    *,
    ports: Any,
    pilot_url: str,
    workdir: Path,
    ardupilot_build: Any = None,
    service_log_level: str = "INFO",
    **kw: Any,
) -> ProximityResult:
    """The proximity scenario, starting ArduCopter SITL from ``ardupilot_build`` (with
    :data:`PROXIMITY_BOOT_PARAMS`) when given; else one must be running with them."""
    sitl = (
        ArduPilotSitl(ardupilot_build, workdir / "ardupilot", ports.instance, boot_params=PROXIMITY_BOOT_PARAMS)
        if ardupilot_build is not None
        else None
    )
    pilot = ArduPilotPilot(pilot_url, ports.system_id, rc_port=ports.rc_port)
    try:
        if sitl is not None:
            await asyncio.to_thread(sitl.start)
        await pilot.connect(60.0)
        return await fly_ardupilot_proximity(cfg, pilot, ports, workdir / "service", service_log_level=service_log_level, **kw)
    finally:
        await pilot.close()
        if sitl is not None:
            await asyncio.to_thread(sitl.stop)
