"""The service against real ArduCopter SITL (its built-in quad model): GUIDED, avoidance and every
failsafe, measured on ArduPilot's own telemetry and on the wire.

How they find ArduPilot: ``COMPANION_ARDUPILOT_BUILD`` names an ArduPilot checkout with a SITL build
(``./waf configure --board sitl && ./waf copter``; docs/sitl-ardupilot.md). The tests start their own
instance (number 4: the ground station on TCP 5800, ArduPilot's SERIAL1 on TCP 5802) and stop it at the
end. The service reaches SERIAL1 through a MAVLink gate (tests/peers/mavlink_gate.py) that records every
setpoint and mode command it sends, with the time, and can stop its position telemetry (its camera
renders from that pose, so frames stop as from an unplugged camera). Without the variable every test
here is skipped, saying so.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import numpy as np
import pytest
from peers.mavlink_gate import MSG_LOCAL_POSITION_NED, MavlinkGate

from companion.config import load_config
from companion.sim.courses import head_on_course
from companion.sitl.ardupilot import (
    ARDUPILOT_BUILD_ENV,
    SITL_PARAMS,
    ArduPilotPilot,
    ArduPilotPorts,
    ArduPilotSitl,
    find_ardupilot_build,
)
from companion.sitl.flight import fly_course, prepare_flight, start_and_place

pytestmark = pytest.mark.sitl

INSTANCE = 4
_GUIDED = 4


@pytest.fixture(scope="module")
def ardupilot(tmp_path_factory: pytest.TempPathFactory):
    build = find_ardupilot_build()
    if build is None:
        pytest.skip(f"no ArduPilot SITL: set {ARDUPILOT_BUILD_ENV} to an ArduPilot checkout with a SITL build (docs/sitl-ardupilot.md)")
    sitl = ArduPilotSitl(build, tmp_path_factory.mktemp("ardupilot"), instance=INSTANCE)
    sitl.start()
    yield sitl
    sitl.stop()


def _run(coro, timeout_s: float = 300.0):
    return asyncio.run(asyncio.wait_for(coro, timeout_s))


async def _pilot(sitl: ArduPilotSitl) -> ArduPilotPilot:
    pilot = ArduPilotPilot(sitl.ports.pilot_url, sitl.ports.system_id, rc_port=sitl.ports.rc_port)
    await pilot.connect(60.0)
    return pilot


async def _engaged(sitl: ArduPilotSitl, workdir: Path, box_north_m: float = 30.0):
    """Take off, start the service (through a gate) on a course with a far box, engage; returns
    (pilot, service, gate, t_guided)."""
    pilot = await _pilot(sitl)
    gate = await MavlinkGate(sitl.ports.api_port).start()
    course = head_on_course(0, box_north_m=box_north_m)
    service = await prepare_flight(course, load_config(None), pilot, sitl.ports, workdir, service_url=gate.url)
    await start_and_place(service, pilot, course)
    await service.request({"cmd": "engage"})
    t = await pilot.wait_for("GUIDED after engage", lambda: pilot.in_offboard, 10.0)
    return pilot, service, gate, t


async def _finish(pilot: ArduPilotPilot, service, gate: MavlinkGate | None = None) -> None:
    """Stop the service, land, and close the pilot's link whatever the landing does."""
    try:
        await service.stop()
        if gate is not None:
            await gate.close()
        if pilot.flight_mode == "GUIDED":
            await pilot.hold()  # the pilot takes the vehicle before landing it
        await pilot.make_ready()
    finally:
        await pilot.close()


def _speed(pilot: ArduPilotPilot) -> float:
    return float(np.linalg.norm(pilot.latest().velocity_ned_m_s[:2]))


def _newest_frame_s(service) -> float:
    """The capture time of the newest frame the service processed (its monotonic clock, which is
    this process's), from its health messages."""
    return max(h["time_s"] - h["frame_age_ms"] / 1e3 for _, h in service.health_history if h.get("frame_age_ms") is not None)


def test_guided_engages_and_arducopter_flies_the_setpoints(ardupilot: ArduPilotSitl, tmp_path: Path) -> None:
    cruise = load_config(None).planner.cruise_speed_m_s

    async def scenario() -> None:
        pilot, service, gate, t_on = await _engaged(ardupilot, tmp_path)
        try:
            await asyncio.sleep(5.0)  # the box is 30 m ahead: forward at (up to) the cruise speed
            assert pilot.flight_mode == "GUIDED" and service.state == "engaged"
            health = service.health or {}
            assert health["vehicle"]["autopilot"] == "ardupilot" and health["vehicle"]["flight_mode"] == "GUIDED"
            window = (t_on + 3.0, t_on + 5.0)
            sent = [s.vx for s in gate.setpoints if window[0] <= s.t_s <= window[1]]
            flown = [float(np.linalg.norm(s.velocity_ned_m_s[:2])) for s in pilot.samples if window[0] <= s.time_s <= window[1]]
            assert len(sent) >= 2 * 20 * 0.9  # >= 20 Hz from the service, plus MAVSDK's re-sending
            assert 0.5 * cruise <= np.median(sent) <= cruise
            # ArduCopter flies what it is sent (its own velocity estimate, median over 2 s).
            assert 0.8 * np.median(sent) < np.median(flown) < 1.2 * np.median(sent)
            modes = [int(c.params[1]) for c in gate.mode_commands_since(0.0)]
            assert modes == [_GUIDED]  # engaged by GUIDED's number, nothing else
            await service.request({"cmd": "disengage"})
            await pilot.wait_for("LOITER after disengage", lambda: pilot.flight_mode == "LOITER", 5.0)
            assert [int(c.params[1]) for c in gate.mode_commands_since(0.0)] == [_GUIDED, 5]
        finally:
            await _finish(pilot, service, gate)

    _run(scenario())


def test_a_head_on_obstacle_is_avoided_with_clearance(ardupilot: ArduPilotSitl, tmp_path: Path) -> None:
    async def scenario():
        pilot = await _pilot(ardupilot)
        try:
            return await fly_course(head_on_course(0), load_config(None), pilot, ardupilot.ports, tmp_path)
        finally:
            await pilot.close()

    flight = _run(scenario())
    r = flight.result
    print(f"head-on with ArduPilot: {r.summary()}")
    assert r.outcome.value in ("goal", "held"), r.reason
    assert r.min_clearance_m > 0.1, r.reason
    assert flight.service_exit_code == 0
    health = [json.loads(line) for line in (tmp_path / "health.jsonl").read_text().splitlines()]
    assert any(h["state"] == "engaged" and h["setpoint"] is not None for h in health)


def test_frames_stopping_give_zero_velocity_then_loiter_on_arducopter(ardupilot: ArduPilotSitl, tmp_path: Path) -> None:
    cfg = load_config(None)

    async def scenario() -> tuple[float, float, float]:
        pilot, service, gate, t_on = await _engaged(ardupilot, tmp_path)
        try:
            await pilot.wait_for("cruise", lambda: _speed(pilot) > 0.5, 8.0)
            # The camera renders from the position ArduPilot sends the service: drop it at the gate,
            # and the camera stops delivering, as an unplugged ZED would.
            gate.blocked.add(MSG_LOCAL_POSITION_NED)
            t_block = time.monotonic()
            await service.wait_state(("degraded",), 3.0)
            t_last = _newest_frame_s(service)
            t_still = await pilot.wait_for("ArduCopter stopped", lambda: _speed(pilot) < 0.15, 5.0)
            assert pilot.flight_mode == "GUIDED"  # zero velocity first, still ours
            t_loiter = await pilot.wait_for("LOITER", lambda: pilot.flight_mode == "LOITER", cfg.command.failsafe_timeout_s + 3.0)
            after = gate.setpoints_since(t_last)
            first_zero = next(i for i, s in enumerate(after) if s.is_zero and all(x.is_zero for x in after[i:]))
            modes = [int(c.params[1]) for c in gate.mode_commands_since(t_block)]
            assert modes == [5], modes  # LOITER, by its number; never BRAKE
            return after[first_zero].t_s - t_last, t_still - t_last, t_loiter - t_last
        finally:
            gate.blocked.clear()
            await _finish(pilot, service, gate)

    zero_s, still_s, loiter_s = _run(scenario())
    print(f"frames stopped (ArduPilot): zero on the wire {zero_s:.2f} s after the last frame, ArduCopter "
          f"below 0.15 m/s after {still_s:.2f} s, LOITER after {loiter_s:.2f} s")
    assert zero_s < cfg.command.stale_frame_timeout_s + 0.1  # the target: zero on the wire within 0.6 s
    assert still_s < 2.0  # the target: ArduCopter below 0.15 m/s within 2 s
    assert cfg.command.failsafe_timeout_s - 0.5 < loiter_s < cfg.command.failsafe_timeout_s + 3.0


def test_killing_the_service_lets_guid_timeout_stop_the_vehicle_in_guided(ardupilot: ArduPilotSitl, tmp_path: Path) -> None:
    """ArduCopter has no companion-loss failsafe: without setpoints it flies the last velocity for
    GUID_TIMEOUT, then brakes and hovers, in GUIDED, until the pilot takes over."""

    async def scenario() -> tuple[float, float]:
        pilot, service, gate, _ = await _engaged(ardupilot, tmp_path)
        try:
            await pilot.wait_for("cruise", lambda: _speed(pilot) > 0.5, 8.0)
            t_kill = service.kill()  # SIGKILL: MAVSDK and its 20 Hz re-sending die with it
            last_setpoint = gate.setpoints[-1].t_s
            t_still = await pilot.wait_for("ArduCopter stopped", lambda: _speed(pilot) < 0.15, 10.0)
            await asyncio.sleep(5.0)
            assert pilot.flight_mode == "GUIDED"  # still GUIDED: no failsafe of ArduPilot's fired
            assert _speed(pilot) < 0.3  # and hovering
            return t_still - t_kill, t_kill - last_setpoint
        finally:
            await _finish(pilot, service, gate)

    still_s, gap_s = _run(scenario())
    print(f"service killed (ArduPilot, GUID_TIMEOUT = {SITL_PARAMS['GUID_TIMEOUT']} s): below 0.15 m/s after "
          f"{still_s:.2f} s, hovering in GUIDED 5 s later (the last setpoint {gap_s:.2f} s before the kill)")
    assert still_s < float(SITL_PARAMS["GUID_TIMEOUT"]) + 2.0


def test_a_pilot_mode_change_disengages_the_service_for_good(ardupilot: ArduPilotSitl, tmp_path: Path) -> None:
    async def scenario() -> None:
        pilot, service, gate, _ = await _engaged(ardupilot, tmp_path)
        try:
            await pilot.wait_for("cruise", lambda: _speed(pilot) > 0.5, 8.0)
            t_pilot = time.monotonic()
            await pilot.hold()  # the pilot takes the vehicle: LOITER
            await service.wait_state(("disengaged",), 3.0)
            assert "LOITER" in (service.health or {}).get("reason", "")
            sent = (service.health or {})["setpoints_sent"]
            await asyncio.sleep(4.0)
            assert pilot.flight_mode == "LOITER"  # never taken back
            assert (service.health or {})["setpoints_sent"] == sent and service.state == "disengaged"
            assert gate.mode_commands_since(t_pilot) == []  # no mode change from the service, BRAKE least of all
            assert gate.setpoints_since(t_pilot + 1.0) == []  # MAVSDK's re-sending stopped too
        finally:
            await _finish(pilot, service, gate)

    _run(scenario())


def test_the_services_obstacle_distance_stops_arducopter_at_its_avoid_margin(tmp_path: Path) -> None:
    """``companion sitl --autopilot ardupilot --scenario proximity``: its own SITL (instance 5, booted with
    ``PRX1_TYPE`` 2), LOITER, the pitch stick full forward at a wall, the service only feeding
    OBSTACLE_DISTANCE: ArduCopter stops the vehicle about ``AVOID_MARGIN`` short, and its own forward
    reading agrees with the true distance."""
    from companion.sitl.scenarios import run_scenario

    build = find_ardupilot_build()
    if build is None:
        pytest.skip(f"no ArduPilot SITL: set {ARDUPILOT_BUILD_ENV} (docs/sitl-ardupilot.md)")
    ports = ArduPilotPorts(5)
    result = _run(
        run_scenario("proximity", load_config(None), ports=ports, pilot_url=ports.pilot_url, workdir=tmp_path, ardupilot_build=build),
        400.0,
    )
    print("\n".join(result.lines()))
    assert result.obstacle_messages > 50
    assert result.passed, result.lines()
