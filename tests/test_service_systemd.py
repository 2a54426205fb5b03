"""The systemd unit, `companion install-service`, and sd_notify from a running service."""

from __future__ import annotations

import configparser
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from peers.fakes import FakeLink, ServiceRunner, avoid_scene_camera, service_config

from companion import exitcodes
from companion.config import load_config
from companion.config.document import render_default_toml
from companion.service.daemon import Service
from companion.service.install import DEFAULT_EXEC_START, install_service, render_unit
from companion.service.notify import Notifier, watchdog_interval_s

ROOT = Path(__file__).resolve().parent.parent
UNIT = ROOT / "systemd" / "companion.service"


def _unit_sections(text: str) -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # keys are case-sensitive
    parser.read_string(text)
    return parser


def test_committed_unit_is_the_generated_one() -> None:
    # Regenerate with tools/gen-systemd-unit.py after changing companion/service/install.py.
    assert UNIT.read_text(encoding="utf-8") == render_unit()


def test_unit_has_what_the_service_relies_on() -> None:
    text = UNIT.read_text(encoding="utf-8")
    unit = _unit_sections(text)
    s = unit["Service"]
    assert s["Type"] == "notify" and s["NotifyAccess"] == "main"
    assert s["ExecStart"] == DEFAULT_EXEC_START and "--config /etc/companion/companion.toml" in s["ExecStart"]
    assert s["ExecReload"] == "/bin/kill -HUP $MAINPID"
    assert s["Restart"] == "on-failure" and s["RestartPreventExitStatus"] == str(exitcodes.STARTUP_FAILURE)
    assert float(s["WatchdogSec"]) > 0
    assert s["User"] == "companion" and "video" in s["SupplementaryGroups"] and "dialout" in s["SupplementaryGroups"]
    for key in ("NoNewPrivileges", "ProtectSystem", "PrivateTmp", "ProtectHome"):
        assert key in s
    assert s["ProtectSystem"] == "strict" and s["DevicePolicy"] == "closed"
    assert "PrivateDevices" not in s
    allowed = [line.split("=", 1)[1] for line in text.splitlines() if line.startswith("DeviceAllow=")]
    for group in ("char-video4linux", "char-ttyTHS", "char-ttyACM", "char-ttyUSB", "char-nvidia*", "char-nvhost*"):
        assert f"{group} rw" in allowed
    # MAVSDK's log callback is a ctypes closure: W^X memory would kill it.
    assert "MemoryDenyWriteExecute" not in s


def test_systemd_analyze_verify(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed (Debian: apt-get install systemd)")
    # verify checks that ExecStart exists: point it at this interpreter, as install-service does.
    unit = tmp_path / "companion.service"
    unit.write_text(render_unit(f"{sys.executable} -m companion run --config /etc/companion/companion.toml"))
    out = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    problems = [line for line in (out.stdout + out.stderr).splitlines() if "companion.service" in line]
    assert out.returncode == 0 and not problems, out.stdout + out.stderr


def test_install_service_into_a_root(tmp_path: Path) -> None:
    steps = install_service(tmp_path, exec_start="/usr/bin/python3 -m companion run --config /etc/companion/companion.toml")
    unit = tmp_path / "etc/systemd/system/companion.service"
    config = tmp_path / "etc/companion/companion.toml"
    assert unit.read_text().count("ExecStart=/usr/bin/python3 -m companion run") == 1
    assert config.read_text() == render_default_toml()  # == config/companion.toml (tests/test_config.py)
    assert load_config(config).service.autostart is False
    assert any("skipped creating the user" in s.what for s in steps)
    # A second install keeps an edited config.
    config.write_text(config.read_text().replace("autostart = false", "autostart = true"))
    steps = install_service(tmp_path, exec_start="/usr/bin/python3 -m companion run")
    assert "autostart = true" in config.read_text()
    assert any("kept the existing" in s.what for s in steps)


def test_install_service_cli_dry_run_writes_nothing(tmp_path: Path, capsys) -> None:
    from companion.cli import main

    assert main(["install-service", "--root", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "would write" in out and "companion.service" in out and "companion.toml" in out
    assert list(tmp_path.iterdir()) == []


def test_notifier_and_watchdog_environment(tmp_path: Path) -> None:
    path = tmp_path / "n.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(path))
    n = Notifier.from_environment({"NOTIFY_SOCKET": str(path)})
    assert n is not None and n.notify("READY=1", "STATUS=a\nb")
    assert server.recv(100) == b"READY=1\nSTATUS=a b"
    server.close()
    assert not n.notify("WATCHDOG=1")  # the socket is gone: logged, not raised
    n.close()
    assert Notifier.from_environment({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000"}) == 2.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "x"}) is None
    assert watchdog_interval_s({}) is None


def test_watchdog_is_fed_by_the_control_loop_only_and_stops_when_it_stalls(tmp_path: Path) -> None:
    path = tmp_path / "n.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(path))
    server.settimeout(0.05)
    env = {"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "400000"}
    service = Service(service_config(tmp_path), camera=avoid_scene_camera(10.0), link=FakeLink(),
                      install_signals=False, environ=env)

    def drain() -> list[str]:
        lines = []
        while True:
            try:
                lines += server.recv(4096).decode().splitlines()
            except (TimeoutError, socket.timeout):
                return lines

    with ServiceRunner(service):
        time.sleep(0.6)
        lines = drain()
        assert "READY=1" in lines and lines.count("WATCHDOG=1") >= 4
        # Stall the control loop (as a hung step would): the watchdog stops while health goes on.
        original = service.control_loop.step
        release = threading.Event()

        async def stalled(now, ticked):
            import asyncio

            while not release.is_set():
                await asyncio.sleep(0.01)

        service.control_loop.step = stalled
        time.sleep(0.3)
        drain()
        time.sleep(0.6)
        assert "WATCHDOG=1" not in drain()
        service.control_loop.step = original
        release.set()
        deadline = time.monotonic() + 3.0
        fed = False
        while not fed and time.monotonic() < deadline:
            fed = "WATCHDOG=1" in drain()
        assert fed  # fed again once the loop runs
    server.close()


def test_startup_failure_when_the_endpoint_is_taken(tmp_path: Path) -> None:
    import asyncio

    import zmq

    ctx = zmq.Context()
    squatter = ctx.socket(zmq.REP)
    squatter.bind(f"ipc://{tmp_path}/control.sock")
    try:
        squatter2 = ctx.socket(zmq.REP)
        port = squatter2.bind_to_random_port("tcp://127.0.0.1")
        cfg = service_config(tmp_path, bus={"control_endpoint": f"tcp://127.0.0.1:{port}"})
        service = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
        assert asyncio.run(service.run()) == exitcodes.STARTUP_FAILURE
        assert "bus.control_endpoint" in service.health_message()["last_error"]
        squatter2.close(0)
    finally:
        squatter.close(0)
        ctx.destroy(linger=0)
