"""ArduPilot's proximity scenario (``companion sitl --scenario proximity``).

* **proximity** (ArduPilot): the same wall, ArduCopter in LOITER with its proximity library fed only by
  the service's OBSTACLE_DISTANCE (``PRX1_TYPE`` 2, simple avoidance stopping at ``AVOID_MARGIN``); the
  pilot's pitch stick full forward. ArduCopter must stop the vehicle about the margin short of the wall.
  Then the service stops while the vehicle stands there, stick still forward: what ArduCopter does is
  measured (its proximity data expires 0.5 s after the last message).
"""

from __future__ import annotations

import asyncio
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import CompanionConfig
from companion.sim.courses import make_course
from companion.sitl.ardupilot import CENTRED_STICKS_US, PITCH_FORWARD_US
from companion.sitl.flight import PARAMS_BY_AUTOPILOT, place_course, placement_at, sitl_config
from companion.sitl.px4 import SitlError
from companion.sitl.service import ServiceProcess
from companion.sitl.sticks import push_until_at_rest


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
        nearest, max_speed, settled = await push_until_at_rest(pilot, wall_distance, cfg.sim.collision_radius_m, "simple avoidance")
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
