"""The ArduPilot SITL harness's parts that need no ArduPilot (CI has none): where it finds the build, the
ports, the command line, the suite loop, and the MAVLink gate the SITL tests put on the service's link."""

from __future__ import annotations

import asyncio
import struct
from pathlib import Path

import pytest
from peers.mavlink_gate import MSG_ATTITUDE, MSG_LOCAL_POSITION_NED, MavlinkGate, decode_command, decode_setpoint, split_frames
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.sim.courses import make_course
from companion.sitl.ardupilot import (
    ARDUPILOT_BUILD_ENV,
    CENTRED_STICKS_US,
    PITCH_FORWARD_US,
    ArduPilotPorts,
    ArduPilotSitl,
    centre_sticks,
    find_ardupilot_build,
)
from companion.sitl.px4 import SitlError


def _fake_checkout(root: Path) -> Path:
    (root / "build/sitl/bin").mkdir(parents=True)
    (root / "build/sitl/bin/arducopter").touch()
    (root / "Tools/autotest/default_params").mkdir(parents=True)
    (root / "Tools/autotest/default_params/copter.parm").touch()
    return root


def test_the_ardupilot_build_is_found_from_the_argument_or_the_environment(tmp_path: Path) -> None:
    assert find_ardupilot_build(None, environ={}) is None
    with pytest.raises(SitlError, match="not an ArduPilot checkout with a SITL build"):
        find_ardupilot_build(None, environ={ARDUPILOT_BUILD_ENV: str(tmp_path)})
    root = _fake_checkout(tmp_path / "ardupilot")
    build = find_ardupilot_build(None, environ={ARDUPILOT_BUILD_ENV: str(root)})
    assert build is not None and build.binary == root.resolve() / "build/sitl/bin/arducopter"
    assert find_ardupilot_build(root / "build/sitl", environ={}).root == root.resolve()  # the build folder works too


def test_ports_follow_ardupilot_sitl_instances() -> None:
    p = ArduPilotPorts(2)
    assert (p.pilot_port, p.api_port, p.rc_port, p.system_id) == (5780, 5782, 5521, 1)
    assert (p.service_url, p.pilot_url) == ("tcpout://127.0.0.1:5782", "tcpout://127.0.0.1:5780")


def test_centred_sticks_go_to_sitls_rc_port() -> None:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(2.0)
        centre_sticks(rx.getsockname()[1])
        data = rx.recv(64)
    assert struct.unpack("<8H", data) == CENTRED_STICKS_US
    assert CENTRED_STICKS_US[2] == 1500  # throttle centred: LOITER holds its altitude


def test_the_pitch_stick_goes_forward_on_channel_2_alone() -> None:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(2.0)
        centre_sticks(rx.getsockname()[1], pitch_us=PITCH_FORWARD_US)
        data = rx.recv(64)
    want = list(CENTRED_STICKS_US)
    want[1] = PITCH_FORWARD_US
    assert struct.unpack("<8H", data) == tuple(want)


def test_boot_parameters_go_to_a_defaults_file_after_copter_parm(tmp_path: Path, monkeypatch) -> None:
    """PRX1_TYPE takes effect only at boot: the proximity scenario's parameters are a second defaults file."""
    import subprocess

    build = find_ardupilot_build(_fake_checkout(tmp_path / "ardupilot"), environ={})
    seen: dict = {}

    class FakeProc:
        returncode = None

        def __init__(self, cmd, **kw):
            seen["cmd"] = cmd
            (kw["cwd"] / "arducopter.log").write_bytes(b"Waiting for connection")

        def poll(self):
            return None

    monkeypatch.setattr(subprocess, "Popen", FakeProc)
    sitl = ArduPilotSitl(build, tmp_path / "sitl", 5, boot_params={"PRX1_TYPE": 2, "AVOID_MARGIN": 2.5})
    sitl.start(timeout_s=2.0)
    defaults = seen["cmd"][seen["cmd"].index("--defaults") + 1].split(",")
    assert defaults == [str(build.defaults), str(tmp_path / "sitl/companion.parm")]
    assert (tmp_path / "sitl/companion.parm").read_text() == "PRX1_TYPE 2\nAVOID_MARGIN 2.5\n"


def test_sitl_cli_keeps_each_scenario_with_its_autopilot(capsys: pytest.CaptureFixture[str]) -> None:
    from companion.cli import main

    assert main(["sitl", "--scenario", "proximity"]) == 2
    assert "--scenario proximity flies ArduPilot" in capsys.readouterr().err
    assert main(["sitl", "--scenario", "collision-prevention", "--autopilot", "ardupilot"]) == 2
    assert "collision-prevention and rc-engage fly PX4" in capsys.readouterr().err


def test_sitl_cli_keeps_each_build_with_its_autopilot(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    from companion.cli import main

    assert main(["sitl", "--course", "doorway", "--autopilot", "ardupilot", "--px4-build", str(tmp_path)]) == 2
    assert "--px4-build goes with --autopilot px4" in capsys.readouterr().err
    assert main(["sitl", "--course", "doorway", "--autopilot", "ardupilot", "--ardupilot-build", str(tmp_path)]) == 2
    assert "not an ArduPilot checkout" in capsys.readouterr().err


def test_an_ardupilot_suite_starts_a_fresh_sitl_per_course(tmp_path: Path, monkeypatch) -> None:
    import companion.sitl.flight as flight_mod

    events: list[str] = []

    class FakeSitl:
        def __init__(self, build, workdir, instance) -> None:
            self.workdir = workdir

        def start(self) -> None:
            events.append(f"start {self.workdir.relative_to(tmp_path)}")

        def stop(self) -> None:
            events.append("stop")

    class FakePilot:
        def __init__(self, url, system_id, rc_port=None) -> None:
            events.append(f"pilot {url} {system_id} rc {rc_port}")

        async def connect(self) -> None:
            pass

        async def close(self) -> None:
            pass

    async def fake_fly(course, cfg, pilot, ports, workdir, **kw):
        events.append(f"flew {course.name} via {kw.get('service_url') or ports.service_url}")
        return course.name

    monkeypatch.setattr(flight_mod, "ArduPilotSitl", FakeSitl)
    monkeypatch.setattr(flight_mod, "ArduPilotPilot", FakePilot)
    monkeypatch.setattr(flight_mod, "fly_course", fake_fly)
    ports = ArduPilotPorts(1)
    courses = [make_course("corridor", 0), make_course("doorway", 0)]
    flown = asyncio.run(
        flight_mod.fly_courses(courses, load_config(None), ports=ports, pilot_url=ports.pilot_url, workdir=tmp_path, ardupilot_build=object())
    )
    assert flown == ["corridor-0", "doorway-0"]
    assert events == [
        "start 00-corridor-0/ardupilot", "pilot tcpout://127.0.0.1:5770 1 rc 5511",
        "flew corridor-0 via tcpout://127.0.0.1:5772", "stop",
        "start 01-doorway-0/ardupilot", "pilot tcpout://127.0.0.1:5770 1 rc 5511",
        "flew doorway-0 via tcpout://127.0.0.1:5772", "stop",
    ]  # fmt: skip


def _mav() -> mavlink.MAVLink:
    m = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return m


def test_the_gate_cuts_frames_and_decodes_setpoints_and_commands() -> None:
    m = _mav()
    sp = m.set_position_target_local_ned_encode(7, 1, 1, mavlink.MAV_FRAME_BODY_NED, 0x05C7, 0, 0, 0, 0.7, 0.0, 0.0, 0, 0, 0, 0, 0.0).pack(m)
    zero = m.set_position_target_local_ned_encode(8, 1, 1, mavlink.MAV_FRAME_BODY_NED, 0x05C7, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0).pack(m)
    cmd = m.command_long_encode(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0).pack(m)
    stream = b"\x00junk" + sp + zero + cmd
    buf = bytearray()
    frames = []
    for i in range(0, len(stream), 7):  # in pieces, as TCP delivers them
        buf += stream[i : i + 7]
        frames += split_frames(buf)
    assert buf == bytearray() and [f[0] for f in frames] == [-1, 84, 84, 76]
    assert b"".join(f[2] for f in frames) == stream  # nothing lost or reordered
    s = decode_setpoint(1.0, frames[1][1])
    assert (s.frame, s.type_mask, s.vx, s.yaw_rate, s.is_zero) == (mavlink.MAV_FRAME_BODY_NED, 0x05C7, pytest.approx(0.7), 0.0, False)
    assert decode_setpoint(1.0, frames[2][1]).is_zero  # MAVLink 2 trimmed its zero bytes
    c = decode_command(2.0, frames[3][1])
    assert (c.command, c.params[:2]) == (mavlink.MAV_CMD_DO_SET_MODE, (1.0, 4.0))


def test_the_gate_drops_blocked_messages_towards_the_service_only() -> None:
    async def scenario() -> list[int]:
        m = _mav()
        ready = asyncio.Event()
        got: list[int] = []

        async def autopilot(reader, writer) -> None:
            for _ in range(3):
                writer.write(m.local_position_ned_encode(0, 0, 0, 0, 0, 0, 0).pack(m))
                writer.write(m.attitude_encode(0, 0, 0, 0, 0, 0, 0).pack(m))
            await writer.drain()
            ready.set()
            await asyncio.sleep(0.5)
            writer.close()

        server = await asyncio.start_server(autopilot, "127.0.0.1", 0)
        gate = await MavlinkGate(server.sockets[0].getsockname()[1], blocked={MSG_LOCAL_POSITION_NED}).start()
        reader, writer = await asyncio.open_connection("127.0.0.1", gate.port)
        writer.write(m.set_position_target_local_ned_encode(0, 1, 1, 8, 0x05C7, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0).pack(m))
        await writer.drain()
        await ready.wait()
        buf = bytearray()
        deadline = asyncio.get_running_loop().time() + 2.0
        while len(got) < 3 and asyncio.get_running_loop().time() < deadline:
            buf += await asyncio.wait_for(reader.read(4096), 2.0)
            got += [f[0] for f in split_frames(buf)]
        assert len(gate.setpoints) == 1 and gate.setpoints[0].vx == 1.0
        writer.close()
        await gate.close()
        server.close()
        return got

    assert asyncio.run(scenario()) == [MSG_ATTITUDE] * 3
