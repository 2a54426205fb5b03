"""The ArduPilot link on the wire: the real MAVSDK link (in-process) against an ArduCopter-like
pymavlink peer over UDP on localhost (its mode numbers, its telemetry only when asked, GUIDED).
Assertions are on what the autopilot receives."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import pytest
from mavlink_peer import COPTER_MODES, ArduCopterPeer, Px4Peer
from peers.fakes import Client, GatedCamera, ServiceRunner, avoid_scene_camera, service_config, wait_until
from pymavlink.dialects.v20 import common as mavlink

from companion import exitcodes
from companion.errors import VehicleError
from companion.service.ardupilot import BRAKE, LOITER, ArduPilotVehicleLink, copter_mode_name
from companion.service.daemon import Service, keep_restart_fields, restart_required
from companion.service.vehicle import MavsdkVehicleLink, make_vehicle_link

BODY_NED = mavlink.MAV_FRAME_BODY_NED
VELOCITY_YAWRATE_MASK = 0x05C7  # ignore position, acceleration, yaw: ArduCopter flies body velocity + yaw rate


def _status(client: Client) -> dict:
    return client.call("status")["result"]


def _vehicle_ready(client: Client) -> bool:
    v = _status(client)["vehicle"]
    return v["link"] == "connected" and v["armed"] and v["flight_mode"] != "UNKNOWN" and v["position_ned_m"] is not None


def _start(tmp_path: Path, peer: ArduCopterPeer, camera=None, **sections) -> tuple[Service, ServiceRunner, Client]:
    vehicle = {"connection": f"udpin://127.0.0.1:{peer.port}", "connect_timeout_s": 5.0, **sections.pop("vehicle", {})}
    cfg = service_config(tmp_path, vehicle=vehicle, **sections)
    service = Service(cfg, camera=camera or avoid_scene_camera(15.0), install_signals=False, environ={})  # link from the config
    runner = ServiceRunner(service).start()
    client = Client(service.bus.control_endpoint, service.bus.health_endpoint)
    return service, runner, client


@pytest.fixture()
def flying(tmp_path: Path):
    """An ArduCopter-like peer hovering in LOITER, armed; the service (vehicle.autopilot "auto") with
    a freezable camera."""
    peer = ArduCopterPeer(mode="LOITER").start()
    camera = GatedCamera(avoid_scene_camera(15.0))
    service, runner, client = _start(tmp_path, peer, camera, command={"failsafe_timeout_s": 1.5})
    try:
        assert wait_until(lambda: _vehicle_ready(client), 10.0), _status(client)["vehicle"]
        yield peer, service, camera, client
    finally:
        client.close()
        runner.stop()
        peer.stop()


def _engage(peer: ArduCopterPeer, client: Client) -> float:
    t0 = time.monotonic()
    reply = client.call("engage")
    assert reply["ok"], reply
    assert peer.wait_for(lambda: peer.mode == "GUIDED", 5.0), peer.commands
    assert wait_until(lambda: _status(client)["state"] == "engaged", 3.0), _status(client)["reason"]
    return t0


def _mode_names(peer: ArduCopterPeer) -> list[str | None]:
    return [c.mode for c in peer.mode_commands()]


def test_the_link_asks_for_telemetry_and_names_arducopters_modes(flying) -> None:
    peer, service, camera, client = flying
    # ArduCopter streams nothing unasked: position/velocity and attitude at vehicle.telemetry_rate_hz.
    assert peer.wait_for(lambda: 193 in {m for _, m, _ in peer.interval_requests}, 3.0)
    asked = {msg_id: interval_us for _, msg_id, interval_us in peer.interval_requests}
    assert asked[mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED] == pytest.approx(1e6 / 30.0, rel=1e-3)
    assert asked[mavlink.MAVLINK_MSG_ID_ATTITUDE] == pytest.approx(1e6 / 30.0, rel=1e-3)
    assert asked[193] == pytest.approx(5e5)  # EKF_STATUS_REPORT at 2 Hz: is there a position estimate?
    v = _status(client)["vehicle"]
    assert v["autopilot"] == "ardupilot" and v["flight_mode"] == "LOITER" and not v["in_offboard"]
    # By ArduCopter's own numbers, where MAVSDK would say HOLD for both LOITER and BRAKE.
    peer.set_mode("BRAKE")
    assert wait_until(lambda: _status(client)["vehicle"]["flight_mode"] == "BRAKE", 3.0)
    peer.set_mode("POSHOLD")
    assert wait_until(lambda: _status(client)["vehicle"]["flight_mode"] == "POSHOLD", 3.0)
    assert peer.setpoints == [] and peer.mode_commands() == []  # passive: nothing sent


def test_guided_setpoints_stale_zero_failsafe_loiter_and_pilot_takeover(flying) -> None:
    peer, service, camera, client = flying
    cfg = service.config

    # Engage: zero setpoints first, then GUIDED by its number (DO_SET_MODE, custom mode 4).
    t_engage = _engage(peer, client)
    guided = peer.mode_commands()[0]
    assert guided.mode == "GUIDED" and guided.result == mavlink.MAV_RESULT_ACCEPTED
    assert int(guided.params[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and int(guided.params[1]) == 4
    before = [s for s in peer.setpoints if s.t_s < guided.t_s]
    assert before and all(s.is_zero for s in before) and before[0].t_s >= t_engage

    # Engaged: body velocity + yaw rate, the mask ArduCopter flies (0x05C7) (the stream's rate, 20 Hz,
    # is a figure of `companion bench`; on a loaded machine the scheduler sets it).
    assert peer.wait_for(lambda: any(not s.is_zero for s in peer.setpoints_since(guided.t_s)), 5.0)
    t0 = time.monotonic()
    assert peer.wait_for(lambda: len(peer.setpoints_since(t0)) >= 20, 30.0)
    window = peer.setpoints_since(t0)[:20]
    for s in window:
        assert s.frame == BODY_NED and s.type_mask == VELOCITY_YAWRATE_MASK and s.mode == "GUIDED"
        assert math.hypot(s.vx, s.vy) <= cfg.envelope.max_horizontal_speed_m_s + 1e-6
        assert abs(math.degrees(s.yaw_rate)) <= cfg.envelope.max_yaw_rate_deg_s + 1e-6
    assert any(not s.is_zero for s in window)

    # Frames stop: zero velocity once the last frame is stale (command.stale_frame_timeout_s), give or
    # take a few control periods (a loaded 2-core CI machine once took 0.6 s against the 0.5 s timeout;
    # the latency itself is a benchmark's business).
    deadline_s = cfg.command.stale_frame_timeout_s + 0.25
    camera.freeze()
    t_freeze = time.monotonic()
    assert wait_until(lambda: _status(client)["state"] == "degraded", 1.0), _status(client)
    assert peer.wait_for(lambda: any(s.is_zero for s in peer.setpoints_since(t_freeze)), 1.0)
    after = peer.setpoints_since(t_freeze)
    assert all(s.is_zero for s in after if s.t_s > t_freeze + deadline_s)
    assert any(s.is_zero for s in after if s.t_s <= t_freeze + deadline_s)
    assert peer.mode == "GUIDED"

    # Failsafe (1.5 s here): LOITER by its number, never BRAKE; then the stream stops.
    assert peer.wait_for(lambda: peer.mode == "LOITER", 2.0)
    hold = peer.mode_commands()[-1]
    assert hold.mode == "LOITER" and int(hold.params[1]) == 5 and 1.2 < hold.t_s - t_freeze < 2.3
    assert [s for s in peer.setpoints if s.t_s <= hold.t_s][-1].is_zero
    assert wait_until(lambda: _status(client)["state"] == "failsafe", 1.0)
    time.sleep(0.5)
    t_quiet = time.monotonic()
    time.sleep(0.7)
    assert peer.setpoints_since(t_quiet) == []

    # An explicit engage; then the pilot switches to BRAKE (MAVSDK would call it HOLD, as LOITER).
    camera.thaw()
    assert wait_until(lambda: _status(client)["frame_age_ms"] < 300.0, 3.0)
    _engage(peer, client)
    n_cmds = len(peer.mode_commands())
    time.sleep(0.5)
    peer.set_mode("BRAKE", "pilot")
    t_pilot = time.monotonic()
    assert wait_until(lambda: _status(client)["state"] == "disengaged", 2.0)
    status = _status(client)
    assert "for BRAKE" in status["reason"] and not status["engaged"]
    time.sleep(1.5)
    # Never fought: no mode change after the pilot's; the stream stopped (MAVSDK's re-sending too).
    assert len(peer.mode_commands()) == n_cmds and peer.mode == "BRAKE"
    assert peer.setpoints_since(t_pilot + 0.8) == []
    assert peer.setpoints_since(t_pilot - 5.0)[-1].is_zero
    assert "BRAKE" not in _mode_names(peer)  # the service itself never asked for BRAKE


def test_shutdown_sends_zero_then_loiter_and_stops(flying) -> None:
    peer, service, camera, client = flying
    _engage(peer, client)
    time.sleep(0.3)
    t_stop = time.monotonic()
    service.request_shutdown_threadsafe("test")
    assert service.stopped.wait(10.0)
    assert service.exit_code == exitcodes.OK
    holds = [c for c in peer.commands_since(t_stop) if c.mode is not None]
    assert [c.mode for c in holds] == ["LOITER"] and peer.mode == "LOITER"
    sent = peer.setpoints_since(t_stop)
    first_zero = next(i for i, s in enumerate(sent) if s.is_zero)
    assert sent[first_zero].t_s <= holds[0].t_s and all(s.is_zero for s in sent[first_zero:])
    time.sleep(0.3)
    assert peer.setpoints_since(holds[0].t_s + 0.3) == []


def test_shutdown_after_the_pilot_took_over_sends_no_mode_change(flying) -> None:
    peer, service, camera, client = flying
    _engage(peer, client)
    peer.set_mode("ALT_HOLD", "pilot")
    assert wait_until(lambda: _status(client)["state"] == "disengaged", 2.0)
    n = len(peer.mode_commands())
    service.request_shutdown_threadsafe("test")
    assert service.stopped.wait(10.0)
    assert len(peer.mode_commands()) == n and peer.mode == "ALT_HOLD"


def test_hold_falls_back_to_brake_when_arducopter_refuses_loiter(tmp_path: Path) -> None:
    with ArduCopterPeer(mode="LOITER", deny_modes=frozenset({"LOITER"})) as peer:
        camera = GatedCamera(avoid_scene_camera(15.0))
        service, runner, client = _start(tmp_path, peer, camera, command={"failsafe_timeout_s": 1.0})
        try:
            assert wait_until(lambda: _vehicle_ready(client), 10.0)
            _engage(peer, client)
            camera.freeze()
            assert peer.wait_for(lambda: peer.mode == "BRAKE", 4.0), peer.mode_commands()
            refused, brake = peer.mode_commands()[-2:]
            assert (refused.mode, refused.result) == ("LOITER", mavlink.MAV_RESULT_FAILED)
            assert (brake.mode, brake.result) == ("BRAKE", mavlink.MAV_RESULT_ACCEPTED)
            assert wait_until(lambda: _status(client)["state"] == "failsafe", 2.0)
        finally:
            client.close()
            runner.stop()


def test_without_a_position_estimate_hold_asks_for_brake_and_keeps_zero_when_both_are_refused(tmp_path: Path) -> None:
    """ArduCopter refuses LOITER and BRAKE without a position estimate (both ``requires_GPS``): the
    service asks for BRAKE first (its EKF status says no position), then LOITER, keeps zero velocity
    in GUIDED, and stops the stream after leave_timeout_s, so that GUID_TIMEOUT brakes the vehicle."""
    with ArduCopterPeer(mode="LOITER") as peer:
        camera = GatedCamera(avoid_scene_camera(15.0))
        service, runner, client = _start(
            tmp_path, peer, camera, command={"failsafe_timeout_s": 1.0}, vehicle={"hold_retry_s": 1.0, "leave_timeout_s": 3.0}
        )
        try:
            assert wait_until(lambda: _vehicle_ready(client), 10.0)
            _engage(peer, client)
            peer.position_ok = False  # the EKF loses its position (GPS gone) while in GUIDED
            time.sleep(1.5)  # a few EKF reports at 2 Hz
            camera.freeze()
            t_freeze = time.monotonic()
            assert wait_until(lambda: _status(client)["state"] == "failsafe", 3.0)
            assert peer.wait_for(lambda: len([c for c in peer.mode_commands() if c.t_s > t_freeze]) >= 2, 3.0)
            first, second = [c for c in peer.mode_commands() if c.t_s > t_freeze][:2]
            assert (first.mode, second.mode) == ("BRAKE", "LOITER")
            assert first.result == second.result == mavlink.MAV_RESULT_FAILED and peer.mode == "GUIDED"
            assert all(s.is_zero for s in peer.setpoints_since(first.t_s))
            # Hold never confirmed: after leave_timeout_s the stream stops (no mode change of ours took).
            assert wait_until(lambda: "setpoints stopped" in _status(client)["reason"], 5.0), _status(client)["reason"]
            time.sleep(0.5)
            t_quiet = time.monotonic()
            time.sleep(0.5)
            assert peer.setpoints_since(t_quiet) == [] and peer.mode == "GUIDED"
        finally:
            client.close()
            runner.stop()


def test_a_configured_autopilot_that_does_not_answer_is_a_startup_failure(tmp_path: Path) -> None:
    with ArduCopterPeer() as peer:
        cfg = service_config(
            tmp_path, vehicle={"connection": f"udpin://127.0.0.1:{peer.port}", "autopilot": "px4", "connect_timeout_s": 5.0}
        )
        service = Service(cfg, camera=avoid_scene_camera(15.0), install_signals=False, environ={})
        assert asyncio.run(asyncio.wait_for(service.run(), 30.0)) == exitcodes.STARTUP_FAILURE
        assert "vehicle.autopilot is 'px4'" in (service.health_message()["last_error"] or "")
        assert peer.setpoints == [] and peer.mode_commands() == []


def test_auto_finds_px4_and_ardupilot_from_the_heartbeat() -> None:
    async def found(peer) -> tuple[str, str]:
        link = MavsdkVehicleLink(f"udpin://127.0.0.1:{peer.port}")
        try:
            await link.connect(5.0)
            for _ in range(100):
                if link.state().flight_mode != "UNKNOWN":
                    break
                await asyncio.sleep(0.05)
            return type(link.link).__name__, link.state().flight_mode
        finally:
            await link.close()

    with Px4Peer(mode="POSCTL") as px4:
        assert asyncio.run(found(px4)) == ("Px4VehicleLink", "POSCTL")
    with ArduCopterPeer(mode="LOITER") as copter:
        assert asyncio.run(found(copter)) == ("ArduPilotVehicleLink", "LOITER")


def test_autopilot_is_a_restart_field_and_builds_the_right_link(tmp_path: Path) -> None:
    cfg = service_config(tmp_path)
    assert cfg.vehicle.autopilot == "auto"
    new = service_config(tmp_path, vehicle={"autopilot": "ardupilot", "telemetry_rate_hz": 20.0})
    assert restart_required(cfg, new) == ["vehicle.autopilot", "vehicle.telemetry_rate_hz"]
    kept = keep_restart_fields(cfg, new)
    assert (kept.vehicle.autopilot, kept.vehicle.telemetry_rate_hz) == ("auto", 30.0)  # until a restart
    link = make_vehicle_link(new.vehicle)
    assert (link.autopilot, link.telemetry_rate_hz) == ("ardupilot", 20.0)


def test_hold_is_loiter_with_a_position_estimate_and_brake_without() -> None:
    link = ArduPilotVehicleLink("udpin://127.0.0.1:9", clock=lambda: 100.0)
    assert link.hold_mode(100.0) == BRAKE  # no position report ever
    link._update(position_timestamp_s=99.5)
    assert link.hold_mode(100.0) == LOITER
    assert link.hold_mode(101.2) == BRAKE  # the last one older than POSITION_FRESH_S
    # ArduPilot's EKF status decides while its reports arrive, whatever the position telemetry does.
    link.note_ekf_status(True, 101.0)
    assert link.hold_mode(101.2) == LOITER  # the position telemetry stopped on this link only
    link.note_ekf_status(False, 101.5)
    assert link.hold_mode(101.6) == BRAKE
    assert link.hold_mode(104.6) == BRAKE  # the report is stale: back to the position telemetry (stale too)
    assert copter_mode_name(4) == "GUIDED" and copter_mode_name(99) == "MODE_99"
    assert {copter_mode_name(n) for n in COPTER_MODES.values()} == set(COPTER_MODES)  # the peer's numbers agree


def test_rates_are_asked_again_when_position_telemetry_stops() -> None:
    link = ArduPilotVehicleLink("udpin://127.0.0.1:9")
    assert not link.rates_due(0.0)  # not connected
    link._update(connected=True)
    assert link.rates_due(0.0)  # never asked
    link._rates_asked_s, link._rates_ok = 0.0, True
    link._update(position_timestamp_s=4.0)
    assert not link.rates_due(4.5)  # asked less than RATE_RETRY_S ago
    assert not link.rates_due(6.0)  # position is flowing
    assert link.rates_due(7.5)  # 3.5 s without position: ArduPilot rebooted or forgot the rates
    link._rates_ok = False
    assert link.rates_due(5.1)  # refused last time: again after RATE_RETRY_S


def test_the_ardupilot_link_refuses_to_engage_before_a_setpoint() -> None:
    link = ArduPilotVehicleLink("udpin://127.0.0.1:9")
    with pytest.raises(VehicleError, match="no autopilot connected"):
        asyncio.run(link.start_offboard())
    with pytest.raises(VehicleError, match="telemetry_rate_hz"):
        ArduPilotVehicleLink("udpin://127.0.0.1:9", telemetry_rate_hz=0.0)


def test_mavsdks_own_set_rate_is_refused_by_arducopter_so_the_link_sends_its_own() -> None:
    """MAVSDK's telemetry.set_rate_* leaves params 3-7 NaN; ArduPilot wants param3 0 (and ArduCopter
    SITL died of SIGFPE on it). The link's own SET_MESSAGE_INTERVAL, with zeros, is accepted."""
    from mavsdk.asyncio.plugins.telemetry import TelemetryError

    async def scenario(peer: ArduCopterPeer) -> None:
        link = MavsdkVehicleLink(f"udpin://127.0.0.1:{peer.port}")
        try:
            await link.connect(5.0)
            ardupilot = link.link
            assert isinstance(ardupilot, ArduPilotVehicleLink)
            with pytest.raises(TelemetryError):
                await ardupilot._telemetry.set_rate_battery(1.0)
            assert await ardupilot.request_telemetry_rates()
        finally:
            await link.close()

    with ArduCopterPeer() as peer:
        asyncio.run(scenario(peer))
        assert peer.intervals_s.get(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED) == pytest.approx(1 / 30.0)
        assert mavlink.MAVLINK_MSG_ID_BATTERY_STATUS not in peer.intervals_s
