"""The service as the ground station and the autopilot see it, on the wire: the real MAVSDK
link in-process against the PX4-like pymavlink peer. Its heartbeat (component 196, its state), its
STATUSTEXT lines and their rate limit, the OBSTACLE_DISTANCE layout, and engaging from the sticks."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from mavlink_peer import Px4Peer
from peers.fakes import Client, GatedCamera, ServiceRunner, avoid_scene_camera, expected_result, service_config, wait_until
from pymavlink.dialects.v20 import common as mavlink

from companion.service.daemon import Service
from companion.service.vehicle import make_vehicle_link

SERVICE = 196  # MAV_COMP_ID_OBSTACLE_AVOIDANCE


def _status(client: Client) -> dict:
    return client.call("status")["result"]


def _ready(client: Client) -> bool:
    v = _status(client)["vehicle"]
    return v["link"] == "connected" and v["armed"] and v["flight_mode"] != "UNKNOWN"


class Flight:
    def __init__(self, tmp_path: Path, **sections) -> None:
        self.peer = Px4Peer(mode="POSCTL", heartbeat_hz=5.0).start()
        vehicle = {"connection": f"udpin://127.0.0.1:{self.peer.port}", "connect_timeout_s": 5.0}
        vehicle.update(sections.pop("vehicle", {}))
        self.cfg = service_config(tmp_path, vehicle=vehicle, **sections)
        self.camera = GatedCamera(avoid_scene_camera(15.0))
        self.service = Service(
            self.cfg, camera=self.camera, link=make_vehicle_link(self.cfg.vehicle), install_signals=False, environ={}
        )
        self.runner = ServiceRunner(self.service).start()
        self.client = Client(self.service.bus.control_endpoint, self.service.bus.health_endpoint)
        assert wait_until(lambda: _ready(self.client), 10.0)

    def close(self) -> None:
        self.client.close()
        self.runner.stop()
        self.peer.stop()

    def service_heartbeats(self, since: float = 0.0, stateful: bool = True) -> list:
        # MAVSDK heartbeats the component itself with MAV_STATE_UNINIT (0); the service's own carry its state.
        return [
            h for h in list(self.peer.heartbeats)
            if h.component_id == SERVICE and h.t_s >= since and (h.system_status != 0 or not stateful)
        ]

    def texts(self, since: float = 0.0) -> list[str]:
        return [t.text for t in list(self.peer.status_texts) if t.t_s >= since]


@pytest.fixture()
def flight(tmp_path: Path):
    f = Flight(tmp_path)
    try:
        yield f
    finally:
        f.close()


def test_heartbeat_follows_the_state_and_statustext_says_each_change(flight: Flight) -> None:
    peer, client = flight.peer, flight.client
    # Passive: the obstacle-avoidance component of the companion computer, standby.
    assert wait_until(lambda: len(flight.service_heartbeats()) >= 2, 5.0)
    hb = flight.service_heartbeats()[-1]
    assert (hb.system_id, hb.component_id) == (peer.system_id, SERVICE)
    assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and hb.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert hb.system_status == mavlink.MAV_STATE_STANDBY
    times = [h.t_s for h in flight.service_heartbeats()]
    assert wait_until(lambda: len(flight.service_heartbeats()) >= 4, 5.0)
    times = [h.t_s for h in flight.service_heartbeats()]
    assert 0.7 < float(np.median(np.diff(times))) < 1.3  # vehicle.heartbeat_rate_hz = 1

    # Engaged: active, and the pilot reads it.
    t0 = time.monotonic()
    assert client.call("engage")["ok"]
    assert wait_until(lambda: _status(client)["state"] == "engaged", 5.0)
    assert wait_until(lambda: "companion: engaged" in flight.texts(t0), 3.0), flight.texts(t0)
    assert flight.texts(t0)[0] == "companion: engaging"
    assert wait_until(lambda: any(h.system_status == mavlink.MAV_STATE_ACTIVE for h in flight.service_heartbeats(t0)), 3.0)
    st = [t for t in peer.status_texts if t.text == "companion: engaged"][0]
    assert st.component_id == SERVICE and st.severity == mavlink.MAV_SEVERITY_NOTICE

    # Frames stop: the camera is gone -> degraded -> failsafe, each said, the heartbeat critical.
    t1 = time.monotonic()
    flight.camera.fail()
    assert wait_until(lambda: "companion: camera lost, holding" in flight.texts(t1), 3.0), flight.texts(t1)
    assert wait_until(lambda: any(h.system_status == mavlink.MAV_STATE_CRITICAL for h in flight.service_heartbeats(t1)), 3.0)
    lost = [t for t in peer.status_texts if t.text == "companion: camera lost, holding"][0]
    assert lost.severity == mavlink.MAV_SEVERITY_ERROR
    assert all(len(t) <= 50 for t in flight.texts())
    health = _status(client)["mavlink"]
    assert health["status_texts_sent"] >= 3 and health["heartbeats_sent"] >= 4


def test_obstacle_distance_on_the_wire(flight: Flight) -> None:
    peer, cfg = flight.peer, flight.cfg
    # Sent at the frame rate while passive (obstacle_distance.send = "always").
    assert wait_until(lambda: len(peer.obstacle_distances) >= 20, 5.0)
    frames0 = _status(flight.client)["processed_frames"]
    t0 = time.monotonic()
    assert wait_until(lambda: len([m for m in peer.obstacle_distances if m.t_s >= t0]) >= 10, 30.0)
    t1 = time.monotonic()
    frames = _status(flight.client)["processed_frames"] - frames0
    window = [m for m in peer.obstacle_distances if t0 <= m.t_s < t1]
    # One per processed frame (15 fps here, fewer on a loaded machine); never more.
    assert frames - 3 <= len(window) <= frames + 2, (len(window), frames)
    assert len(window) >= 10
    m = window[-1]
    assert m.component_id == SERVICE
    assert len(m.distances) == 72 and m.increment == 5 and m.increment_f == 5.0 and m.angle_offset == 0.0
    assert m.frame == mavlink.MAV_FRAME_BODY_FRD
    # The rig's limits: f·B/63 (64 disparities: 0.64 m, rounded up) and obstacle_distance.max_distance_m.
    assert m.min_distance == 65 and m.max_distance == 1200
    # Capture time on the monotonic clock, microseconds, increasing.
    stamps = [w.time_usec for w in window]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert abs(m.time_usec / 1e6 - m.t_s) < 0.5
    # The bins: the camera's view (45° right, 39° left) filled, the rest unknown; the box on the
    # left-front is in the left bins, nothing within 12 m to the right.
    d = np.array(m.distances)
    known = set(np.flatnonzero(d != 65535))
    assert known == set(range(0, 10)) | set(range(64, 72))
    result, _ = expected_result(cfg, avoid_scene_camera())
    np.testing.assert_array_equal(d, result.obstacle.distances_cm)  # exactly the pipeline's bins
    left = d[64:72]
    assert left.min() < 200  # the box, 1.35-1.5 m away
    assert d[5:10].min() > 150


def test_obstacle_distance_only_while_engaged_when_so_configured(tmp_path: Path) -> None:
    f = Flight(tmp_path, obstacle_distance={"send": "engaged"})
    try:
        time.sleep(1.0)
        assert f.peer.obstacle_distances == []
        assert f.client.call("engage")["ok"]
        assert wait_until(lambda: _status(f.client)["state"] == "engaged", 5.0)
        assert wait_until(lambda: len(f.peer.obstacle_distances) >= 5, 3.0)
    finally:
        f.close()


def test_statustext_rate_limit_on_the_wire(tmp_path: Path) -> None:
    f = Flight(tmp_path, vehicle={"status_text_min_interval_s": 2.0, "status_text_burst": 1})
    try:
        t0 = time.monotonic()
        assert f.client.call("engage")["ok"]  # "engaging", then "engaged" within ~0.6 s
        assert wait_until(lambda: "companion: engaged" in f.texts(t0), 5.0)
        sent = [t for t in f.peer.status_texts if t.t_s >= t0]
        assert [t.text for t in sent] == ["companion: engaging", "companion: engaged"]
        assert sent[1].t_s - sent[0].t_s > 1.8  # the second waited for its token, and arrived
        # A flood of state changes (pause / resume 10 times in 1 s) costs one line per 2 s.
        t1 = time.monotonic()
        for _ in range(10):
            f.client.call("pause")
            time.sleep(0.05)
            f.client.call("resume")
            time.sleep(0.05)
        t_end = time.monotonic()

        def flood() -> list:
            return [t for t in f.peer.status_texts if t.t_s >= t1]

        # The last word arrives (once its token is there: up to 2 s after the flood).
        assert wait_until(lambda: flood() and flood()[-1].text == "companion: engaged", 5.0), [t.text for t in flood()]
        # One line per 2 s, and the burst of 1: over the flood's own length (longer on a loaded machine).
        assert 1 <= len(flood()) <= 3 + (t_end - t1) / 2.0, [t.text for t in flood()]
        assert _status(f.client)["mavlink"]["status_texts_suppressed"] >= 10
    finally:
        f.close()


def test_engage_from_the_sticks(tmp_path: Path) -> None:
    f = Flight(tmp_path, vehicle={"engage_on_offboard_switch": True})
    peer, client = f.peer, f.client
    try:
        # Ready: zero setpoints stream (PX4 ignores them outside Offboard), nothing else.
        assert peer.wait_for(lambda: len(peer.setpoints) >= 10, 3.0)
        assert all(s.is_zero for s in peer.setpoints) and peer.mode == "POSCTL"
        assert _status(client)["state"] == "passive"
        # The pilot's switch to Offboard is accepted (the stream is there) and the service takes over.
        t0 = time.monotonic()
        assert peer.pilot_switch("OFFBOARD")
        assert wait_until(lambda: _status(client)["state"] == "engaged", 2.0)
        assert "offboard switch" in _status(client)["reason"]
        assert peer.wait_for(lambda: any(not s.is_zero for s in peer.setpoints_since(t0)), 2.0)
        assert wait_until(lambda: "companion: engaged" in f.texts(t0), 3.0)
        # Switching back to Position mode hands the vehicle back at once, and no mode command is ever sent.
        peer.pilot_switch("POSCTL")
        t1 = time.monotonic()
        assert wait_until(lambda: _status(client)["state"] == "disengaged", 1.0)
        t_seen = time.monotonic()
        time.sleep(0.5)  # what comes after it, if anything
        assert all(s.is_zero for s in peer.setpoints_since(max(t1 + 0.2, t_seen)))
        assert peer.mode_commands() == []
        # Ready again: a second switch engages again.
        assert peer.pilot_switch("OFFBOARD")
        assert wait_until(lambda: _status(client)["state"] == "engaged", 2.0)
        peer.pilot_switch("POSCTL")
        # Not ready (the camera is gone): the stream stops, and PX4 refuses the switch.
        assert wait_until(lambda: _status(client)["state"] == "disengaged", 1.0)
        f.camera.fail()
        assert wait_until(lambda: not _status(client)["offboard_switch_ready"], 5.0)
        assert wait_until(lambda: peer.setpoints_since(time.monotonic() - 1.0) == [], 5.0)
        assert not peer.pilot_switch("OFFBOARD")
    finally:
        f.close()


def test_the_service_is_a_component_of_the_vehicles_system(tmp_path: Path) -> None:
    f = Flight(tmp_path, vehicle={"system_id": 7, "component_id": 197})
    try:
        assert wait_until(lambda: len(f.peer.heartbeats) >= 2, 5.0)
        assert {(h.system_id, h.component_id) for h in f.peer.heartbeats} == {(7, 197)}
        assert wait_until(lambda: len(f.peer.obstacle_distances) >= 1, 5.0)
        assert f.peer.obstacle_distances[0].component_id == 197
    finally:
        f.close()
