"""Only the operator can command, and live changes cannot leave the safety envelope (a running service,
in-process, with the fake vehicle link): strict types on the wire, the envelope, what may change while
engaged, a controller that must still see near as near, the request budgets, the connection limit,
the socket's permissions, and the small truths (last_error, ctl with a broken file)."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq
from peers.fakes import Client, FakeLink, ServiceRunner, avoid_scene_camera, engage_and_wait, service_config, wait_until

from companion.config import CompanionConfig, apply_patch, load_bus_config, parse_config
from companion.config.envelope import envelope_violations
from companion.core.rig_check import check_rig_config
from companion.core.safety import near_blindness
from companion.errors import ConfigError
from companion.service.control import live_change_refusal
from companion.service.daemon import Service

ROOT = Path(__file__).resolve().parent.parent


def _engage(client: Client, link: FakeLink) -> None:
    engage_and_wait(client, link)


@pytest.fixture()
def running(tmp_path: Path):
    config_path = tmp_path / "companion.toml"
    cfg = service_config(tmp_path)
    service = Service(
        cfg, config_path=config_path, camera=avoid_scene_camera(15.0), link=FakeLink(), install_signals=False, environ={}
    )
    with ServiceRunner(service):
        client = Client(service.bus.control_endpoint, service.bus.health_endpoint)
        try:
            yield service, service.link, client, config_path
        finally:
            client.close()


def _error(reply: dict) -> str:
    assert not reply["ok"], reply
    return reply["error"]["message"]


# ---------------------------------------------------------------------------------------------- the config


def test_strict_types_on_the_wire() -> None:
    cfg = CompanionConfig()
    with pytest.raises(ConfigError, match=r"planner.cruise_speed_m_s: Input should be a valid number \(got '2.5'\)"):
        apply_patch(cfg, {"planner": {"cruise_speed_m_s": "2.5"}})
    with pytest.raises(ConfigError, match="planner.cruise_speed_m_s: Input should be a valid number"):
        apply_patch(cfg, {"planner": {"cruise_speed_m_s": True}})
    with pytest.raises(ConfigError, match="vehicle.require_armed_to_engage: Input should be a valid boolean"):
        apply_patch(cfg, {"vehicle": {"require_armed_to_engage": 0}})
    with pytest.raises(ConfigError, match="finite"):
        apply_patch(cfg, {"planner": {"cruise_speed_m_s": float("nan")}})
    assert apply_patch(cfg, {"planner": {"cruise_speed_m_s": 1}}).planner.cruise_speed_m_s == 1.0  # an integer is a number


@pytest.mark.parametrize(
    ("patch", "named"),
    [
        ({"planner": {"cruise_speed_m_s": 15.0}}, "envelope.max_horizontal_speed_m_s"),
        ({"command": {"stale_frame_timeout_s": 2.0, "failsafe_timeout_s": 4.0}}, "envelope.max_stale_frame_timeout_s"),
        ({"command": {"failsafe_timeout_s": 30.0}}, "envelope.max_failsafe_timeout_s"),
        ({"vehicle": {"setpoint_rate_hz": 2.0}}, "envelope.min_setpoint_rate_hz"),
        ({"vehicle": {"require_armed_to_engage": False}}, "envelope.arming_check_may_be_off"),
        ({"service": {"override_max_duration_s": 300.0}}, "envelope.max_override_duration_s"),
        ({"service": {"override_respects_brake": False}}, "envelope.override_may_ignore_brake"),
        ({"planner": {"max_yaw_rate_deg_s": 200.0}}, "envelope.max_yaw_rate_deg_s"),
        ({"planner": {"max_vertical_speed_m_s": 3.0}}, "envelope.max_vertical_speed_m_s"),
    ],
)
def test_a_config_outside_its_envelope_is_refused_naming_the_limit(patch: dict, named: str) -> None:
    with pytest.raises(ConfigError, match="outside the safety envelope") as err:
        apply_patch(CompanionConfig(), patch)
    assert named in str(err.value)


def test_the_envelope_itself_widens_only_in_the_file() -> None:
    wide = parse_config({"envelope": {"max_horizontal_speed_m_s": 5.0}, "planner": {"cruise_speed_m_s": 4.5}})
    assert envelope_violations(wide) == []
    from companion.config import load_config

    assert envelope_violations(load_config(ROOT / "config" / "paper.toml")) == []  # the paper's profile fits the defaults


def test_a_controller_blind_to_near_is_refused() -> None:
    cfg = CompanionConfig()
    assert near_blindness(cfg) is None
    far_lut = apply_patch(cfg, {"lut": {"points_m": [[0.2, 2.5], [40.0, 60.0]]}})
    assert "every region 0.5 m away" in near_blindness(far_lut)
    late_terms = {
        "controller": {
            "input_terms": {
                "near": {"shape": "left_shoulder", "params_m": [0.1, 0.3]},
                "far": {"shape": "right_shoulder", "params_m": [0.1, 0.3]},
            }
        }
    }
    late_near = apply_patch(cfg, late_terms)
    with pytest.raises(ConfigError, match="nothing could ever read near"):  # the rig check sees it first
        check_rig_config(late_near, "patch")
    assert "not brake" in near_blindness(late_near)
    # Rules without the paper's escapes still brake (no rule fired means brake): not blind.
    main = [r.model_dump() for r in cfg.controller.main_rules if r.name in ("R1", "S1", "S2", "S3", "S4")]
    assert near_blindness(apply_patch(cfg, {"controller": {"main_rules": main}})) is None


def test_what_may_change_while_engaged() -> None:
    cfg = CompanionConfig()
    tuned = apply_patch(cfg, {"controller": {"preferred_yaw_side": "left"}, "lut": {"median_frames": 5}})
    assert live_change_refusal(cfg, tuned, engaged=True, from_file=False) is None  # tuning
    slower = apply_patch(cfg, {"planner": {"cruise_speed_m_s": 1.0}})
    assert "disengage first to change planner.cruise_speed_m_s" in live_change_refusal(
        cfg, slower, engaged=True, from_file=False
    )
    later_stale = apply_patch(cfg, {"command": {"stale_frame_timeout_s": 0.4}})
    assert "disengage first to change command.stale_frame_timeout_s" in live_change_refusal(
        cfg, later_stale, engaged=True, from_file=False
    )
    assert live_change_refusal(cfg, later_stale, engaged=False, from_file=False) is None
    later_watchdog = apply_patch(cfg, {"command": {"progress_step_m": 2.0}})
    assert "command.progress_step_m" in live_change_refusal(cfg, later_watchdog, engaged=True, from_file=False)
    widened = apply_patch(cfg, {}).model_copy(
        update={"envelope": cfg.envelope.model_copy(update={"max_horizontal_speed_m_s": 3.0})}
    )
    assert "cannot change the safety envelope" in live_change_refusal(cfg, widened, engaged=False, from_file=False)
    assert "only while not engaged" in live_change_refusal(cfg, widened, engaged=True, from_file=True)
    assert live_change_refusal(cfg, widened, engaged=False, from_file=True) is None
    frozen = cfg.model_copy(update={"envelope": cfg.envelope.model_copy(update={"live_changes_while_engaged": "none"})})
    assert "no live changes while engaged" in live_change_refusal(frozen, tuned.model_copy(update={"envelope": frozen.envelope}), engaged=True, from_file=False)


# ---------------------------------------------------------------------------------------------- a running service


def test_live_changes_while_engaged_over_the_wire(running) -> None:
    service, link, client, _ = running
    _engage(client, link)
    assert client.call("set_config", patch={"controller": {"avoid_speed_fraction": 0.2}})["ok"]  # tuning
    assert "disengage first" in _error(client.call("set_config", patch={"planner": {"cruise_speed_m_s": 0.9}}))
    assert "outside the safety envelope" in _error(client.call("set_config", patch={"planner": {"cruise_speed_m_s": 15}}))
    assert "disengage first" in _error(client.call("set_config", patch={"command": {"stale_frame_timeout_s": 0.3}}))
    assert "cannot change the safety envelope" in _error(
        client.call("set_config", patch={"envelope": {"max_horizontal_speed_m_s": 10.0}})
    )
    assert "not brake" in _error(client.call("set_config", patch={"lut": {"points_m": [[0.2, 2.5], [40.0, 60.0]]}}))
    assert "valid number" in _error(client.call("set_config", patch={"planner": {"cruise_speed_m_s": "0.8"}}))
    assert service.config.controller.avoid_speed_fraction == 0.2 and service.config.command.stale_frame_timeout_s == 0.5
    assert client.call("disengage")["ok"]
    assert wait_until(lambda: client.call("status")["result"]["state"] == "disengaged", 3.0)
    assert client.call("set_config", patch={"command": {"stale_frame_timeout_s": 0.3}})["ok"]  # not engaged now


def test_a_good_reload_clears_the_last_rejection(running) -> None:
    service, _, client, config_path = running
    config_path.write_text("[planner]\ncruise_speed_m_s = -1\n")
    assert "cruise_speed_m_s" in _error(client.call("reload"))
    assert "reload rejected" in client.call("status")["result"]["last_error"]
    bus = service.config.bus
    config_path.write_text(
        f'[bus]\nhealth_endpoint = "{bus.health_endpoint}"\ncontrol_endpoint = "{bus.control_endpoint}"\n'
        f"requests_per_s_per_client = {bus.requests_per_s_per_client}\nmax_requests_per_s = {bus.max_requests_per_s}\n"
        '[camera]\nsource = "sim"\nfps_hz = 15.0\n[stereo]\nbackend = "opencv-bm"\n[planner]\ncruise_speed_m_s = 0.6\n'
    )
    assert client.call("reload")["ok"]
    assert client.call("status")["result"]["last_error"] is None


def test_request_budgets_answer_a_flooding_client_and_spare_the_others(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, bus={"requests_per_s_per_client": 20.0, "max_requests_per_s": 200.0})
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        ctx = zmq.Context()
        flooder = ctx.socket(zmq.DEALER)
        flooder.connect(service.bus.control_endpoint)
        for i in range(100):
            flooder.send(json.dumps({"cmd": "ping", "id": i}).encode())
        replies = []
        while flooder.poll(1000):
            replies.append(json.loads(flooder.recv()))
        ok = [r for r in replies if r["ok"]]
        limited = [r for r in replies if not r["ok"]]
        assert len(replies) == 100
        assert 15 <= len(ok) <= 30 and limited and all(r["error"]["type"] == "RateLimited" for r in limited)
        assert "requests_per_s_per_client" in limited[0]["error"]["message"]
        other = Client(service.bus.control_endpoint)
        assert other.call("ping")["ok"]  # another client has its own budget
        status = other.call("status")["result"]
        assert status["control"]["rate_limited"] >= len(limited)
        other.close()
        flooder.close(0)
        ctx.destroy(linger=0)


def test_a_flood_over_connections_each_under_its_budget_leaves_the_operator_in() -> None:
    """On a loaded machine the server read each flooding connection at under its own budget, so all
    eight counted as light, drained the reserve, and the operator's ping was refused. The
    reserve is for connections under their fair share of the budget of all, whatever rate each is
    read at; the flood's connections are refused and the total stays bounded."""
    import asyncio

    from companion.config import BusConfig
    from companion.service.control_server import ControlServer

    cfg = BusConfig(requests_per_s_per_client=50.0, max_requests_per_s=100.0)
    loop = asyncio.new_event_loop()
    server = ControlServer(None, cfg, loop, lambda r: None, None, lambda m: None, clock=lambda: 0.0)  # type: ignore[arg-type]
    try:
        admitted = {"flood": 0, "operator": 0}
        refused = {"flood": 0, "operator": 0}
        flooders = [f"flood-{i}".encode() for i in range(8)]
        for tick in range(6000):  # 6 s in 1 ms steps
            now_s = tick / 1000.0
            # Each flooding connection is read at 40 requests/s (under its own 50/s), 320/s in all.
            for i, ident in enumerate(flooders):
                if (tick + 3 * i) % 25 == 0:
                    (admitted if server._admit(ident, now_s) is None else refused)["flood"] += 1
            if tick % 500 == 250:  # the operator: 2 requests a second
                (admitted if server._admit(b"operator", now_s) is None else refused)["operator"] += 1
        assert refused["operator"] == 0, (admitted, refused)
        assert admitted["operator"] == 12
        assert refused["flood"] > 0
        assert admitted["flood"] + admitted["operator"] <= 2 * 100.0 * 6.0 + 2 * 100.0
    finally:
        loop.close()
        for fd in (server._wake_r, server._wake_w):
            os.close(fd)


def test_one_clients_flood_does_not_lock_out_another_operator(tmp_path: Path) -> None:
    """One group member flooding from several connections once spent the budget of all clients, and
    another operator's requests, disengage included, got RateLimited. The connections that spent it
    are refused; one that has used little of its own budget gets in; a stop request always does."""
    import threading

    cfg = service_config(tmp_path, bus={"requests_per_s_per_client": 50.0, "max_requests_per_s": 100.0})
    link = FakeLink()
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=link, install_signals=False, environ={})
    with ServiceRunner(service):
        operator = Client(service.bus.control_endpoint, service.bus.health_endpoint)
        _engage(operator, link)
        stop = threading.Event()
        seen: dict[str, int] = {}

        def flood() -> None:
            ctx = zmq.Context()
            socks = []
            for _ in range(8):
                sock = ctx.socket(zmq.DEALER)
                sock.setsockopt(zmq.LINGER, 0)
                sock.connect(service.bus.control_endpoint)
                socks.append(sock)
            try:
                while not stop.is_set():
                    for sock in socks:
                        with contextlib.suppress(zmq.Again):
                            sock.send(b'{"cmd": "ping"}', zmq.NOBLOCK)
                        while sock.poll(0):
                            reply = json.loads(sock.recv())
                            kind = "ok" if reply["ok"] else reply["error"]["message"].split(" = ")[0]
                            seen[kind] = seen.get(kind, 0) + 1
                    time.sleep(0.001)
            finally:
                for sock in socks:
                    sock.close(0)
                ctx.term()

        flooder = threading.Thread(target=flood, daemon=True)
        flooder.start()
        try:
            # The budget of all is spent by the flood (its connections hear so).
            assert wait_until(lambda: seen.get("more than bus.max_requests_per_s", 0) > 50, 20.0), seen
            reply = operator.call("ping")
            assert reply["ok"], reply  # a light user still gets in
            reply = operator.call("disengage")
            assert reply["ok"], reply
            assert wait_until(lambda: not link.state().in_offboard, 3.0)
            # A stop request is never refused by a budget, even from a connection that spent its own.
            spent = zmq.Context()
            sock = spent.socket(zmq.DEALER)
            sock.setsockopt(zmq.LINGER, 0)
            sock.connect(service.bus.control_endpoint)
            for _ in range(120):
                sock.send(b'{"cmd": "ping"}')
            sock.send(b'{"cmd": "disengage", "id": "last"}')
            replies = []
            while sock.poll(2000):
                replies.append(json.loads(sock.recv()))
                if replies[-1].get("id") == "last":
                    break
            sock.close(0)
            spent.term()
            assert replies[-1]["id"] == "last", replies[-3:]
            assert replies[-1]["ok"] or replies[-1]["error"]["type"] not in ("RateLimited", "Busy"), replies[-1]
            assert any(not r["ok"] and r["error"]["type"] == "RateLimited" for r in replies[:-1])
        finally:
            stop.set()
            flooder.join(5.0)
            operator.close()


_HUGE_MESSAGE_SENDER = """
import sys, time, zmq
ctx = zmq.Context()
sock = ctx.socket(zmq.DEALER)
sock.setsockopt(zmq.LINGER, 0)
sock.connect(sys.argv[1])
frame = b"x" * (100 * 1024)
for i in range(2999):
    sock.send(frame, zmq.SNDMORE)
sock.send(frame)
print("sent", flush=True)
time.sleep(float(sys.argv[2]))
sock.close(0)
ctx.term()
"""


def test_one_huge_multipart_message_is_cut_before_it_is_buffered(tmp_path: Path, caplog) -> None:
    """One DEALER sending a single message of 3000 frames of 100 KiB (each frame under the frame limit)
    once took the service from 152 to 702 MB: ZeroMQ keeps a message's frames until its last one. The
    connection is cut at the whole message's bound, with a logged reason; the resident size stays
    within 20 % of its start, and the control plane answers others meanwhile."""
    import logging
    import threading

    from companion.bench.common import rss_bytes

    caplog.set_level(logging.WARNING)
    cfg = service_config(tmp_path)
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        other = Client(service.bus.control_endpoint)
        assert other.call("ping")["ok"]
        time.sleep(1.0)  # settled: the pipeline's buffers are allocated
        start = rss_bytes(os.getpid())
        peak = [start]
        stop = threading.Event()

        def sample() -> None:
            while not stop.is_set():
                peak[0] = max(peak[0], rss_bytes(os.getpid()))
                time.sleep(0.02)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        sender = subprocess.Popen(
            [sys.executable, "-c", _HUGE_MESSAGE_SENDER, service.bus.control_endpoint, "5"],
            stdout=subprocess.PIPE, text=True,
        )
        try:
            assert wait_until(lambda: service.bus.relay.cut >= 1, 20.0), "the connection was not cut"
            for _ in range(5):
                assert other.call("ping")["ok"]
            sender.wait(30)
        finally:
            if sender.poll() is None:
                sender.kill()
                sender.wait()
            stop.set()
            sampler.join(2.0)
            other.close()
        assert peak[0] <= 1.2 * start, (start / 2**20, peak[0] / 2**20)
        assert "control connection cut: a message of more than" in caplog.text


def test_connections_beyond_the_limit_are_refused(tmp_path: Path) -> None:
    """With ``bus.max_connections = 3``, six clients that connect one after another and stay connected:
    the first three are answered, the other three are refused in their handshake (and keep being
    refused as they reconnect), and once the six have gone a new client gets in."""
    cfg = service_config(tmp_path, bus={"max_connections": 3})
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        ctx = zmq.Context()
        try:
            answered, socks = [], []  # each socket stays open (a dropped one would close)
            for i in range(6):
                s = ctx.socket(zmq.DEALER)
                socks.append(s)
                s.setsockopt(zmq.LINGER, 0)
                # A refused connection can leave the socket without a pipe, where a blocking send waits
                # forever (this test once hung CI): a send that cannot go out counts as not answered.
                s.setsockopt(zmq.SNDTIMEO, 500)
                s.connect(service.bus.control_endpoint)
                try:
                    s.send(json.dumps({"cmd": "ping", "id": i}).encode())
                except zmq.Again:
                    answered.append(False)
                    continue
                # Generous for the three let in (a loaded machine); a refused one never answers.
                answered.append(bool(s.poll(10_000 if i < 3 else 1_000)) and bool(s.recv()))
            assert answered == [True] * 3 + [False] * 3, answered
            assert wait_until(lambda: service.bus.stats()["refused_connections"] >= 3, 5.0)
        finally:
            ctx.destroy(linger=0)
        # Gone connections free their places.
        assert wait_until(lambda: service.bus.stats()["connections"] == 0, 5.0)
        again = Client(service.bus.control_endpoint)
        try:
            assert again.call("ping")["ok"]
        finally:
            again.close()


def test_a_failed_gatekeeper_stops_the_service_cleanly(tmp_path: Path, monkeypatch) -> None:
    """The gatekeeper answers every handshake; if its thread dies (a bug), no operator without a
    connection open could command or stop the service any more. The service says what failed and
    stops as it does on a signal (zero, Hold if ours), exiting with the internal-error code."""
    from companion import exitcodes
    from companion.service.bus import Gatekeeper

    def broken(self) -> None:
        raise RuntimeError("a bug in the gatekeeper")

    monkeypatch.setattr(Gatekeeper, "_count", broken)  # the first control connection ends the thread
    cfg = service_config(tmp_path)
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    runner = ServiceRunner(service).start()
    client = Client(service.bus.control_endpoint)
    try:
        client.sock.send(json.dumps({"cmd": "ping"}).encode())
        assert wait_until(service.stopped.is_set, 30.0), "the service did not stop"
    finally:
        client.close()
        code = runner.stop()
    assert code == exitcodes.INTERNAL_ERROR
    assert "gatekeeper failed: RuntimeError('a bug in the gatekeeper')" in (service.errors.message or "")


def test_a_client_beyond_the_limit_gets_an_error_not_a_hang(tmp_path: Path) -> None:
    """``companion ctl``'s client against a service whose connections are all taken: each call
    returns, with a reply or a ClientError naming the endpoint, within its timeout (a refused
    connection can leave nothing to send on, where a plain send waited forever). Which connections
    the gatekeeper refuses is test_connections_beyond_the_limit_are_refused's business."""
    from companion.service.client import ClientError, ControlClient

    cfg = service_config(tmp_path, bus={"max_connections": 1})
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        clients = [ControlClient(service.bus.control_endpoint, timeout_s=1.0) for _ in range(5)]
        errors = []
        t0 = time.monotonic()
        try:
            for c in clients:  # every connection stays open: later ones are beyond the limit
                try:
                    assert c.call({"cmd": "ping"})["ok"]
                except ClientError as err:
                    errors.append(str(err))
        finally:
            for c in clients:
                c.close()
        elapsed_s = time.monotonic() - t0
        assert elapsed_s < len(clients) * 5.0 + 30.0, elapsed_s  # each call ends by its 1 s timeout: never a hang
        assert all(service.bus.control_endpoint in e for e in errors), errors


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to try the socket as another user (uid nobody)")
def test_another_user_cannot_use_the_control_socket(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    run.chmod(0o755)  # others may enter the folder: only the socket's own mode keeps them out
    tmp_path.chmod(0o755)
    cfg = service_config(run)
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        sock = Path(service.bus.control_endpoint.removeprefix("ipc://"))
        assert sock.stat().st_mode & 0o777 == 0o660
        endpoint = service.bus.control_endpoint
        # The interpreter may lie where uid nobody cannot run it: fork this one and drop to nobody.
        out = _as_nobody(lambda: _try_to_engage(endpoint))
        assert out == "no reply; ControlClient: permission denied", out
        assert service.supervisor.state.value == "passive"  # the engage never arrived


def _try_to_engage(endpoint: str) -> str:
    """In a process of uid nobody: a raw ZeroMQ engage, then ``companion ctl``'s client."""
    from companion.service.client import ClientError, ControlClient

    ctx = zmq.Context()
    s = ctx.socket(zmq.DEALER)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    s.send(b'{"cmd": "engage"}')
    raw = "answered" if s.poll(1500) else "no reply"
    s.close(0)
    ctx.destroy(linger=0)
    try:
        ControlClient(endpoint, timeout_s=1.0).close()
        client = "ControlClient: connected"
    except ClientError as err:
        client = "ControlClient: permission denied" if "permission denied" in str(err) and "group" in str(err) else str(err)
    return f"{raw}; {client}"


def _as_nobody(fn) -> str:
    """Run ``fn`` in a forked child as uid/gid nobody; its string result comes back through a pipe."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: no pytest, no service threads; only fn
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            os.write(w, fn().encode())
        finally:
            os._exit(0)
    os.close(w)
    chunks = []
    while True:
        data = os.read(r, 4096)
        if not data:
            break
        chunks.append(data)
    os.close(r)
    os.waitpid(pid, 0)
    return b"".join(chunks).decode()


def test_ctl_finds_the_endpoint_in_a_file_whose_other_sections_are_invalid(running) -> None:
    service, _, _, config_path = running
    broken = config_path.parent / "broken.toml"
    broken.write_text(
        f'[bus]\ncontrol_endpoint = "{service.bus.control_endpoint}"\nhealth_endpoint = "{service.bus.health_endpoint}"\n'
        "[planner]\ncruise_speed_m_s = -5\n[nonsense]\nx = 1\n"
    )
    assert load_bus_config(broken).control_endpoint == service.bus.control_endpoint
    out = subprocess.run(
        [sys.executable, "-m", "companion", "ctl", "--config", str(broken), "status"], capture_output=True, text=True, timeout=30
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["state"] == "passive"
    watch = subprocess.run(
        [sys.executable, "-m", "companion", "watch", "--config", str(broken), "--json", "--count", "1"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert watch.returncode == 0 and json.loads(watch.stdout)["type"] == "health", watch.stderr


def test_auto_endpoints_live_in_a_private_runtime_directory(tmp_path: Path) -> None:
    from companion.service.runtime import find_socket, resolve_endpoint, runtime_dir

    env = {"XDG_RUNTIME_DIR": str(tmp_path)}
    assert resolve_endpoint("auto", "control", env) == f"ipc://{tmp_path}/companion/control.sock"
    assert (runtime_dir(env).stat().st_mode & 0o777) == 0o700
    systemd = {"RUNTIME_DIRECTORY": "/run/companion"}
    assert resolve_endpoint("auto", "health", systemd) == "ipc:///run/companion/health.sock"
    assert resolve_endpoint("tcp://127.0.0.1:5561", "control", env) == "tcp://127.0.0.1:5561"
    with pytest.raises(ConfigError, match="no control socket of a running service"):
        find_socket("control", {"XDG_RUNTIME_DIR": str(tmp_path / "none")})


def test_a_service_whose_controller_is_blind_to_near_does_not_start(tmp_path: Path) -> None:
    import asyncio

    from companion import exitcodes

    cfg = service_config(tmp_path, lut={"points_m": [[0.2, 2.5], [40.0, 60.0]]})
    service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    assert asyncio.run(service.run()) == exitcodes.STARTUP_FAILURE
    assert "not brake" in service.health_message()["last_error"]
