"""A new user's first hour on a busy laptop: the runtime directory, clients without a service, and the
command line's one-line errors.

Each test is one thing a new user hit: sockets from an earlier run found in the shared /tmp folder, a
socket file left by a stopped service blamed on CURVE keys after a 3 s wait, a traceback for
``--endpoint nonsense``, ``--timeout-s -1`` waiting forever.
"""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import pytest

from companion import exitcodes
from companion.cli import main
from companion.errors import ConfigError
from companion.service.runtime import candidate_sockets, check_listening, find_socket


def _stale_socket(path: Path) -> None:
    """A socket file with no process listening on it (what a killed service leaves)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.close()  # the file stays; nobody listens


def test_each_test_has_a_runtime_directory_of_its_own() -> None:
    xdg = os.environ["XDG_RUNTIME_DIR"]
    assert Path(xdg).is_dir() and xdg != f"/run/user/{os.getuid()}"
    assert "RUNTIME_DIRECTORY" not in os.environ


def test_a_client_with_xdg_runtime_dir_never_looks_in_the_shared_tmp_folder(tmp_path: Path) -> None:
    places = candidate_sockets("control", {"XDG_RUNTIME_DIR": str(tmp_path)})
    assert places[-1] == tmp_path / "companion" / "control.sock"
    assert not any(str(p).startswith("/tmp/companion-") for p in places)
    # without XDG_RUNTIME_DIR the service falls back to /tmp, and so does the client
    assert str(candidate_sockets("control", {})[-1]).startswith("/tmp/companion-")


def test_a_socket_with_no_service_behind_it_is_reported_at_once(tmp_path: Path) -> None:
    env = {"XDG_RUNTIME_DIR": str(tmp_path)}
    _stale_socket(tmp_path / "companion" / "control.sock")
    with pytest.raises(ConfigError, match="no running service at .*control.sock"):
        find_socket("control", env)
    check_listening(f"ipc://{tmp_path}/nothing-here.sock")  # not there yet: a waiting client connects later


def test_ctl_on_a_stale_socket_says_no_running_service_without_waiting(capsys: pytest.CaptureFixture[str]) -> None:
    _stale_socket(Path(os.environ["XDG_RUNTIME_DIR"]) / "companion" / "control.sock")
    t0 = time.monotonic()
    assert main(["ctl", "--timeout-s", "30", "ping"]) == exitcodes.BAD_INPUT
    err = capsys.readouterr().err
    assert "no running service" in err and "CURVE" not in err and len(err.strip().splitlines()) == 1
    assert time.monotonic() - t0 < 20.0  # at once, not after the 30 s timeout (generous for a loaded machine)


@pytest.mark.parametrize(
    "argv, words",
    [
        (["ctl", "--endpoint", "nonsense", "ping"], "--endpoint 'nonsense': not a ZeroMQ endpoint"),
        (["watch", "--endpoint", "nonsense"], "--endpoint 'nonsense': not a ZeroMQ endpoint"),
        (["ctl", "--endpoint", "tcp://127.0.0.1:99999", "ping"], "not a ZeroMQ endpoint"),
        (["ctl", "--timeout-s", "-1", "ping"], "--timeout-s -1: must be a number of seconds > 0"),
        (["ctl", "--timeout-s", "nan", "ping"], "--timeout-s nan: must be"),
        (["watch", "--timeout-s", "0"], "--timeout-s 0: must be"),
        (["view", "--health-endpoint", "nonsense", "--port", "0"], "--health-endpoint 'nonsense': not a ZeroMQ endpoint"),
        (["view", "--control-endpoint", "tcp://:x", "--port", "0"], "--control-endpoint 'tcp://:x': not a ZeroMQ endpoint"),
    ],
)
def test_endpoints_and_timeouts_get_one_line_and_exit_2(argv: list[str], words: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == exitcodes.BAD_INPUT
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


def test_the_service_keeps_its_sockets_in_its_runtime_directory_and_removes_them(private_runtime_dir: str) -> None:
    """Every socket file, the relay's private one too, lies in the runtime directory (systemd removes
    it when the service stops, even killed): nothing is left in /tmp, and a clean stop empties it."""
    from companion.config.service import BusConfig
    from companion.service.bus import Bus

    bus = Bus(BusConfig())
    bus.open()
    try:
        folder = Path(private_runtime_dir) / "companion"
        files = sorted(p.name for p in folder.iterdir() if not p.is_dir())
        (private,) = [p for p in folder.iterdir() if p.is_dir()]
        assert files == ["control.sock", "health.sock"]
        assert private.stat().st_mode & 0o077 == 0  # the router's folder: private
        assert [p.name for p in private.iterdir()] == ["router.sock"]
    finally:
        bus.close()
    assert list(folder.iterdir()) == []


def test_view_without_a_service_says_so_in_the_terminal() -> None:
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-m", "companion", "view", "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        lines = []
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if "no running service" in line or len(lines) > 10:
                break
        assert any("no running service at ipc://" in line for line in lines), lines
    finally:
        proc.terminate()
        proc.wait(30)


def test_bench_says_what_it_is_doing(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--frames", "1", "--warmup", "0", "--sizes", "160x120:16", "--no-rectify"]) == 0
    err = capsys.readouterr().err
    assert "companion bench: 160x120/16: timing 0 + 1 frames..." in err and "the renderer" in err


def test_an_unexpected_error_is_one_line_without_a_traceback(monkeypatch, capsys: pytest.CaptureFixture[str]) -> None:
    import companion.cli.process as process

    def boom(args):
        raise RuntimeError("something no one foresaw")

    monkeypatch.setattr(process, "run", boom)
    from companion.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["process", "--sbs", "x.png"])
    assert args.func is boom or True  # set_defaults captured the original: call through main below
    monkeypatch.setattr("companion.cli.build_parser", lambda: _parser_with(parser, boom))
    assert main(["process", "--sbs", "x.png"]) == exitcodes.INTERNAL_ERROR
    err = capsys.readouterr().err
    assert "internal error: RuntimeError: something no one foresaw" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def _parser_with(parser, func):
    for action in parser._subparsers._group_actions:  # noqa: SLF001
        action.choices["process"].set_defaults(func=func)
    return parser


def test_sim_help_lists_every_course_it_flies(capsys: pytest.CaptureFixture[str]) -> None:
    from companion.sim.courses import COURSE_KINDS

    with pytest.raises(SystemExit):
        main(["sim", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for kind in (*COURSE_KINDS, "head-on", "wall"):
        assert kind in text, kind


def test_view_help_names_the_sockets_it_really_follows(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["view", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "5560" not in text and "5561" not in text and "5562" not in text
    assert "$XDG_RUNTIME_DIR/companion" in text


def test_sim_and_demo_check_the_rig_they_fly_in_the_words_every_tool_uses(tmp_path: Path, capsys) -> None:
    from companion.config import CompanionConfig
    from companion.sim.loop import simulated_rig_check_lines

    few = CompanionConfig().model_copy(update={"stereo": CompanionConfig().stereo.model_copy(update={"num_disparities": 16})})
    lines = simulated_rig_check_lines(few)
    sim = few.sim
    assert lines and all(line.startswith("rig check: ") for line in lines)
    assert f"{sim.eye_width_px}x{sim.eye_height_px} px" in lines[0] and "the nearest depth this rig can measure" in lines[0]
    config = tmp_path / "few.toml"
    config.write_text("[stereo]\nnum_disparities = 32\n[calibration]\nideal_baseline_m = 0.2\n")
    assert main(["sim", "--course", "no-such-course", "--config", str(config)]) == exitcodes.BAD_INPUT
    err = capsys.readouterr().err
    assert "companion sim: rig check: " in err and "unknown course" in err


def test_eval_given_a_folder_as_an_image_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import cv2
    import numpy as np

    cv2.imwrite(str(tmp_path / "r.png"), np.zeros((20, 40), np.uint8))
    np.save(tmp_path / "d.npy", np.ones((20, 40), np.float32))
    code = main(["eval", "--left", str(tmp_path), "--right", str(tmp_path / "r.png"), "--gt-disparity", str(tmp_path / "d.npy")])
    err = capsys.readouterr().err
    assert code == exitcodes.BAD_INPUT and "a folder, not an image file" in err and len(err.strip().splitlines()) == 1


def test_the_overlay_labels_use_the_legend_s_three_colours() -> None:
    from companion.core.overlay import _FAR, _MID, _NEAR, _depth_colour

    colours = {_depth_colour(d, 0.75, 2.25) for d in (0.1, 0.75, 0.8, 1.0, 1.5, 2.2, 2.25, 9.0, float("nan"))}
    assert colours == {_NEAR, _MID, _FAR}
