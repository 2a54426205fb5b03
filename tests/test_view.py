"""The preview (drawn only while watched, off the flight path), `companion view` without a browser (access,
control, a hung or killed view), the flight recording, `companion sim --view` and `companion review`."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import zmq
from peers.browser import ViewProcess
from peers.fakes import (
    Client,
    FakeLink,
    ServiceRunner,
    avoid_scene_camera,
    avoid_scene_preview_inputs,
    engage_and_wait,
    service_config,
    wait_until,
)

from companion.config import parse_config
from companion.errors import ConfigError, ProtocolError
from companion.service.daemon import Service
from companion.service.preview_frame import PREVIEW_TOPIC, encode_jpeg, pack, render_preview, unpack

ROOT = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------------------------------------- pure parts


def test_view_config_is_checked() -> None:
    with pytest.raises(ConfigError, match="view.preview_endpoint: .*reachable from the network"):
        parse_config({"view": {"preview_endpoint": "tcp://0.0.0.0:5562"}})
    with pytest.raises(ConfigError, match="view.record_dir: .*absolute path"):
        parse_config({"view": {"record_dir": "flights"}})
    with pytest.raises(ConfigError, match="view.preview_rate_hz"):
        parse_config({"view": {"preview_rate_hz": 0}})
    cfg = parse_config({"view": {"preview_endpoint": "ipc:///tmp/p.sock", "preview_width_px": 320}})
    assert cfg.view.preview_width_px == 320


def test_preview_image_and_message(tmp_path: Path) -> None:
    image = render_preview(avoid_scene_preview_inputs(service_config(tmp_path)), 320)
    assert image.shape == (179, 320, 3) and image.dtype == np.uint8
    # The inset (lower right quarter) is the disparity's colours, not the camera's grey.
    inset = image[-40:, -70:].astype(int)
    assert np.abs(inset[..., 0] - inset[..., 2]).mean() > 30
    jpeg = encode_jpeg(image, 70)
    header, body = unpack(pack({"type": "preview", "seq": 1}, jpeg))
    assert header == {"type": "preview", "seq": 1} and body == jpeg
    with pytest.raises(ProtocolError, match="expected"):
        unpack([PREVIEW_TOPIC, b"{}"])
    with pytest.raises(ProtocolError, match="not a JPEG"):
        unpack([PREVIEW_TOPIC, b"{}", b"GIF89a"])


# ---------------------------------------------------------------------------------------------- the service side


def _count_disparity_requests(service: Service) -> list[float]:
    """Wrap the pipeline's process: the times at which it was asked for a disparity image."""
    asked: list[float] = []
    pipeline = service.vision.pipeline
    original = pipeline.process

    def process(image, timestamp_s, want_disparity=False):
        if want_disparity:
            asked.append(time.monotonic())
        return original(image, timestamp_s, want_disparity=want_disparity)

    pipeline.process = process
    return asked


def test_preview_only_while_watched_at_the_rate_asked_for(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, view={"preview_rate_hz": 4.0, "preview_width_px": 320})
    service = Service(cfg, camera=avoid_scene_camera(15.0), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        asked = _count_disparity_requests(service)
        publisher = service.view.publisher
        time.sleep(1.0)
        assert asked == [] and publisher.published == 0 and not publisher.subscribed
        assert service.vision.latest.result.disparity is None  # nobody watches: no disparity image at all

        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.SUBSCRIBE, b"preview")
        sub.connect(cfg.view.preview_endpoint)
        got = []
        deadline = time.monotonic() + 60.0  # generous: the worker starts on a busy machine
        while len(got) < 6 and time.monotonic() < deadline:
            if sub.poll(100):
                got.append(unpack(sub.recv_multipart()))
        sub.close(0)
        ctx.destroy(linger=0)
        assert len(got) == 6, len(got)
        # 4 Hz asked, from a 15 fps camera: the pictures are frames about a period apart, never every frame
        # (on the service's clock, so a busy machine only spaces them further). A late picture lets the
        # next catch up by at most half a period, and a picture's frame may be a camera frame older than
        # its turn: five gaps span at least 3.5 periods less a frame.
        gaps = np.diff([h["time_s"] for h, _ in got])
        assert np.all(gaps > 0) and np.sum(gaps) >= 3.5 / 4.0 - 1.0 / 15.0, gaps
        assert [h["seq"] for h, _ in got] == sorted(h["seq"] for h, _ in got)
        header, jpeg = got[-1]
        assert header["width_px"] == 320 and header["near_m"] == 0.75 and header["decision"] == "avoid"
        assert jpeg[:2] == b"\xff\xd8"
        # The disparity was asked for once per preview, not per frame.
        assert len(got) <= len(asked) <= len(got) + 3
        assert wait_until(lambda: not publisher.subscribed, 10.0)
        n = len(asked)
        time.sleep(0.6)
        assert len(asked) == n  # gone again with the viewer
        # Size and rate apply live.
        assert Client(cfg.bus.control_endpoint).call("set_config", patch={"view": {"preview_width_px": 400}})["ok"]


def test_a_hung_or_killed_view_changes_nothing_for_the_service(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, view={"preview_rate_hz": 15.0})
    link = FakeLink()
    service = Service(cfg, camera=avoid_scene_camera(15.0), link=link, install_signals=False, environ={})
    with ServiceRunner(service):
        client = Client(cfg.bus.control_endpoint, cfg.bus.health_endpoint)
        try:
            engage_and_wait(client, link)
            with ViewProcess("--health-endpoint", cfg.bus.health_endpoint, "--preview-endpoint", cfg.view.preview_endpoint,
                             "--control-endpoint", cfg.bus.control_endpoint) as view:
                assert wait_until(lambda: service.view.publisher.published > 5, 60.0)
                os.kill(view.pid, signal.SIGSTOP)  # hung: reads nothing, answers nothing
                try:
                    t0 = time.monotonic()
                    # The service goes on: setpoints keep coming and the preview is dropped, never queued
                    # (the setpoint rate's budget is `companion bench`'s, not a test's).
                    assert wait_until(lambda: len(link.sent_since(t0)) >= 20 and client.health(30.0)["fps"] > 0, 60.0)
                    # Commanding all along (engaged, or degraded a moment on a loaded machine).
                    assert wait_until(lambda: client.health(30.0)["state"] == "engaged", 30.0)
                finally:
                    os.kill(view.pid, signal.SIGCONT)
                os.kill(view.pid, signal.SIGKILL)
                view.proc.wait()
            assert wait_until(lambda: not service.view.publisher.subscribed, 3.0)
            t1 = time.monotonic()
            assert wait_until(lambda: len(link.sent_since(t1)) >= 8, 30.0)
            assert wait_until(lambda: client.health(30.0)["state"] == "engaged", 30.0)
        finally:
            client.close()


# ---------------------------------------------------------------------------------------------- access


def _get(url: str, headers: dict[str, str] | None = None, data: bytes | None = None) -> tuple[int, bytes, dict]:
    req = urllib.request.Request(url, data=data, headers=headers or {}, method="POST" if data is not None else "GET")
    try:
        with urllib.request.urlopen(req, timeout=5) as resp:
            return resp.status, resp.read(), dict(resp.headers)
    except urllib.error.HTTPError as err:
        return err.code, err.read(), dict(err.headers)


def test_view_access_token_origin_and_control(tmp_path: Path) -> None:
    link = FakeLink()
    cfg = service_config(tmp_path)
    service = Service(cfg, camera=avoid_scene_camera(15.0), link=link, install_signals=False, environ={})
    token_file = tmp_path / "token"
    token_file.write_text("s3cret-token-for-the-field\n")
    token_file.chmod(0o600)
    endpoints = ("--health-endpoint", cfg.bus.health_endpoint, "--preview-endpoint", cfg.view.preview_endpoint,
                 "--control-endpoint", cfg.bus.control_endpoint)
    with ServiceRunner(service):
        # A network bind: the token is required (and shown only in the printed URL).
        with ViewProcess(*endpoints, "--host", "0.0.0.0", "--token-file", str(token_file)) as view:
            assert view.url.endswith("/?token=s3cret-token-for-the-field")
            port = view.url.split(":")[2].split("/")[0]
            base = f"http://127.0.0.1:{port}"
            assert _get(base + "/")[0] == 401
            assert _get(base + "/api/health")[0] == 401
            # ?token= once: a cookie for the page's reads (the page drops the token from the address
            # bar itself); the page never holds the token.
            import http.cookiejar

            jar = http.cookiejar.CookieJar()
            opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar))
            with opener.open(base + "/?token=s3cret-token-for-the-field", timeout=5) as resp:
                status, body, headers = resp.status, resp.read(), dict(resp.headers)
            assert status == 200 and b"companion view" in body and b"s3cret" not in body
            cookie = next(c for c in jar if c.name == "companion_view_token")
            assert cookie.value == "s3cret-token-for-the-field" and cookie.has_nonstandard_attr("HttpOnly")
            assert "default-src 'self'" in headers["Content-Security-Policy"]
            assert b"http://" not in body and b"https://" not in body  # nothing from outside
            auth = {"Authorization": "Bearer s3cret-token-for-the-field"}
            assert wait_until(lambda: json.loads(_get(base + "/api/health", auth)[1])["health"] is not None, 5.0)
            assert _get(base + "/api/health", {"Authorization": "Bearer wrong-token-xxxx"})[0] == 401
            # The cookie lets the page watch; commanding needs the token as a header.
            page = {"Content-Type": "application/json", "X-Companion-View": "1", "Origin": base}
            req = urllib.request.Request(base + "/api/control", data=b'{"cmd": "engage"}', headers=page, method="POST")
            with pytest.raises(urllib.error.HTTPError) as refused:
                opener.open(req, timeout=5)
            assert refused.value.code == 403 and b"Bearer" in refused.value.read() and not link.state().in_offboard
        # Loopback: watching is open (loopback Host names only); commanding needs the page's header,
        # its origin and the token the view made up and printed.
        with ViewProcess(*endpoints, env={"COMPANION_VIEW_TOKEN": ""}) as view:
            base, _, token = view.url.partition("/?token=")
            assert len(token) >= 24 and any("made up" in line for line in view.lines)
            assert _get(base + "/")[0] == 200 and token.encode() not in _get(base + "/")[1]
            assert _get(base + "/", {"Host": "evil.example:8080"})[0] == 403  # DNS rebinding
            engage = json.dumps({"cmd": "engage"}).encode()
            bearer = {"Authorization": f"Bearer {token}"}
            assert _get(base + "/api/control", {"Content-Type": "application/json", **bearer}, engage)[0] == 403
            page = {"Content-Type": "application/json", "X-Companion-View": "1"}
            status, body, _ = _get(base + "/api/control", page, engage)  # what another local user could send
            assert status == 403 and b"token" in body and not link.state().in_offboard
            status, _, _ = _get(base + "/api/control", {**page, "Authorization": "Bearer " + "x" * len(token)}, engage)
            assert status == 403 and not link.state().in_offboard
            page = {**page, **bearer}
            status, _, _ = _get(base + "/api/control", {**page, "Origin": "http://evil.example"}, engage)
            assert status == 403 and not link.state().in_offboard
            status, body, _ = _get(base + "/api/control", page, json.dumps({"cmd": "set_config"}).encode())
            assert status == 400 and b"engage, disengage, pause, resume" in body
            # as an operator would on a loaded machine: again while the frames are not fresh yet
            deadline = time.monotonic() + 60.0
            while True:
                status, body, _ = _get(base + "/api/control", {**page, "Origin": base}, engage)
                if status != 200 or json.loads(body)["ok"] or time.monotonic() > deadline:
                    break
                if not any(w in body.decode() for w in ("s old", "no frame processed yet")):
                    break
                time.sleep(0.5)
            assert status == 200 and json.loads(body)["ok"], body
            assert wait_until(lambda: link.state().in_offboard, 3.0)
            status, body, _ = _get(base + "/api/control", page, engage)
            assert status == 200 and not json.loads(body)["ok"] and "already engaged" in body.decode()
            assert wait_until(lambda: _get(base + "/preview.jpg")[0] == 200, 60.0)
            status, jpeg, headers = _get(base + "/preview.jpg")
            assert status == 200 and jpeg[:2] == b"\xff\xd8" and headers["Content-Type"] == "image/jpeg"
            timeline = json.loads(_get(base + "/api/timeline")[1])["timeline"]
            assert timeline and {"t", "state", "kind", "yaw", "pitch"} <= set(timeline[-1])


@pytest.mark.skipif(
    os.geteuid() != 0 or not all(shutil.which(t) for t in ("useradd", "userdel", "runuser", "curl")),
    reason="needs root to create a second local user, and useradd, userdel, runuser and curl",
)
def test_another_local_user_cannot_command_through_the_view(tmp_path: Path) -> None:
    """The operator runs ``companion view`` on loopback; another local user once engaged the vehicle
    with ``curl -X POST http://127.0.0.1:PORT/api/control -H 'X-Companion-View: 1' -d '{"cmd":"engage"}'``
    (the header and origin checks stop browsers only). A second user made for this test may watch
    but not command; the operator's token commands."""
    user = f"cvtest{os.getpid() % 100000}"
    subprocess.run(["useradd", "--no-create-home", "--home-dir", "/nonexistent", "--shell", "/usr/sbin/nologin", user],
                   check=True, capture_output=True)
    try:
        link = FakeLink()
        cfg = service_config(tmp_path)
        service = Service(cfg, camera=avoid_scene_camera(15.0), link=link, install_signals=False, environ={})
        token_file = tmp_path / "view-token"
        token_file.write_text("operator-only-token-0123456789\n")
        token_file.chmod(0o600)
        with ServiceRunner(service), ViewProcess(
            "--health-endpoint", cfg.bus.health_endpoint, "--control-endpoint", cfg.bus.control_endpoint,
            "--token-file", str(token_file),
        ) as view:
            base, _, token = view.url.partition("/?token=")
            assert token == "operator-only-token-0123456789"

            def curl(*args: str, as_user: str | None = None) -> tuple[str, str]:
                cmd = ["curl", "-s", "-m", "10", "-w", "\n%{http_code}", *args]
                if as_user is not None:
                    cmd = ["runuser", "-u", as_user, "--", *cmd]
                out = subprocess.run(cmd, capture_output=True, text=True, timeout=30, cwd="/").stdout
                body, _, code = out.rpartition("\n")
                return code, body

            engage = ["-X", "POST", base + "/api/control", "-H", "X-Companion-View: 1", "-H",
                      "Content-Type: application/json", "-d", '{"cmd":"engage"}']
            # The outsider: watching works, the page does not hold the token, commanding is refused.
            code, page = curl(base + "/", as_user=user)
            assert code == "200" and token not in page
            code, body = curl(*engage, as_user=user)
            assert code == "403" and "token" in body, (code, body)
            code, body = curl(*engage, "-H", "Authorization: Bearer operator-only-token-012345678X", as_user=user)
            assert code == "403", (code, body)
            assert not link.state().in_offboard and service.supervisor.state.value == "passive"
            # Nor can it read the token where the operator keeps it.
            for secret in (str(token_file), f"/proc/{view.pid}/environ", f"/proc/{view.pid}/cmdline"):
                seen = subprocess.run(["runuser", "-u", user, "--", "cat", secret], capture_output=True, timeout=30)
                assert token.encode() not in seen.stdout, secret
            # The operator's token commands (asked again while a loaded machine's frames are late, as an
            # operator would: "newest frame is 0.55 s old").
            def operator_engages() -> bool:
                code, body = curl(*engage, "-H", f"Authorization: Bearer {token}")
                assert code == "200", (code, body)
                reply = json.loads(body)
                assert reply["ok"] or " s old" in str(reply["error"]["message"]), reply
                return bool(reply["ok"])

            assert wait_until(operator_engages, 30.0, poll_s=0.5)
            assert wait_until(lambda: link.state().in_offboard, 3.0)
    finally:
        subprocess.run(["userdel", user], capture_output=True)


def test_a_network_bind_without_a_token_gets_one_made_up(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "COMPANION_VIEW_TOKEN"}
    proc = subprocess.run(
        [sys.executable, "-m", "companion", "view", "--token-file", str(tmp_path / "missing"), "--host", "0.0.0.0"],
        capture_output=True, text=True, timeout=30, env=env,
    )
    assert proc.returncode == 2 and "--token-file" in proc.stderr and "cannot read it" in proc.stderr
    with ViewProcess("--health-endpoint", "ipc:///nonexistent/h.sock", "--no-control", "--host", "0.0.0.0",
                     env={"COMPANION_VIEW_TOKEN": ""}) as view:
        assert "?token=" in view.url and len(view.url.split("?token=")[1]) >= 16
        assert any("made up" in line for line in view.lines)


# ---------------------------------------------------------------------------------------------- recording, review


def test_the_service_records_health_and_preview_and_review_reports_it(tmp_path: Path) -> None:
    rec = tmp_path / "flights"
    cfg = service_config(tmp_path, view={"record_dir": str(rec), "record_preview_every": 1, "preview_rate_hz": 10.0})
    link = FakeLink()
    service = Service(cfg, camera=avoid_scene_camera(15.0), link=link, install_signals=False, environ={})
    with ServiceRunner(service):
        client = Client(cfg.bus.control_endpoint)
        try:
            recorder = service.view.recorder
            assert wait_until(lambda: recorder.health_lines >= 5, 30.0)
            engage_and_wait(client, link)  # asked again while a loaded machine's first frames are late
            assert wait_until(lambda: recorder.preview_frames >= 20 and recorder.health_lines >= 25, 90.0)
            assert client.call("pause")["ok"]
            n = recorder.health_lines
            assert wait_until(lambda: recorder.health_lines >= n + 3, 30.0)
            assert client.call("disengage")["ok"]
            n = recorder.health_lines
            assert wait_until(lambda: recorder.health_lines >= n + 3, 30.0)
        finally:
            client.close()
    runs = list(rec.iterdir())
    assert len(runs) == 1
    run = runs[0]
    lines = (run / "health.jsonl").read_text().splitlines()
    assert len(lines) >= 25 and json.loads(lines[-1])["type"] == "health"
    states = {json.loads(line)["state"] for line in lines}
    assert {"passive", "engaged", "paused", "disengaged"} <= states
    index = [json.loads(line) for line in (run / "preview" / "index.jsonl").read_text().splitlines()]
    assert len(index) >= 20 and all((run / "preview" / i["file"]).is_file() for i in index)
    assert "[view]" in (run / "config.toml").read_text()

    out = subprocess.run(
        [sys.executable, "-m", "companion", "review", str(run)], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert out.returncode == 0, out.stderr
    html = (run / "review.html").read_text()
    for part in ("Decisions and regions", "Setpoints against the vehicle", "Frame age", "Contact sheet", "engaged", "paused"):
        assert part in html, part
    assert html.count("<svg") >= 4 and "data:image/jpeg;base64," in html
    assert "http://" not in html.replace("http://www.w3.org/2000/svg", "")


def test_review_of_a_bounded_recording_and_of_a_sitl_workdir(tmp_path: Path) -> None:
    from companion.service.preview import FlightRecorder
    from companion.view.review import write_review

    # The recorder's bound: preview frames stop at 80 %, health at 100 %.
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    recorder = FlightRecorder(tmp_path / "rec", f"tcp://127.0.0.1:{port}", None, preview_every=0, max_bytes=4000)
    run = recorder.start()
    time.sleep(0.3)
    message = json.dumps({"type": "health", "seq": 1, "time_s": 1.0, "state": "passive", "reason": "x" * 300}).encode()
    for _ in range(30):
        pub.send(message)
        time.sleep(0.005)
    time.sleep(0.3)
    recorder.close()
    pub.close(0)
    ctx.destroy(linger=0)
    size = (run / "health.jsonl").stat().st_size
    assert 0 < size <= 4000 and recorder.health_lines == len((run / "health.jsonl").read_text().splitlines()) < 30

    # A companion sitl --workdir: one folder per flight, each with health.jsonl and companion.toml.
    work = tmp_path / "sitl"
    for i, kind in enumerate(("brake", "avoid")):
        flight = work / f"{i:02d}-doorway-{i}"
        flight.mkdir(parents=True)
        (flight / "companion.toml").write_text("")
        rows = []
        for k in range(60):
            t = 100.0 + k * 0.1
            decision = kind if 20 <= k < 30 else "clear"
            rows.append({
                "type": "health", "seq": k + 1, "time_s": t, "unix_time_s": 1.8e9 + t, "state": "engaged" if k >= 5 else "engaging",
                "reason": "r", "engaged": k >= 5, "fps": 15.0, "frame_age_ms": 40.0, "stages_ms": {"total_ms": 17.0},
                "frame_to_setpoint_ms": {"last": 25.0, "median": 24.0, "p99": 30.0, "samples": k},
                "regions_m": {n: (0.6 if decision != "clear" and n == "center" else 3.0) for n in
                              ("up_left", "up", "up_right", "left", "center", "right", "down_left", "down", "down_right")},
                "yaw": 0.4 if decision == "avoid" else 0.0, "pitch": 0.0,
                "decision": {"kind": decision, "speed_fraction": 0.5, "reason": "rule"},
                "setpoint": {"forward_m_s": 1.0, "right_m_s": 0.0, "down_m_s": 0.0, "yaw_rate_deg_s": 10.0},
                "vehicle": {"link": "connected", "flight_mode": "OFFBOARD", "armed": True, "in_offboard": True,
                            "position_ned_m": [k * 0.1, 0.0, -1.5], "attitude_rad": [0, 0, 0.1], "velocity_ned_m_s": [1.0, 0.0, 0.0]},
                "dropped_frames": k // 10, "processed_frames": k, "last_error": None,
            })
        (flight / "health.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = write_review(work, None)
    assert out == work / "review.html"
    html = out.read_text()
    assert "00-doorway-0" in html and "01-doorway-1" in html
    assert "Path from above" in html and "brake" in html and "avoid" in html
    assert html.count("class=\"moment\"") >= 2  # one brake and one avoid moment, drawn from the regions


# ---------------------------------------------------------------------------------------------- the simulator


def _sim_with_view(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen[str], str | None, list[str]]:
    """``companion sim --view`` on head-on-1 as a process; its page's URL (None: it printed none) and
    the lines it printed up to it."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "companion", "sim", "--course", "head-on", "--seed", "1", "--view", "--view-port", "0",
         *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
    )
    assert proc.stdout is not None
    lines: list[str] = []
    for line in proc.stdout:
        lines.append(line)
        if "view:          open " in line:
            return proc, line.split("open ", 1)[1].strip(), lines
    return proc, None, lines


def test_sim_course_with_the_view(tmp_path: Path) -> None:
    proc, url, lines = _sim_with_view(tmp_path, "--view-linger-s", "3")
    try:
        assert url, "".join(lines)
        assert wait_until(lambda: (json.loads(_get(url + "api/health")[1])["health"] or {}).get("state") == "engaged", 10.0)
        h = json.loads(_get(url + "api/health")[1])
        assert h["health"]["camera"]["source"].startswith("sim") and h["health"]["vehicle"]["link"] == "simulated"
        assert wait_until(lambda: _get(url + "preview.jpg")[0] == 200, 5.0)
        status, body, _ = _get(url + "api/control", {"Content-Type": "application/json", "X-Companion-View": "1"}, b'{"cmd": "engage"}')
        assert status == 409 and b"no control socket" in body
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rest, _ = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            rest, _ = proc.communicate()
    assert proc.returncode in (0, 130), "".join(lines) + rest  # 130: the Ctrl-C above, mid-flight
    with pytest.raises(urllib.error.URLError):  # the view went with it
        urllib.request.urlopen(url, timeout=2)


def test_a_killed_sim_takes_its_page_down(tmp_path: Path) -> None:
    """``companion sim --view`` killed outright (SIGKILL: no cleanup of its own) leaves no page serving:
    the view's input is a pipe the sim held, and the view stops when it closes. Before, the view served
    on, orphaned, holding its port."""
    proc, url, lines = _sim_with_view(tmp_path)
    try:
        assert url, "".join(lines)
        assert _get(url + "api/health")[0] == 200
    finally:
        proc.kill()
        proc.communicate()

    def down() -> bool:
        try:
            urllib.request.urlopen(url, timeout=1)
        except urllib.error.URLError:
            return True
        return False

    assert wait_until(down, 15.0), "the page still serves after its sim was killed"


def test_the_view_stops_when_its_input_closes(tmp_path: Path) -> None:
    """``companion view --until-input-closes``: the end of its standard input ends it, exit 0."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "companion", "view", "--no-control", "--health-endpoint", f"ipc://{tmp_path}/h.sock",
         "--port", "0", "--until-input-closes"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
    )
    assert proc.stdin is not None and proc.stdout is not None
    try:
        for line in proc.stdout:
            if "companion view: open " in line:
                break
        proc.stdin.close()
        rc = proc.wait(timeout=15)
        out = proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
    assert rc == 0, out


def test_the_page_and_the_terminal_give_the_rig_check_when_near_cannot_be_measured(tmp_path: Path) -> None:
    """``process``, ``eval`` and ``run`` say when the rig cannot measure down to where the controller's
    near is full; the view said nothing, and its bars showed such a rig's regions as far. The service's
    health carries the rig check (``rig``), the page data has its lines, and the view prints them in its
    terminal, in the same words as the other tools."""
    from companion.core.rectifier import make_rectifier
    from companion.core.rig_check import check_rig, rig_check_lines

    # The ideal rig (f 336 px, B 0.12 m) with 32 disparities measures nothing nearer than 1.30 m: the
    # controller's near is full from 0.75 m.
    cfg = service_config(tmp_path, stereo={"num_disparities": 32})
    geometry = make_rectifier(cfg.calibration, cfg.camera.width_px, cfg.camera.height_px).geometry
    expected = rig_check_lines(check_rig(geometry, cfg.stereo, cfg.regions, cfg.controller))
    assert any("cannot be measured" in line for line in expected), expected
    service = Service(cfg, camera=avoid_scene_camera(15.0), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        with ViewProcess("--health-endpoint", cfg.bus.health_endpoint, "--no-control") as view:
            base = view.url.split("?", 1)[0].rstrip("/")

            def page_data() -> dict:
                status, body, _ = _get(base + "/api/health")
                assert status == 200, body
                return json.loads(body)

            assert wait_until(lambda: (page_data()["health"] or {}).get("rig") is not None, 60.0), page_data()
            data = page_data()
            rig = data["health"]["rig"]
            assert rig["lines"] == expected and rig["near_unmeasurable"] is True, rig
            assert rig["min_measurable_depth_m"] == pytest.approx(geometry.focal_baseline_px_m / 31, abs=1e-3)
            assert data["view"]["rig_lines"] == expected
            # The page shows them (an element of its own, filled from each health message).
            status, index, _ = _get(base + "/")
            assert status == 200 and b'id="rig"' in index
            # The terminal: the same words as `companion process` prints, once the service is heard.
            assert wait_until(lambda: all(f"companion view: {line}" in view.lines for line in expected), 30.0), view.lines
    # The default setting measures near enough: nothing to say.
    from companion.service.health import rig_status

    assert rig_status(service_config(tmp_path)) == {"min_measurable_depth_m": pytest.approx(40.32 / 63, abs=1e-3),
                                                    "near_unmeasurable": False, "lines": []}
