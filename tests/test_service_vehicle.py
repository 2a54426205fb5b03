"""The vehicle side on the wire: the real MAVSDK link (in-process) against a PX4-like pymavlink peer
over UDP on localhost. Assertions are on what the autopilot receives."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import pytest
from mavlink_peer import Px4Peer
from peers.fakes import Client, GatedCamera, ServiceRunner, avoid_scene_camera, service_config, wait_until
from pymavlink.dialects.v20 import common as mavlink

from companion import exitcodes
from companion.service.daemon import Service
from companion.service.vehicle import MavsdkVehicleLink

BODY_NED = mavlink.MAV_FRAME_BODY_NED
VELOCITY_YAWRATE_MASK = 0b0000010111000111  # ignore position, acceleration, yaw: 1479


def _status(client: Client) -> dict:
    return client.call("status")["result"]


def _vehicle_ready(client: Client) -> bool:
    v = _status(client)["vehicle"]
    return v["link"] == "connected" and v["armed"] and v["flight_mode"] != "UNKNOWN"


@pytest.fixture()
def flying(tmp_path: Path):
    """A peer flying in POSCTL, armed; a service with the MAVSDK link and a freezable camera."""
    peer = Px4Peer(mode="POSCTL", heartbeat_hz=5.0).start()
    port = peer.port
    cfg = service_config(
        tmp_path,
        vehicle={"connection": f"udpin://127.0.0.1:{port}", "connect_timeout_s": 5.0},
        # The default's failsafe logic (5 s) is in the supervisor tests.
        command={"failsafe_timeout_s": 1.5},
    )
    camera = GatedCamera(avoid_scene_camera(15.0))
    service = Service(cfg, camera=camera, link=MavsdkVehicleLink(cfg.vehicle.connection), install_signals=False, environ={})
    runner = ServiceRunner(service).start()
    client = Client(service.bus.control_endpoint, service.bus.health_endpoint)
    try:
        assert wait_until(lambda: _vehicle_ready(client), 10.0)
        yield peer, service, camera, client, cfg
    finally:
        client.close()
        runner.stop()
        peer.stop()


def _engage(peer: Px4Peer, client: Client) -> float:
    t0 = time.monotonic()
    reply = client.call("engage")
    assert reply["ok"], reply
    assert peer.wait_for(lambda: peer.mode == "OFFBOARD", 5.0), peer.commands
    assert wait_until(lambda: _status(client)["state"] == "engaged", 3.0)
    return t0


def test_setpoints_on_the_wire_stale_zero_failsafe_hold_and_pilot_takeover(flying) -> None:
    peer, service, camera, client, cfg = flying

    # Passive: nothing on the wire, no mode change.
    time.sleep(0.3)
    assert peer.setpoints == [] and peer.mode_commands() == []

    # Engage: zero setpoints stream first, then OFFBOARD is requested (and accepted).
    t_engage = _engage(peer, client)
    offboard_cmd = peer.mode_commands()[0]
    assert offboard_cmd.mode == "OFFBOARD" and offboard_cmd.result == mavlink.MAV_RESULT_ACCEPTED
    before = [s for s in peer.setpoints if s.t_s < offboard_cmd.t_s]
    assert len(before) >= 3 and all(s.is_zero for s in before) and before[0].t_s >= t_engage

    # Engaged: body-frame velocity + yaw-rate setpoints of the local planner, within its limits (the
    # stream's rate, 20 Hz, is a figure of `companion bench`; on a loaded machine the scheduler sets it).
    assert peer.wait_for(lambda: any(not s.is_zero for s in peer.setpoints_since(offboard_cmd.t_s)), 5.0)
    t0 = time.monotonic()
    assert peer.wait_for(lambda: len(peer.setpoints_since(t0)) >= 20, 30.0)
    window = peer.setpoints_since(t0)[:20]
    top = cfg.envelope.max_horizontal_speed_m_s
    for s in window:
        assert s.frame == BODY_NED and s.type_mask == VELOCITY_YAWRATE_MASK
        assert math.hypot(s.vx, s.vy) <= top + 1e-6
        assert abs(math.degrees(s.yaw_rate)) <= cfg.envelope.max_yaw_rate_deg_s + 1e-6
    assert any(not s.is_zero for s in window)
    # The autopilot's velocity reaches the service (the planner plans with it): the peer flies the
    # setpoints at once.
    assert wait_until(lambda: math.hypot(*_status(client)["vehicle"]["velocity_ned_m_s"][:2]) > 0.0, 2.0)

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
    assert [c.mode for c in peer.mode_commands()] == ["OFFBOARD"]

    # Failsafe (1.5 s here): Hold on the wire, the vehicle leaves offboard, then the stream stops.
    assert peer.wait_for(lambda: peer.mode == "HOLD", 2.0)
    hold = peer.mode_commands()[-1]
    assert hold.mode == "HOLD" and 1.2 < hold.t_s - t_freeze < 2.3
    last_before_hold = [s for s in peer.setpoints if s.t_s <= hold.t_s][-1]
    assert last_before_hold.is_zero
    assert wait_until(lambda: _status(client)["state"] == "failsafe", 1.0)
    time.sleep(0.5)
    t_quiet = time.monotonic()
    time.sleep(0.7)
    assert peer.setpoints_since(t_quiet) == []

    # Frames come back: still failsafe, nothing sent, never re-engaged by itself.
    camera.thaw()
    time.sleep(1.0)
    assert _status(client)["state"] == "failsafe"
    assert peer.setpoints_since(t_quiet) == [] and len(peer.mode_commands()) == 2

    # An explicit engage; then the pilot switches to Position mode.
    _engage(peer, client)
    n_cmds = len(peer.mode_commands())
    time.sleep(0.5)
    peer.set_mode("POSCTL", "pilot")
    t_pilot = time.monotonic()
    assert wait_until(lambda: _status(client)["state"] == "disengaged", 2.0)
    status = _status(client)
    assert "left OFFBOARD for POSCTL" in status["reason"] and not status["engaged"]
    time.sleep(1.5)
    # Never fought: no mode change after the pilot's; the stream stopped (MAVSDK's re-sending too,
    # although its own 3 s grace since the offboard start had not run out), its last value zero.
    assert len(peer.mode_commands()) == n_cmds and peer.mode == "POSCTL"
    late = peer.setpoints_since(t_pilot + 0.8)
    assert late == [], f"{len(late)} setpoints after the pilot took over"
    assert peer.setpoints_since(t_pilot - 5.0)[-1].is_zero
    assert not client.call("pause")["ok"]


def test_shutdown_sends_zero_then_hold_and_stops(flying) -> None:
    peer, service, camera, client, cfg = flying
    _engage(peer, client)
    time.sleep(0.3)
    t_stop = time.monotonic()
    service.request_shutdown_threadsafe("test")
    assert service.stopped.wait(10.0)
    assert service.exit_code == exitcodes.OK
    hold = [c for c in peer.commands_since(t_stop) if c.mode == "HOLD"]
    assert len(hold) == 1 and peer.mode == "HOLD"
    sent = peer.setpoints_since(t_stop)
    # The request reaches the service's loop asynchronously: the setpoints it (and MAVSDK's 20 Hz
    # re-send) sent before handling it may still land after t_stop, for as long as a loaded machine
    # takes to deliver it. From the first zero on, everything is zero, and that zero precedes the Hold.
    assert any(s.is_zero for s in sent), sent
    first_zero = next(i for i, s in enumerate(sent) if s.is_zero)
    assert sent[first_zero].t_s <= hold[0].t_s and all(s.is_zero for s in sent[first_zero:])
    time.sleep(0.3)
    assert peer.setpoints_since(hold[0].t_s + 0.3) == []


def test_shutdown_after_the_pilot_took_over_sends_no_mode_change(flying) -> None:
    peer, service, camera, client, cfg = flying
    _engage(peer, client)
    peer.set_mode("ALTCTL", "pilot")
    assert wait_until(lambda: _status(client)["state"] == "disengaged", 2.0)
    n = len(peer.mode_commands())
    service.request_shutdown_threadsafe("test")
    assert service.stopped.wait(10.0)
    assert len(peer.mode_commands()) == n and peer.mode == "ALTCTL"


def test_offboard_refused_without_a_stream_is_reported(tmp_path: Path) -> None:
    """The peer wants more setpoints than a 0 s prestream gives: PX4-like refusal, reported, no retry."""
    with Px4Peer(offboard_min_setpoints=50) as peer:
        port = peer.port
        cfg = service_config(tmp_path, vehicle={"connection": f"udpin://127.0.0.1:{port}", "offboard_prestream_s": 0.0})
        service = Service(cfg, camera=avoid_scene_camera(15.0), link=MavsdkVehicleLink(cfg.vehicle.connection),
                          install_signals=False, environ={})
        with ServiceRunner(service):
            client = Client(service.bus.control_endpoint)
            assert wait_until(lambda: _vehicle_ready(client), 10.0)
            assert client.call("engage")["ok"]
            assert wait_until(lambda: _status(client)["state"] == "disengaged", 5.0)
            status = _status(client)
            assert "refused" in status["reason"] and peer.mode == "POSCTL"
            assert len(peer.mode_commands()) == 1
            client.close()


def test_bad_connection_url_is_a_startup_failure(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, vehicle={"connection": "serial:///dev/ttyNOPE-companion-test:57600"})
    service = Service(cfg, camera=avoid_scene_camera(15.0), link=MavsdkVehicleLink(cfg.vehicle.connection),
                      install_signals=False, environ={})
    assert asyncio.run(service.run()) == exitcodes.STARTUP_FAILURE
    assert "ttyNOPE" in (service.health_message()["last_error"] or "")


@pytest.mark.slow
def test_vehicle_link_lost_stops_the_stream_without_a_mode_change(flying) -> None:
    peer, service, camera, client, cfg = flying
    _engage(peer, client)
    peer.silent = True  # the autopilot's side goes quiet (radio or cable)
    t_cut = time.monotonic()
    assert wait_until(lambda: _status(client)["state"] == "failsafe", 8.0)
    assert "link lost" in _status(client)["reason"]
    t_detect = time.monotonic()
    time.sleep(0.5)
    assert peer.setpoints_since(t_detect + 0.2) == []
    assert [c.mode for c in peer.commands_since(t_cut) if c.mode] == []
    # PX4's own offboard-loss failsafe acts (the stream stopped, nothing keeps it alive).
    assert peer.wait_for(lambda: peer.mode == "HOLD", 2.0)
    assert peer.mode_log[-1][2] == "offboard loss failsafe"


def test_sim_camera_renders_from_the_autopilots_telemetry_and_stops_with_it(tmp_path: Path) -> None:
    """camera.sim_pose = "telemetry" (PX4 SITL in the loop): frames come from the pose the autopilot
    reports over the service's own link; when that telemetry stops, frames stop (stale-frame failsafe)."""
    peer = Px4Peer(mode="POSCTL", heartbeat_hz=5.0).start()
    cfg = service_config(
        tmp_path,
        vehicle={"connection": f"udpin://127.0.0.1:{peer.port}", "connect_timeout_s": 5.0},
        camera={
            "width_px": 160, "height_px": 120, "sim_world": "course", "sim_course": "head-on",
            "sim_pose": "telemetry", "open_timeout_s": 15.0,
        },
    )
    service = Service(cfg, install_signals=False, environ={})  # camera and link from the config
    runner = ServiceRunner(service).start()
    client = None
    try:
        assert wait_until(lambda: service.ready.is_set() or service.stopped.is_set(), 20.0)
        assert service.ready.is_set(), service.exit_code
        client = Client(service.bus.control_endpoint, service.bus.health_endpoint)
        assert wait_until(lambda: _status(client)["camera"]["status"] == "streaming", 5.0)
        frames = _status(client)["camera"]["frames"]
        assert wait_until(lambda: _status(client)["camera"]["frames"] > frames + 5, 3.0)
        peer.silent = True  # the autopilot stops talking: no pose, so no frame
        assert wait_until(lambda: "telemetry" in str(_status(client)["camera"]["last_error"]), 5.0)
        assert _status(client)["frame_age_ms"] > 500.0
        peer.silent = False
        assert wait_until(lambda: _status(client)["camera"]["status"] == "streaming" and _status(client)["frame_age_ms"] < 300.0, 10.0)
    finally:
        if client is not None:
            client.close()
        runner.stop()
        peer.stop()
