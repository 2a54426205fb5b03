"""The SITL harness's pure parts (CI has no PX4): where it finds PX4, the ports, the service's config."""

from __future__ import annotations

import asyncio
import math
import os
import socket
import tomllib
from pathlib import Path

import pytest

from companion.config import load_config, parse_config
from companion.config.document import render_config_toml
from companion.sim.courses import head_on_course, make_course
from companion.core.placement import CoursePlacement
from companion.config import apply_patch
from companion.sitl.flight import placement_patch, sitl_config
from companion.sitl.px4 import PX4_BUILD_ENV, Px4Ports, SitlError, find_px4_build
from companion.sitl.service import ServiceProcess


def test_px4_build_is_found_from_the_argument_or_the_environment(tmp_path: Path) -> None:
    assert find_px4_build(None, environ={}) is None
    with pytest.raises(SitlError, match="not a PX4 SITL build folder"):
        find_px4_build(None, environ={PX4_BUILD_ENV: str(tmp_path)})
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin/px4").touch()
    (tmp_path / "etc/init.d-posix").mkdir(parents=True)
    (tmp_path / "etc/init.d-posix/rcS").touch()
    assert find_px4_build(None, environ={PX4_BUILD_ENV: str(tmp_path)}) == tmp_path.resolve()
    assert find_px4_build(tmp_path, environ={}) == tmp_path.resolve()


def test_ports_follow_px4s_startup_script() -> None:
    p = Px4Ports(3)
    assert (p.api_port, p.system_id, p.service_url) == (14543, 4, "udpin://127.0.0.1:14543")
    assert Px4Ports(0).pilot_url == "udpin://127.0.0.1:14550"


def test_the_service_config_renders_the_course_from_telemetry_and_round_trips(tmp_path: Path) -> None:
    user = parse_config({"planner": {"cruise_speed_m_s": 0.8}, "service": {"autostart": True}})
    placement = CoursePlacement((1.0, -2.0, -0.3), math.radians(30.0))
    cfg = sitl_config(user, make_course("forest", 5), placement, "udpin://127.0.0.1:14541", tmp_path)
    cam = cfg.camera
    assert (cam.source, cam.sim_world, cam.sim_course, cam.sim_course_seed, cam.sim_pose) == ("sim", "course", "forest", 5, "telemetry")
    assert (cam.sim_origin_north_m, cam.sim_origin_east_m, cam.sim_origin_down_m) == (1.0, -2.0, -0.3)
    assert cam.sim_origin_yaw_deg == pytest.approx(30.0)
    assert (cam.width_px, cam.height_px, cam.fps_hz) == (user.sim.eye_width_px, user.sim.eye_height_px, user.sim.camera_rate_hz)
    assert cfg.vehicle.connection == "udpin://127.0.0.1:14541"
    assert cfg.bus.control_endpoint == f"ipc://{tmp_path}/control.sock"
    assert cfg.service.autostart is False  # engaged by the harness's request, as a user would
    assert cfg.planner.cruise_speed_m_s == 0.8  # the user's tuning flies
    # What the harness writes for `companion run` loads back to the same config.
    assert parse_config(tomllib.loads(render_config_toml(cfg, ["# test"]))) == cfg


def test_sitl_cli_rejects_bad_arguments_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from companion.cli import main

    assert main(["sitl", "--course", "doorway", "--instance", "12"]) == 2
    assert "--instance must be 0..9" in capsys.readouterr().err
    assert main(["sitl", "--suite", "quick", "--plot", "x.png"]) == 2
    assert "--plot goes with --course" in capsys.readouterr().err
    assert main(["sitl", "--course", "nowhere"]) == 2
    assert "unknown course" in capsys.readouterr().err
    assert load_config(None).camera.sim_pose == "fixed"  # the default service is untouched


def test_placement_fields_are_the_inverse_of_placement_from_config() -> None:
    from companion.service.camera_sim import placement_fields, placement_from_config

    placement = CoursePlacement((1.5, -2.0, -0.3), math.radians(-120.0))
    cfg = parse_config({"camera": placement_fields(placement)})
    back = placement_from_config(cfg)
    assert back.origin_ned_m == placement.origin_ned_m
    assert back.yaw_rad == pytest.approx(placement.yaw_rad)


def test_the_service_process_keeps_every_health_message_in_its_workdir(tmp_path: Path) -> None:
    import asyncio
    import json

    from companion.sitl.service import ServiceProcess

    service = ServiceProcess(load_config(None), tmp_path)
    sent = [{"type": "health", "seq": k, "state": "engaged"} for k in range(3)]
    service.health_history.extend((float(k), h) for k, h in enumerate(sent))
    assert asyncio.run(service.stop()) is None  # never started: nothing to stop, the log is written
    lines = (tmp_path / "health.jsonl").read_text().splitlines()
    assert [json.loads(line) for line in lines] == sent


def test_the_flight_log_names_what_drove_each_row() -> None:
    import numpy as np

    from companion.sim.loop import LogKind
    from companion.sitl.flight import _Recorder
    from companion.sitl.pilot import Sample

    course = make_course("doorway", 0)
    placement = CoursePlacement((0.0, 0.0, -1.5), 0.0)

    def sample(t: float, mode: str = "OFFBOARD") -> Sample:
        return Sample(t, np.array([0.1 * t, 0.0, -1.5]), np.array([0.1, 0.0, 0.0]), np.zeros(3), 0.0, mode)

    rec = _Recorder(course, load_config(None), placement, sample(0.0))
    health = [
        {"state": "engaged", "decision": {"kind": "clear"}},
        {"state": "engaged", "decision": {"kind": "avoid"}},
        {"state": "degraded", "decision": {"kind": "clear"}},
        {"state": "paused", "decision": {"kind": "clear"}},  # the progress watchdog's hold
        {"state": "engaged", "decision": {"kind": "clear"}},
    ]
    for k, h in enumerate(health):
        rec.add(sample(0.05 * k, "HOLD" if k == 4 else "OFFBOARD"), h)
    assert rec.log().kind.tolist() == [LogKind.CLEAR, LogKind.AVOID, LogKind.STALE, LogKind.BRAKE, LogKind.HOLD]


def test_a_suite_flies_a_course_again_with_a_fresh_px4_when_a_step_failed(tmp_path: Path, monkeypatch) -> None:
    """SIH sometimes starts without baro or compass data and lands: with a PX4 build the harness
    starts another PX4 and flies that course once more; a second failure ends the suite, named."""
    import asyncio

    import companion.sitl.flight as flight_mod

    events: list[str] = []

    class FakePx4:
        def __init__(self, build, workdir, instance) -> None:
            self.workdir = workdir

        def start(self) -> None:
            events.append(f"start {self.workdir.relative_to(tmp_path)}")

        def stop(self) -> None:
            events.append("stop")

    class FakePilot:
        def __init__(self, url, system_id) -> None:
            pass

        async def connect(self) -> None:
            pass

        async def close(self) -> None:
            pass

    fails = {"doorway-0": 1, "forest-0": 2}

    async def fake_fly(course, cfg, pilot, ports, workdir, **kw):
        if fails.get(course.name, 0):
            fails[course.name] -= 1
            raise SitlError("the service refused 'engage': vehicle is disarmed")
        events.append(f"flew {course.name}")
        return course.name

    monkeypatch.setattr(flight_mod, "Px4Sitl", FakePx4)
    monkeypatch.setattr(flight_mod, "Pilot", FakePilot)
    monkeypatch.setattr(flight_mod, "fly_course", fake_fly)
    courses = [make_course("corridor", 0), make_course("doorway", 0), make_course("forest", 0)]
    ports = Px4Ports(0)

    async def suite():
        return await flight_mod.fly_courses(courses, load_config(None), ports=ports, pilot_url="udpin://x", workdir=tmp_path, px4_build=tmp_path)

    with pytest.raises(SitlError, match="^forest-0: the service refused"):
        asyncio.run(suite())
    assert events == [
        "start 00-corridor-0/px4", "flew corridor-0", "stop",
        "start 01-doorway-0/px4", "stop", "start 01-doorway-0/retry/px4", "flew doorway-0", "stop",
        "start 02-forest-0/px4", "stop", "start 02-forest-0/retry/px4", "stop",
    ]  # fmt: skip


def test_the_service_config_accepts_every_course_the_harness_flies() -> None:
    # camera.sim_course is a Literal of its own (the config does not import the simulator); every kind
    # of the suites, and the harness's extra courses, must be in it, or `companion sitl` fails at that course.
    import typing

    from companion.config.service import CameraConfig
    from companion.sim.courses import COURSE_KINDS

    allowed = set(typing.get_args(CameraConfig.model_fields["sim_course"].annotation))
    assert set(COURSE_KINDS) | {"head-on", "wall"} <= allowed


def test_the_planner_s_band_moves_with_the_course_ground() -> None:
    """The course's ground lies where the hover put it, not at PX4's take-off point: the placement
    patch keeps the user's floor and ceiling (planner.floor_m, ceiling_m) at their height over the
    ground the camera sees and the judge scores. The hover put the course's ground 0.17-0.19 m above
    the take-off ground in a PX4 SITL office flight; a 3 m ceiling left at the take-off point stood
    0.6 m over an office's 3 m walls in another, and the planner climbed over them into the top."""
    user = parse_config({})
    course = make_course("office", 0)
    # hovering 0.17 m above the course's start altitude: the course's ground is 0.17 m above the origin
    above = CoursePlacement((1.0, 2.0, -0.17), 0.3)
    patch = placement_patch(user, above)
    assert set(patch) == {"camera", "planner"}
    placed = apply_patch(sitl_config(user, course, above, "udpin://127.0.0.1:14541", Path("/tmp")), patch)
    assert placed.camera.sim_origin_down_m == -0.17
    assert placed.planner.floor_m == pytest.approx(user.planner.floor_m + 0.17)
    assert placed.planner.ceiling_m == pytest.approx(user.planner.ceiling_m + 0.17)
    # below the start altitude: the band comes down with the ground, the floor never below 0
    low = placement_patch(user, CoursePlacement((0.0, 0.0, 0.6), 0.0))["planner"]
    assert low == {"floor_m": 0.0, "ceiling_m": pytest.approx(user.planner.ceiling_m - 0.6)}


# ---------------------------------------------------------------- what the harness starts, it stops


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _service(workdir: Path) -> ServiceProcess:
    """The service as the harness starts it, its vehicle link on a port no autopilot sends to: it
    never becomes ready."""
    course = head_on_course(0)
    url = f"udpin://127.0.0.1:{_free_udp_port()}"
    cfg = sitl_config(load_config(None), course, CoursePlacement((0.0, 0.0, 0.0), 0.0), url, workdir, 1)
    return ServiceProcess(cfg, workdir)


def _gone(pid: int | None) -> bool:
    assert pid is not None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_a_service_that_is_not_ready_in_time_is_stopped(tmp_path: Path) -> None:
    """No autopilot answers: the start fails naming why, and the service's process is gone (a failed
    engage once left it running beside the next test's)."""
    service = _service(tmp_path)

    async def scenario() -> None:
        with pytest.raises(SitlError, match="not ready|exited"):
            await service.start(timeout_s=2.0)

    asyncio.run(scenario())
    assert _gone(service.pid)


def test_the_service_keeps_its_temporary_files_in_its_workdir(tmp_path: Path) -> None:
    """MAVSDK leaves a folder of component metadata in the temporary directory of every run; a
    service the harness kills must not leave it in the machine's /tmp."""
    service = _service(tmp_path)
    seen: list[str] = []

    async def scenario() -> None:
        # A start that never ends by itself (no autopilot answers) is cancelled once the environment
        # has been read: a loaded machine cannot end it before the reading, and a cancelled start
        # stops the process.
        start = asyncio.get_running_loop().create_task(service.start(timeout_s=3600.0))
        while service.pid is None and not start.done():
            await asyncio.sleep(0.01)
        if service.pid is not None:
            environ = Path(f"/proc/{service.pid}/environ").read_bytes().split(b"\0")
            seen.extend(e.decode() for e in environ if e.startswith(b"TMPDIR="))
        start.cancel()
        with pytest.raises(asyncio.CancelledError):
            await start

    asyncio.run(scenario())
    assert seen == [f"TMPDIR={tmp_path / 'tmp'}"]
    assert _gone(service.pid)


def test_a_cancelled_start_stops_the_service(tmp_path: Path) -> None:
    """The caller gives up (a test's overall timeout cancels the task): the process still goes."""
    service = _service(tmp_path)

    async def scenario() -> None:
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(service.start(timeout_s=60.0), 2.0)

    asyncio.run(scenario())
    assert _gone(service.pid)
