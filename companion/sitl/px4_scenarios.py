"""PX4's scenarios with a ground-station pilot on the sticks (``companion sitl --scenario ...``).

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
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import CompanionConfig
from companion.sim.courses import Course, make_course
from companion.sim.scoring import Outcome
from companion.sitl.flight import SITL_PARAMS, _Recorder, placement_at, sitl_config, start_and_place
from companion.sitl.pilot import Pilot
from companion.sitl.px4 import Px4Ports, SitlError
from companion.sitl.service import ServiceProcess
from companion.sitl.sticks import PX4_MAIN_OFFBOARD, StickPilot, horizontal_speed, push_until_at_rest


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
        nearest, max_speed, settled = await push_until_at_rest(pilot, wall_distance, cfg.sim.collision_radius_m, "collision prevention")
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
        await pilot.wait_for("speed towards the wall", lambda: horizontal_speed(pilot.latest()) > 0.6 * manual_speed_m_s
                             or wall_distance(pilot.latest()) < cp_dist_m + 1.5, 10.0)
        s_stop = pilot.latest()
        t_stop = pilot._clock()
        result.speed_at_stop_m_s, result.distance_at_stop_m = horizontal_speed(s_stop), wall_distance(s_stop)
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
        slow = [s.time_s for s in after if s.time_s > t_stop + 0.3 and horizontal_speed(s) < 0.15]
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
        result = await pilot.set_px4_mode(PX4_MAIN_OFFBOARD)
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
