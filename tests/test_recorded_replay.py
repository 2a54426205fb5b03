"""Recorded flights replayed: rendered pairs (true depth known) written as an ASL/EuRoC folder and as ROS 1
and ROS 2 bags, read back as stereo pairs, run through the pipeline by ``companion process --sequence``
and by the service's camera source."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.config import CompanionConfig, apply_patch
from companion.errors import CameraError, InputError
from companion.recorded.camera import RecordedCamera
from companion.view.replay import replay_sequence
from companion.recorded.sequence import PairMatcher, SequenceReport, open_sequence, pick_topics
from recorded_data import GEOMETRY, PERIOD_NS, Flight, distorted_rig, render_flight, write_asl, write_bag

pytest.importorskip("rosbags")

N = 24


@pytest.fixture(scope="module")
def flight() -> Flight:
    """Toward a wall from 3.5 m to 1.2 m at 2 m/s: clear, then avoid, then brake."""
    return render_flight(N, start_m=2.5, speed_m_s=2.0)


@pytest.fixture(scope="module")
def asl_replay(flight: Flight, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    base = tmp_path_factory.mktemp("asl")
    folder = write_asl(base / "flight", flight)
    summary = replay_sequence(open_sequence(folder), CompanionConfig(), base / "out", overlay_every_s=0.25)
    return base / "out", summary


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def test_pair_matcher_pairs_by_time_and_counts_the_unmatched() -> None:
    report = SequenceReport()
    m = PairMatcher(2_000_000, report)
    out = []
    for side, t in ((0, 0), (1, 1_000_000), (0, 50_000_000), (0, 100_000_000), (1, 101_000_000), (1, 150_000_000)):
        out += m.push(side, t, f"{side}@{t}")
    m.finish()
    assert [(t, a, b) for t, a, b in out] == [(0, "0@0", "1@1000000"), (100_000_000, "0@100000000", "1@101000000")]
    assert (report.unmatched_left, report.unmatched_right) == (1, 1)


def test_topics_are_found_by_their_names() -> None:
    zed = ["/zed/zed_node/left/image_rect_color", "/zed/zed_node/right/image_rect_color",
           "/zed/zed_node/left_raw/image_raw_color", "/zed/zed_node/right_raw/image_raw_color", "/zed/zed_node/rgb/image_rect_color"]
    assert pick_topics(zed) == ("/zed/zed_node/left/image_rect_color", "/zed/zed_node/right/image_rect_color")
    assert pick_topics(["/cam0/image_raw", "/cam1/image_raw"]) == ("/cam0/image_raw", "/cam1/image_raw")
    assert pick_topics(["/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw"])[0] == "/camera/infra1/image_rect_raw"
    assert pick_topics(["/a/image", "/b/image"]) is None


def test_asl_flight_gives_true_depths_and_the_decisions_of_an_approach(flight: Flight, asl_replay) -> None:
    """The recording's own sensor.yaml rig is used; the centre region follows the rendered wall."""
    out, summary = asl_replay
    assert summary.frames == N and summary.eye_size_px == (GEOMETRY.width_px, GEOMETRY.height_px)
    assert summary.calibration == str(out / "calibration.yaml")
    records = _records(out / "frames.jsonl")
    assert [r["frame"] for r in records] == list(range(N))
    assert records[1]["time_s"] == pytest.approx(PERIOD_NS / 1e9)
    for r, truth in zip(records, flight.centre_depth_m):
        assert r["regions_m"]["center"] == pytest.approx(truth, rel=0.08)
    kinds = [r["decision"] for r in records]
    assert kinds[0] == "clear" and kinds[-1] == "brake" and "avoid" in kinds
    assert records[-1]["setpoint"]["forward_m_s"] == 0.0
    assert summary.decisions == {k: kinds.count(k) for k in set(kinds)}


def test_asl_replay_writes_the_review_report_with_overlay_frames(asl_replay) -> None:
    out, summary = asl_replay
    index = [json.loads(line) for line in (out / "preview" / "index.jsonl").read_text().splitlines()]
    assert len(index) >= 4 and all((out / "preview" / item["file"]).is_file() for item in index)
    health = _records(out / "health.jsonl")
    assert len(health) == N and health[-1]["processed_frames"] == N
    html = summary.review.read_text(encoding="utf-8")
    assert summary.review == out / "review.html"
    assert "data:image/jpeg;base64," in html  # the contact sheet shows overlay frames, not drawn regions
    assert "brake at" in html and "avoid at" in html


def test_asl_gaps_and_unmatched_frames_are_reported(flight: Flight, tmp_path: Path) -> None:
    folder = write_asl(tmp_path / "flight", flight, drop_right=(3,), skip=(10, 11, 12), sensor_yaml=False)
    seq = open_sequence(folder)
    assert seq.calibration() is None
    pairs = list(seq.pairs())
    assert len(pairs) == N - 4
    report = seq.report
    assert (report.unmatched_left, report.unmatched_right) == (1, 0)
    assert [round(g[1], 3) for g in report.gaps] == [0.1, 0.2]
    assert "1 left and 0 right frames with no partner" in report.summary() and "2 gaps (longest 0.20 s" in report.summary()


@pytest.mark.parametrize(
    "kind",
    ["ros2-sqlite3-mono8", "ros2-mcap-bgr8", "ros2-compressed", "ros1-rgb8"],
)
def test_bags_replay_as_the_asl_folder_does(flight: Flight, asl_replay, tmp_path: Path, kind: str) -> None:
    """The same pairs in a bag (camera_info as the calibration) give the same records."""
    ros1 = kind.startswith("ros1")
    path = tmp_path / ("flight.bag" if ros1 else "flight")
    write_bag(
        path, flight, ros1=ros1, compressed="compressed" in kind, encoding=kind.rsplit("-", 1)[-1] if "8" in kind else "mono8",
        storage="mcap" if "mcap" in kind else "sqlite3",
    )
    if "sqlite3" in kind:
        path = path / "flight.db3"  # the .db3 itself names its bag too
    seq = open_sequence(path)
    assert seq.kind == "rosbag" and seq.topics[0].startswith("/zed/left/")
    summary = replay_sequence(seq, CompanionConfig(), tmp_path / "out")
    assert summary.frames == N and summary.calibration == str(tmp_path / "out" / "calibration.yaml")
    want = _records(asl_replay[0] / "frames.jsonl")
    got = _records(tmp_path / "out" / "frames.jsonl")
    assert [r["decision"] for r in got] == [r["decision"] for r in want]
    assert [r["timestamp_ns"] for r in got] == flight.times_ns
    for a, b in zip(got, want):
        assert a["regions_m"]["center"] == pytest.approx(b["regions_m"]["center"], abs=1e-3)


def test_csv_records_and_the_cli_summary(flight: Flight, tmp_path: Path, capsys) -> None:
    folder = write_asl(tmp_path / "flight", flight)
    out = tmp_path / "out"
    assert main(["process", "--sequence", str(folder), "--out", str(out), "--format", "csv", "--limit", "6", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 6 and summary["records"] == str(out / "frames.csv")
    assert sum(summary["decisions"].values()) == 6 and summary["pipeline_ms"]["median"] > 0
    with (out / "frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6 and float(rows[0]["center_m"]) == pytest.approx(flight.centre_depth_m[0], rel=0.08)
    assert (out / "review.html").is_file()


def test_recorded_rate_is_kept_on_the_given_clock(flight: Flight, tmp_path: Path) -> None:
    folder = write_asl(tmp_path / "flight", flight)
    now = [0.0]
    slept: list[float] = []

    def sleep(s: float) -> None:
        slept.append(s)
        now[0] += s

    replay_sequence(open_sequence(folder), CompanionConfig(), tmp_path / "out", realtime=True, limit=8,
                    clock=lambda: now[0], sleep=sleep)
    # The pipeline took no time on this clock: every pair waited for its recorded moment.
    assert sum(slept) == pytest.approx(7 * PERIOD_NS / 1e9)


def _one_line_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


def test_wrong_sequences_get_one_line(flight: Flight, tmp_path: Path, capsys) -> None:
    out = str(tmp_path / "out")
    assert "not a ROS 2 bag" in _one_line_error(capsys, ["process", "--sequence", str(tmp_path), "--out", out])
    assert "no such file" in _one_line_error(capsys, ["process", "--sequence", str(tmp_path / "x.bag"), "--out", out])
    folder = write_asl(tmp_path / "flight", flight)
    assert "needs --out" in _one_line_error(capsys, ["process", "--sequence", str(folder)])
    bag = write_bag(tmp_path / "bag", Flight(flight.left[:2], flight.right[:2], flight.times_ns[:2], flight.centre_depth_m[:2]))
    err = _one_line_error(capsys, ["process", "--sequence", str(bag), "--out", out, "--left-topic", "/zed/left/nothing", "--right-topic", "/zed/right/image_rect_gray"])
    assert "no topic /zed/left/nothing" in err
    err = _one_line_error(capsys, ["process", "--sequence", str(bag), "--out", out, "--left-topic", "/zed/left/camera_info", "--right-topic", "/zed/right/image_rect_gray"])
    assert "not sensor_msgs/Image" in err
    deep = write_bag(tmp_path / "deep", Flight(flight.left[:2], flight.right[:2], flight.times_ns[:2], flight.centre_depth_m[:2]), encoding="mono16")
    err = _one_line_error(capsys, ["process", "--sequence", str(deep), "--out", out])
    assert "no stereo pair could be processed (0 pairs, 2 undecodable frames skipped)" in err
    assert "image encoding 'mono16' is not one the replay reads" in err


def test_the_service_camera_source_reads_a_recorded_flight(flight: Flight, tmp_path: Path) -> None:
    from companion.service.camera import make_camera

    folder = write_asl(tmp_path / "flight", flight)
    cfg = apply_patch(CompanionConfig(), {"camera": {
        "source": "replay", "replay_path": str(folder), "width_px": GEOMETRY.width_px, "height_px": GEOMETRY.height_px,
        "replay_rate_hz": 1000.0,
    }})
    cam = make_camera(cfg)
    assert isinstance(cam, RecordedCamera)
    cam.open()
    try:
        frames = [cam.read() for _ in range(N)]
        assert frames[0].image.shape == (GEOMETRY.height_px, 2 * GEOMETRY.width_px, 3) and frames[0].image.dtype == np.uint8
        assert np.array_equal(frames[5].image[:, : GEOMETRY.width_px, 0], flight.left[5])
        assert np.array_equal(frames[5].image[:, GEOMETRY.width_px :, 0], flight.right[5])
        assert [f.seq for f in frames] == list(range(1, N + 1))
        with pytest.raises(CameraError, match="end of the recording") as err:
            cam.read()
        assert err.value.context.get("ended") is True
    finally:
        cam.close()
    looping = RecordedCamera(folder, GEOMETRY.width_px, GEOMETRY.height_px, rate_hz=1000.0, loop=True)
    looping.open()
    try:
        assert len([looping.read() for _ in range(N + 3)]) == N + 3
    finally:
        looping.close()
    wrong = RecordedCamera(folder, 672, 376, rate_hz=1000.0)
    wrong.open()
    try:
        with pytest.raises(CameraError, match="eyes are 320x200"):
            wrong.read()
    finally:
        wrong.close()


def test_the_service_camera_source_paces_at_the_recorded_rate(flight: Flight, tmp_path: Path) -> None:
    folder = write_asl(tmp_path / "flight", flight)
    now = [10.0]
    cam = RecordedCamera(folder, GEOMETRY.width_px, GEOMETRY.height_px, clock=lambda: now[0])
    waits: list[float] = []
    cam._stop.wait = lambda s: (waits.append(s), now.__setitem__(0, now[0] + s))[-1]  # type: ignore[method-assign]
    cam.open()
    try:
        stamps = [cam.read().timestamp_s for _ in range(4)]
    finally:
        cam.close()
    assert [round(b - a, 6) for a, b in zip(stamps, stamps[1:])] == [PERIOD_NS / 1e9] * 3
    assert all(math.isfinite(w) for w in waits)


def test_a_bag_without_the_rosbags_library_says_how_to_get_it(tmp_path: Path, monkeypatch) -> None:
    import builtins

    real = builtins.__import__

    def no_rosbags(name: str, *args, **kwargs):
        if name.startswith("rosbags"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V2.0\n")
    monkeypatch.setattr(builtins, "__import__", no_rosbags)
    with pytest.raises(InputError, match=r"pip install 'companion\[recorded\]'"):
        open_sequence(tmp_path / "x.bag")


def test_a_progress_bar_runs_on_a_terminal_only(flight: Flight, tmp_path: Path) -> None:
    import io

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    folder = write_asl(tmp_path / "flight", flight)
    tty, pipe = Terminal(), io.StringIO()
    replay_sequence(open_sequence(folder), CompanionConfig(), tmp_path / "a", limit=4, progress=tty)
    replay_sequence(open_sequence(folder), CompanionConfig(), tmp_path / "b", limit=4, progress=pipe)
    assert "4/4" in tty.getvalue() and tty.getvalue().endswith("\n")
    assert pipe.getvalue() == ""


def test_a_raw_distorted_rig_is_rectified_from_its_sensor_yaml(tmp_path: Path) -> None:
    """Raw frames with EuRoC-strong lens distortion and a degree between the eyes: the replay rectifies
    them with the rig the folder's sensor.yaml files describe, and the six regions that see the flat wall
    square ahead read its distance, evenly (with the distortion left out, the corners read 6 to 7 %
    further than the centre; with the rotation left out, a third nearer)."""
    rig = distorted_rig()
    raw = render_flight(6, start_m=3.0, speed_m_s=2.0, rig=rig)
    folder = write_asl(tmp_path / "flight", raw, rig=rig)
    # StereoBM's sub-pixel disparities: an integer-disparity matcher's quantisation at this range (about
    # 5 % a step) would hide what the rectification does to the wall's evenness.
    cfg = CompanionConfig.model_validate({"stereo": {"backend": "opencv-bm"}})
    summary = replay_sequence(open_sequence(folder), cfg, tmp_path / "out")
    assert summary.frames == 6
    for r, truth in zip(_records(tmp_path / "out" / "frames.jsonl"), raw.centre_depth_m):
        wall = [r["regions_m"][k] for k in ("up_left", "up", "up_right", "left", "center", "right")]
        assert all(d == pytest.approx(truth, rel=0.06) for d in wall), (wall, truth)
        assert (max(wall) - min(wall)) / truth < 0.04, (wall, truth)


def test_a_uvc_config_replays_and_its_run_config_is_the_replay_camera(flight: Flight, tmp_path: Path) -> None:
    """A flight config (a ZED over UVC) replays a recording of another size; the run's config.toml is
    that config with the recording as its camera, which the service can run."""
    from companion.config import load_config

    folder = write_asl(tmp_path / "flight", flight)
    cfg = apply_patch(CompanionConfig(), {"camera": {"source": "uvc", "model": "zed"}})
    bag = write_bag(tmp_path / "bag", flight)
    for path in (folder, bag):
        out = tmp_path / f"out-{path.name}"
        replay_sequence(open_sequence(path), cfg, out, limit=2)
        run = load_config(out / "config.toml").camera
        assert (run.source, run.replay_path, run.width_px, run.height_px) == ("replay", path.resolve(), 320, 200)
    assert (run.replay_left_topic, run.replay_right_topic) == ("/zed/left/image_rect_gray", "/zed/right/image_rect_gray")
