"""`companion ctl`, `companion watch` and `companion bench --e2e` against a running service."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from peers.fakes import FakeLink, ServiceRunner, avoid_scene_camera, service_config, wait_until

from companion.bench.common import BenchSize
from companion.cli import main
from companion.config import CompanionConfig
from companion.errors import CompanionError, InputError
from companion.service.client import parse_assignments, render_health
from companion.service.daemon import Service


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cli")
    cfg = service_config(tmp)
    svc = Service(cfg, camera=avoid_scene_camera(10.0), link=FakeLink(), install_signals=False, environ={})
    runner = ServiceRunner(svc).start()
    yield svc
    runner.stop()


def _ctl(svc: Service, *args: str) -> list[str]:
    return ["--log-level", "WARNING", "ctl", "--endpoint", svc.bus.control_endpoint, *args]


def test_ctl_commands(service: Service, capsys) -> None:
    assert main(_ctl(service, "ping")) == 0
    assert json.loads(capsys.readouterr().out)["pong"] is True
    assert main(_ctl(service, "status")) == 0
    assert json.loads(capsys.readouterr().out)["state"] == "passive"
    assert main(_ctl(service, "get", "planner")) == 0
    assert json.loads(capsys.readouterr().out)["config"]["cruise_speed_m_s"] == CompanionConfig().planner.cruise_speed_m_s
    assert main(_ctl(service, "set", "planner.cruise_speed_m_s=1.25", "controller.preferred_yaw_side=left")) == 0
    assert json.loads(capsys.readouterr().out)["changed"] == ["controller", "planner"]
    assert main(_ctl(service, "set", "planner.cruise_speed_m_s=-2")) == 2
    assert "planner.cruise_speed_m_s" in capsys.readouterr().err
    assert main(_ctl(service, "override", "--yaw", "0.5", "--duration", "2")) == 2
    assert "not engaged" in capsys.readouterr().err
    # engage as an operator would on a loaded machine: again while frames are not fresh yet
    assert wait_until(lambda: main(_ctl(service, "engage")) == 0 or service.supervisor.engaged, 60.0, poll_s=0.5)
    assert wait_until(lambda: service.supervisor.engaged, 3.0)
    capsys.readouterr()
    assert main(_ctl(service, "override", "--yaw", "0.5", "--speed", "0.2", "--duration", "0.5")) == 0
    assert json.loads(capsys.readouterr().out)["state"] == "override"
    for cmd in ("pause", "resume", "disengage"):
        assert main(_ctl(service, cmd)) == 0, cmd
    assert main(_ctl(service, "reload")) == 2
    assert "without --config" in capsys.readouterr().err


def test_ctl_without_a_service_says_so(tmp_path: Path, capsys) -> None:
    code = main(["--log-level", "WARNING", "ctl", "--endpoint", f"ipc://{tmp_path}/none.sock", "--timeout-s", "0.3", "ping"])
    assert code == 2 and "no reply from" in capsys.readouterr().err


def test_watch_json_and_screen(service: Service, capsys) -> None:
    assert main(["watch", "--endpoint", service.bus.health_endpoint, "--json", "--count", "2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and all(json.loads(line)["type"] == "health" for line in lines)
    assert main(["watch", "--endpoint", service.bus.health_endpoint, "--count", "1"]) == 0
    screen = capsys.readouterr().out
    assert "state " in screen and "regions (m):" in screen and "vehicle" in screen
    assert "center" not in render_health({"regions_m": {}})  # missing fields render as '--'


def test_parse_assignments() -> None:
    patch = parse_assignments(["a.b=1", "a.c=[0.5, 2.0]", "d.e=left", "a.f=true"])
    assert patch == {"a": {"b": 1, "c": [0.5, 2.0], "f": True}, "d": {"e": "left"}}
    for bad in ("novalue", "=3", "a..b=1"):
        with pytest.raises(InputError):
            parse_assignments([bad])


def test_e2e_bench_counts_frames_and_never_processes_one_twice(capsys) -> None:
    from companion.bench.e2e import run_e2e_bench

    args = argparse.Namespace(backend="opencv-bm", frames=15, warmup=3)
    report = run_e2e_bench(args, [BenchSize(320, 240, 32)])
    run = report["runs"]["320x240/32/opencv-bm"]
    assert run["samples"] == 15 and run["processed_twice"] == 0
    assert run["captured_frames"] >= run["processed_frames"] > 0
    assert run["dropped_frames"] >= 0 and run["latency_ms"]["p99_ms"] > 0
    assert "median ms" in capsys.readouterr().out


def test_viewer_cost_splits_latencies_by_the_subscription_of_their_window() -> None:
    from companion.bench.e2e import _SETTLE_SAMPLES, viewer_cost

    # 3 windows of 40 frames: unwatched 10 ms, watched 12 ms (the first few after each change skipped).
    lat_s = [0.010] * 40 + [0.012] * 40 + [0.010] * 40
    toggles = [(0, False), (40, True), (80, False)]
    cost = viewer_cost(lat_s, toggles, 0, 120)
    assert cost["watched"]["n"] == 40 - _SETTLE_SAMPLES and cost["unwatched"]["n"] == 80 - 2 * _SETTLE_SAMPLES
    assert cost["median_diff_ms"] == pytest.approx(2.0) and cost["p99_diff_ms"] == pytest.approx(2.0)
    lo, hi = cost["p99_diff_ci95_ms"]
    assert lo == pytest.approx(2.0) and hi == pytest.approx(2.0)
    with pytest.raises(CompanionError, match="too few samples"):
        viewer_cost(lat_s, [(0, True)], 0, 120)


def test_e2e_bench_alternates_the_viewer_and_compares_both_kinds_of_window(tmp_path: Path) -> None:
    from companion.bench.e2e import measure_e2e

    fig = measure_e2e(BenchSize(320, 240, 32), "opencv-bm", 150, 5, tmp_path, viewer="alternate", window_s=0.5)
    cost = fig["viewer_cost"]
    assert cost["windows"] >= 3 and cost["watched"]["n"] >= 10 and cost["unwatched"]["n"] >= 10
    assert fig["previews_received"] > 0
    assert np.isfinite(cost["p99_diff_ms"])
