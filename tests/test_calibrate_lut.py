"""``companion calibrate lut``: the paper's depth table measured on rendered targets at known distances,
with a deliberate scale error (the config's rig says 0.105 m, the renderer's is 0.12 m) to correct."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from calib_data import LUT_GEOMETRY, write_lut_captures
from companion.backends import make_pipeline
from companion.calib.lut import read_distances_csv
from companion.cli import main
from companion.config import load_config, parse_config
from companion.config.edit import set_config_value
from companion.core.lut import DepthLUT, fit_lut
from companion.core.types import REGION_INDEX
from companion.errors import ConfigError, InputError
from companion.sim.render import Box, Pose, Scene, StereoRenderer

#: The config's rig is 12.5 % short of the rendered one: every depth reads 12.5 % near.
CONFIG = "# my rig\n[calibration]\nideal_baseline_m = 0.105  # deliberately wrong\n"


def _centre_depth(cfg, distance_m: float) -> float:
    """The centre region's depth after the LUT, through the service's pipeline, for a target at
    ``distance_m`` that the fit never saw."""
    scene = Scene(obstacles=(Box.on_ground(8.05, 0.0, (0.1, 4.0, 3.0)),), ground=True)
    frame = StereoRenderer(LUT_GEOMETRY, scene, seed=7).render_side_by_side(Pose.at(8.0 - distance_m, 0.0, 1.5))
    pipeline = make_pipeline(cfg, LUT_GEOMETRY.width_px, LUT_GEOMETRY.height_px)
    return float(pipeline.process(frame, 0.0).refined.depth_m[REGION_INDEX["center"]])


def test_the_measured_lut_corrects_a_scale_error_at_distances_it_never_saw(tmp_path: Path, capsys) -> None:
    csv_path = write_lut_captures(tmp_path / "lut", distances_m=(1.0, 2.0, 3.0, 4.5))
    config = tmp_path / "companion.toml"
    config.write_text(CONFIG)
    plot = tmp_path / "lut.png"
    code = main(["calibrate", "lut", "--captures", str(tmp_path / "lut"), "--distances", str(csv_path),
                 "--config", str(config), "--plot", str(plot), "--json"])
    out = capsys.readouterr().out
    assert code == 0
    doc = json.loads(out)
    assert doc["max_error_before_pct"] > 11.0 and doc["max_error_after_pct"] < 0.5
    assert all(r["error_before_pct"] < -11.0 for r in doc["distances"])
    cfg = load_config(config)
    assert [list(p) for p in cfg.lut.points_m] == doc["points_m"]
    assert config.read_text().startswith(CONFIG)  # edited in place: the user's lines stay
    assert plot.stat().st_size > 1000
    before = parse_config({"calibration": {"ideal_baseline_m": 0.105}})
    for d in (1.5, 2.5, 3.5):  # not among the captures
        assert _centre_depth(before, d) == pytest.approx(0.875 * d, rel=0.03)
        assert _centre_depth(cfg, d) == pytest.approx(d, rel=0.02)


def test_distances_typed_in_and_a_dry_run(tmp_path: Path, capsys, monkeypatch) -> None:
    write_lut_captures(tmp_path / "lut", distances_m=(1.0, 3.0))
    (tmp_path / "lut" / "distances.csv").unlink()
    config = tmp_path / "c.toml"
    config.write_text(CONFIG)
    monkeypatch.setattr("sys.stdin", io.StringIO("one\n1.0\n3 m\n"))
    assert main(["calibrate", "lut", "--captures", str(tmp_path / "lut"), "--config", str(config), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "'one' is not a number" in out and "points_m = [[0.2," in out and "unchanged" in out
    assert config.read_text() == CONFIG


def test_unusable_captures_are_refused_with_the_reason(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "lut"
    write_lut_captures(folder, distances_m=(1.0, 2.0))
    # A target far too small for the centre region: it sees the target AND what is behind it.
    scene = Scene(obstacles=(Box.on_ground(3.0, 0.0, (0.1, 0.3, 1.6)),), ground=True)
    import cv2

    cv2.imwrite(str(folder / "target_02.png"), StereoRenderer(LUT_GEOMETRY, scene).render_side_by_side(Pose.at(0.0, 0.0, 1.5)))
    with (folder / "distances.csv").open("a") as f:
        f.write("target_02.png,3\n")
    assert main(["calibrate", "lut", "--captures", str(folder), "--distances", str(folder / "distances.csv")]) == 2
    err = capsys.readouterr().err
    assert "target_02.png" in err and "must fill the centre" in err


def test_distances_csv_errors_name_the_row(tmp_path: Path) -> None:
    path = tmp_path / "d.csv"
    path.write_text("file,true_distance_m\na.png,1.5\n# a comment\nb.png,-2\n")
    with pytest.raises(InputError, match=r"d.csv:4: distance '-2' must be a positive"):
        read_distances_csv(path)
    path.write_text("a.png,1.5\nb.png,far\n")
    with pytest.raises(InputError, match=r"d.csv:2: distance 'far' is not a number"):
        read_distances_csv(path)
    path.write_text("a.png,1.5\nb.png,2\n")
    assert read_distances_csv(path) == {"a.png": 1.5, "b.png": 2.0}


def test_fit_pools_makes_monotone_extends_and_refuses_too_little() -> None:
    table = fit_lut([0.9, 0.86, 1.75, 2.6, 3.5, 3.4], [1, 1, 2, 3, 4, 4])
    assert table[0] == (0.2, pytest.approx(0.2 * 1 / 0.88, abs=1e-3)) and table[1] == (0.88, 1.0)
    assert table[-1][0] == 40.0 and table[-1][1] == pytest.approx(40 * 4 / 3.45, abs=1e-3)
    DepthLUT(table)  # a valid table: both columns strictly increasing
    # A computed depth that went back (2.0 at 3 m after 2.1 at 2 m) is pooled with its neighbour.
    table = fit_lut([1.0, 2.1, 2.0, 4.0], [1, 2, 3, 4], extend_to_m=None)
    assert table == [(1.0, 1.0), (2.05, 2.5), (4.0, 4.0)]
    with pytest.raises(ValueError, match="at least 2 different true distances"):
        fit_lut([1.0, 1.1], [2.0, 2.0])
    with pytest.raises(ValueError, match="must be finite and positive"):
        fit_lut([1.0, float("nan")], [1.0, 2.0])


def test_config_editor_keeps_the_file_and_refuses_what_it_cannot_edit() -> None:
    text = "# top\n[lut]\n# the table\npoints_m = [\n  [0.2, 0.2],  # a comment ]\n  [40.0, 40.0],\n]\nmedian_frames = 3\n\n[planner]\ncruise_speed_m_s = 0.5\n"
    out = set_config_value(text, "lut", "points_m", [[0.2, 0.25], [40.0, 46.0]])
    assert out == "# top\n[lut]\n# the table\npoints_m = [[0.2, 0.25], [40.0, 46.0]]\nmedian_frames = 3\n\n[planner]\ncruise_speed_m_s = 0.5\n"
    assert set_config_value("", "calibration", "file", "/x/c.yaml") == '[calibration]\nfile = "/x/c.yaml"\n'
    assert set_config_value("[lut]\n", "lut", "median_frames", 5) == "[lut]\nmedian_frames = 5\n"
    with pytest.raises(ConfigError, match="set lut.points_m by hand"):
        set_config_value("lut.points_m = [[1.0, 1.0], [2.0, 2.0]]\n", "lut", "points_m", [[1.0, 1.0]])
    with pytest.raises(ConfigError, match="not valid TOML"):
        set_config_value("[lut\n", "lut", "points_m", [[1.0, 1.0]])


def test_live_lut_capture_asks_for_distances_and_saves_what_it_measured(tmp_path: Path, capsys, monkeypatch) -> None:
    import companion.cli.calibrate as cli

    scene = Scene(obstacles=(Box.on_ground(8.05, 0.0, (0.1, 4.0, 3.0)),), ground=True)
    renderer = StereoRenderer(LUT_GEOMETRY, scene)
    where = {"d": 1.0}

    class _Camera:
        name = "fake"

        def open(self) -> None: ...

        def close(self) -> None: ...

        def read(self):
            from companion.interfaces import Frame

            return Frame(image=renderer.render_side_by_side(Pose.at(8.0 - where["d"], 0.0, 1.5)), timestamp_s=0.0, seq=1)

    answers = iter(["1", "2.5", ""])

    def ask(prompt: str) -> str:
        value = next(answers)
        if value:
            where["d"] = float(value)
        return value

    monkeypatch.setattr(cli, "_camera_from_config", lambda config: _Camera())
    monkeypatch.setattr("builtins.input", ask)
    config = tmp_path / "c.toml"
    config.write_text(CONFIG)
    assert main(["calibrate", "lut", "--live", "--config", str(config), "--frames", "2",
                 "--save-captures", str(tmp_path / "caps")]) == 0
    assert "2 frames at 2.5 m" in capsys.readouterr().out
    assert read_distances_csv(tmp_path / "caps" / "distances.csv") == {
        "d00_1m_00.png": 1.0, "d00_1m_01.png": 1.0, "d01_2.5m_00.png": 2.5, "d01_2.5m_01.png": 2.5,
    }
    points = load_config(config).lut.points_m
    assert DepthLUT(points).apply(np.array([0.875 * 2.5]))[0] == pytest.approx(2.5, rel=0.02)
