"""``companion process``: JSON out, an overlay, and one-line errors with exit code 2 for bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cli import main
from companion.core.geometry import StereoGeometry
from companion.sim.render import Box, Pose, Scene, StereoRenderer

DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("frames")
    geometry = StereoGeometry.ideal(672, 376, hfov_deg=90.0, baseline_m=0.12)
    box = Box.on_ground(1.5, -2.0, (1.0, 4.3, 6.0))  # blocks the centre and the left at 1 m
    r = StereoRenderer(geometry, Scene(obstacles=(box,)), seed=3).render(Pose.at(0.0, 0.0, 1.5))
    paths = {"sbs": d / "sbs.png", "left": d / "left.png", "right": d / "right.png"}
    cv2.imwrite(str(paths["sbs"]), r.side_by_side())
    cv2.imwrite(str(paths["left"]), r.left_bgr)
    cv2.imwrite(str(paths["right"]), r.right_bgr)
    return paths


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(["process", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_sbs_frame_prints_json_and_writes_the_overlay(rendered, tmp_path, capsys) -> None:
    overlay = tmp_path / "overlay.png"
    code, out, _ = _run(capsys, "--sbs", str(rendered["sbs"]), "--overlay", str(overlay))
    assert code == 0
    doc = json.loads(out)
    assert set(doc["regions_m"]) == {
        "up_left", "up", "up_right", "left", "center", "right", "down_left", "down", "down_right"
    }
    assert doc["regions_m"]["center"] == pytest.approx(1.0, rel=0.05)
    assert doc["decision"] == "avoid" and doc["yaw"] > 0.3
    assert doc["setpoint"]["yaw_rate_deg_s"] > 0
    assert "disparity_ms" in doc["timings_ms"] and "total_ms" in doc["timings_ms"]
    image = cv2.imread(str(overlay))
    # The view (376 rows), then the legend panel below it.
    assert image is not None and image.shape[1:] == (672, 3) and 376 + 40 < image.shape[0] < 376 + 160


def test_left_right_pair_gives_the_same_answer(rendered, capsys) -> None:
    _, out_sbs, _ = _run(capsys, "--sbs", str(rendered["sbs"]))
    _, out_pair, _ = _run(capsys, "--left", str(rendered["left"]), "--right", str(rendered["right"]))
    a, b = json.loads(out_sbs), json.loads(out_pair)
    assert a["regions_m"] == b["regions_m"] and a["decision"] == b["decision"]


def _assert_one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], lines[0]


def test_unreadable_image(tmp_path, capsys) -> None:
    bad = tmp_path / "not-an-image.png"
    bad.write_text("hello", encoding="utf-8")
    _assert_one_line_error(*_run(capsys, "--sbs", str(bad))[::2], "not a readable image", str(bad))
    _assert_one_line_error(*_run(capsys, "--sbs", str(tmp_path / "missing.png"))[::2], "no such file")


def test_left_right_size_mismatch(rendered, tmp_path, capsys) -> None:
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), cv2.imread(str(rendered["right"]))[:, :600])
    code, _, err = _run(capsys, "--left", str(rendered["left"]), "--right", str(small))
    _assert_one_line_error(code, err, "left and right differ", "672x376", "600x376")


def test_odd_side_by_side_width(rendered, tmp_path, capsys) -> None:
    odd = tmp_path / "odd.png"
    cv2.imwrite(str(odd), cv2.imread(str(rendered["sbs"]))[:, :-1])
    code, _, err = _run(capsys, "--sbs", str(odd))
    _assert_one_line_error(code, err, "odd")


def test_calibration_for_another_resolution(tmp_path, capsys) -> None:
    frame = tmp_path / "frame640.png"
    cv2.imwrite(str(frame), np.random.default_rng(0).integers(0, 255, (480, 1280, 3), dtype=np.uint8))
    code, _, err = _run(capsys, "--sbs", str(frame), "--calib", str(DATA / "SN000000.conf"))
    _assert_one_line_error(code, err, "640x480")


def test_invalid_config(rendered, tmp_path, capsys) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[stereo]\nnum_disparities = 70\n", encoding="utf-8")
    code, _, err = _run(capsys, "--sbs", str(rendered["sbs"]), "--config", str(cfg))
    _assert_one_line_error(code, err, "stereo.num_disparities", "70")


def test_non_monotone_lut(rendered, tmp_path, capsys) -> None:
    cfg = tmp_path / "lut.toml"
    cfg.write_text("[lut]\npoints_m = [[0.5, 0.5], [2.0, 1.9], [1.5, 3.0]]\n", encoding="utf-8")
    code, _, err = _run(capsys, "--sbs", str(rendered["sbs"]), "--config", str(cfg))
    _assert_one_line_error(code, err, "lut.points_m", "strictly increasing")


def test_console_script_exit_code_and_stderr(tmp_path) -> None:
    # Through a real process: exit status 2 and a single line, as a shell user sees it.
    bad = tmp_path / "x.png"
    bad.write_bytes(b"\x89PNG broken")
    proc = subprocess.run(
        [sys.executable, "-m", "companion", "process", "--sbs", str(bad)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "not a readable image" in proc.stderr


def test_a_rig_that_cannot_measure_the_near_threshold_is_said_with_its_own_numbers(rendered, tmp_path, capsys) -> None:
    """A real pair (f 995 px, baseline 0.193 m, 64 disparities: nothing nearer than about 3 m is
    measurable) gave "clear" with a motorcycle 2.2 m ahead, exit 0 and no word; the service refuses
    that rig, and ``eval`` warned. ``process`` now says so, with the file's focal, not the default rig's."""
    calib = tmp_path / "long-baseline.npz"
    K = np.array([[995.0, 0.0, 336.0], [0.0, 995.0, 188.0], [0.0, 0.0, 1.0]])
    np.savez(calib, K1=K, D1=np.zeros(5), K2=K, D2=np.zeros(5), R=np.eye(3), T=np.array([-0.193, 0.0, 0.0]),
             image_size=np.array([672, 376]))
    code, out, err = _run(capsys, "--sbs", str(rendered["sbs"]), "--calib", str(calib))
    assert code == 0
    doc = json.loads(out)
    assert doc["min_measurable_depth_m"] == pytest.approx(995.0 * 0.193 / 63, rel=0.01)
    assert doc["near_unmeasurable"] is True and doc["rig_check"]["errors"]
    assert "rig check: error:" in err and "f = 995 px" in err and "f = 336 px" not in err
    assert "Traceback" not in err
    if doc["decision"] == "clear":
        assert "would not be seen" in err
    # far regions are flagged: nothing nearer than the limit could have been measured
    assert set(doc["far_regions_unverified"]) <= set(doc["regions_m"])


def test_the_default_rig_reports_its_nearest_measurable_depth(rendered, capsys) -> None:
    code, out, _ = _run(capsys, "--sbs", str(rendered["sbs"]))
    doc = json.loads(out)
    assert code == 0 and 0.0 < doc["min_measurable_depth_m"] < 0.75 and "near_unmeasurable" not in doc


def test_a_folder_given_as_an_image_is_named_as_one(tmp_path, capsys) -> None:
    code, _, err = _run(capsys, "--left", str(tmp_path), "--right", str(tmp_path))
    assert code == 2 and "a folder, not an image file" in err and len(err.strip().splitlines()) == 1
