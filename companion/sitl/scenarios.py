"""The ground-station scenarios with PX4 or ArduPilot SITL in the loop (``companion sitl --scenario ...``):
:func:`run_scenario` starts the autopilot and the ground station's pilot and flies one.

* **collision-prevention** (PX4): PX4's own Collision Prevention, fed only by the service's
  OBSTACLE_DISTANCE, must stop a pilot flying at a wall (:mod:`companion.sitl.px4_scenarios`).
* **rc-engage** (PX4): the ground station's switch to Offboard engages the service, and its switch back
  to Position mode hands the vehicle back (:mod:`companion.sitl.px4_scenarios`).
* **proximity** (ArduPilot): ArduCopter's proximity library, fed only by the service, must stop a pilot
  flying at a wall (:mod:`companion.sitl.proximity`).
* **step-response** (PX4): the ground station flies offboard itself and steps its velocity and yaw-rate
  setpoints; the simulator's vehicle model is fitted to PX4's response
  (:mod:`companion.sitl.step_response`).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig
from companion.sitl.ardupilot import ArduPilotPilot, ArduPilotSitl
from companion.sitl.proximity import PROXIMITY_BOOT_PARAMS, ProximityResult, fly_ardupilot_proximity
from companion.sitl.px4 import Px4Ports, Px4Sitl, SitlError
from companion.sitl.px4_scenarios import fly_collision_prevention, fly_rc_engage
from companion.sitl.sticks import StickPilot

SCENARIOS: tuple[str, ...] = ("collision-prevention", "rc-engage", "proximity", "step-response")


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
