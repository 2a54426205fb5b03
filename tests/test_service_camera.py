"""Camera sources, recordings, the one-slot mailbox and the capture thread's reconnect."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from companion.config import parse_config
from companion.errors import CameraError, ConfigError
from companion.interfaces import CameraSource, Frame
from companion.service.camera import make_camera
from companion.service.camera_replay import ReplayCamera
from companion.service.camera_sim import PoseUnavailable, sim_camera_from_config
from companion.service.camera_v4l2 import UvcCamera
from companion.service.capture import CaptureThread, FrameMailbox
from companion.service.recording import (
    RecordingWriter,
    read_timestamps,
    timestamps_path,
)


def _frames(n: int, w: int = 32, h: int = 24) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    return [rng.integers(0, 256, (h, 2 * w, 3), dtype=np.uint8) for _ in range(n)]


# ---------------------------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    ("camera", "expected"),
    [
        ({"source": "uvc", "width_px": 1280, "height_px": 700, "fps_hz": 30}, "not a ZED mode"),
        ({"source": "uvc", "width_px": 2208, "height_px": 1242, "fps_hz": 30}, "2208x1242 at 15 Hz, not 30 Hz"),
        ({"source": "uvc", "width_px": 1920, "height_px": 1080, "fps_hz": 60}, "not 60 Hz"),
        ({"source": "replay"}, "needs replay_path"),
        ({"reconnect_initial_s": 3.0, "reconnect_max_s": 1.0}, "reconnect_max_s"),
    ],
)
def test_camera_config_is_validated_with_a_clear_error(camera: dict, expected: str) -> None:
    with pytest.raises(ConfigError) as exc:
        parse_config({"camera": camera})
    assert expected in str(exc.value) and "camera" in str(exc.value)


@pytest.mark.parametrize(("w", "h", "fps"), [(2208, 1242, 15), (1920, 1080, 30), (1280, 720, 60), (672, 376, 100), (672, 376, 15)])
def test_every_zed_mode_is_accepted(w: int, h: int, fps: float) -> None:
    cfg = parse_config({"camera": {"source": "uvc", "width_px": w, "height_px": h, "fps_hz": fps}})
    cam = make_camera(cfg)
    assert isinstance(cam, UvcCamera) and cam.eye_size_px == (w, h)


def test_missing_uvc_device_is_a_camera_error() -> None:
    cam = UvcCamera("/dev/video-nonexistent-99", 672, 376, 30.0)
    with pytest.raises(CameraError, match="cannot open"):
        cam.open()
    with pytest.raises(CameraError, match="not open"):
        cam.read()
    cam.close()
    cam.close()


# ---------------------------------------------------------------------------------------------- recordings


@pytest.mark.parametrize("container", ["folder", "rec.mkv"])
def test_record_then_replay_gives_the_same_frames_at_the_recorded_rate(tmp_path: Path, container: str) -> None:
    frames = _frames(6)
    out = tmp_path / container
    with RecordingWriter(out, 50.0) as w:
        for i, f in enumerate(frames):
            w.write(f, 10.0 + i * 0.04, i + 1)  # recorded at 25 fps
    ts = read_timestamps(out)
    assert ts is not None and np.allclose(np.diff(ts.timestamp_s), 0.04)
    cam = ReplayCamera(out, 32, 24)
    assert isinstance(cam, CameraSource)
    cam.open()
    got = [cam.read() for _ in range(6)]
    for a, b in zip(got, frames, strict=False):
        assert np.array_equal(a.image, b)  # lossless
    dts = np.diff([g.timestamp_s for g in got])
    assert np.all(dts > 0.03) and np.all(dts < 0.08)  # paced at the recorded 25 fps
    assert [g.seq for g in got] == list(range(1, 7))
    with pytest.raises(CameraError) as exc:
        cam.read()
    assert exc.value.context.get("ended") is True
    cam.close()


def test_replay_at_a_given_rate_with_loop_and_preload(tmp_path: Path) -> None:
    frames = _frames(3)
    with RecordingWriter(tmp_path / "r", 30.0) as w:
        for i, f in enumerate(frames):
            w.write(f, i * 1.0, i + 1)  # recorded at 1 fps
    cam = ReplayCamera(tmp_path / "r", 32, 24, rate_hz=100.0, loop=True, preload=True)
    cam.open()
    t0 = time.monotonic()
    got = [cam.read() for _ in range(8)]
    # the given 100 Hz (0.07 s), not the recorded 1 fps (7 s): far below 7 s even on a loaded machine
    assert time.monotonic() - t0 < 3.5
    assert np.array_equal(got[3].image, frames[0]) and np.array_equal(got[7].image, frames[1])
    assert [g.seq for g in got] == list(range(1, 9))
    cam.close()


def test_replay_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match="no such recording"):
        ReplayCamera(tmp_path / "missing", 32, 24).open()
    (tmp_path / "empty").mkdir()
    with pytest.raises(CameraError, match="no frame_"):
        ReplayCamera(tmp_path / "empty", 32, 24).open()
    with RecordingWriter(tmp_path / "r", 30.0) as w:
        w.write(_frames(1)[0], 0.0, 1)
    cam = ReplayCamera(tmp_path / "r", 64, 24)
    cam.open()
    with pytest.raises(CameraError, match="expected side-by-side 128x24"):
        cam.read()
    timestamps_path(tmp_path / "r").write_text("index,timestamp_s,seq\n0,abc,1\n")
    with pytest.raises(CameraError, match="timestamps.csv:2"):
        ReplayCamera(tmp_path / "r", 32, 24).open()


def test_record_cli_writes_what_replay_reads(tmp_path: Path) -> None:
    from companion.cli import main

    out = tmp_path / "rec"
    assert main(["--log-level", "WARNING", "record", "--out", str(out), "--frames", "3"]) == 0
    cam = make_camera(parse_config({"camera": {"source": "replay", "replay_path": str(out), "replay_rate_hz": 200.0}}))
    cam.open()
    frame = cam.read()
    assert frame.image.shape == (376, 1344, 3)
    cam.close()


# ---------------------------------------------------------------------------------------------- sim


def test_sim_camera_renders_the_configured_pose_read_only_at_its_rate() -> None:
    cfg = parse_config({"camera": {"fps_hz": 20.0, "width_px": 160, "height_px": 120}})
    cam = sim_camera_from_config(cfg)
    assert cam.eye_size_px == (160, 120)
    cam.open()
    t0 = time.monotonic()
    a, b, c = cam.read(), cam.read(), cam.read()
    assert time.monotonic() - t0 >= 0.09
    assert a.image.shape == (120, 320, 3) and a.image is b.image and not a.image.flags.writeable
    assert (a.seq, b.seq, c.seq) == (1, 2, 3)
    cam.close()


def test_sim_camera_follows_its_pose_provider() -> None:
    from companion.sim.render import Pose

    cfg = parse_config({"camera": {"fps_hz": 100.0, "width_px": 160, "height_px": 120}})
    poses = iter([(Pose.at(2.0, 0.0, 1.5), 7.0), (Pose.at(30.0, 0.0, 1.5), 7.5)])
    cam = sim_camera_from_config(cfg, pose_provider=lambda: next(poses))
    cam.open()
    a, b = cam.read(), cam.read()
    assert not np.array_equal(a.image, b.image)
    assert (a.timestamp_s, b.timestamp_s) == (7.0, 7.5)  # stamped with the pose's time
    with pytest.raises(CameraError, match="pose provider failed"):
        cam.read()  # the provider raises StopIteration


class _Telemetry:
    """A vehicle link's state() whose position arrives when the test says."""

    def __init__(self) -> None:
        from companion.interfaces import VehicleState

        self.value = VehicleState()

    def __call__(self):
        return self.value

    def arrive(self, position, attitude, at_s: float) -> None:
        from dataclasses import replace

        self.value = replace(
            self.value,
            position_ned_m=np.asarray(position, dtype=np.float64),
            attitude_rad=np.asarray(attitude, dtype=np.float64),
            position_timestamp_s=at_s,
        )


def test_telemetry_pose_is_placed_in_the_scene_and_stamped_with_its_arrival() -> None:
    from companion.service.camera_sim import TelemetryPose
    from companion.core.placement import CoursePlacement

    now = [100.0]
    tel = _Telemetry()
    # The course origin at local (10, 5, -0.4), its north axis heading east (90 deg).
    provide = TelemetryPose(tel, CoursePlacement((10.0, 5.0, -0.4), math.pi / 2), 0.3, lambda: now[0])
    with pytest.raises(PoseUnavailable, match="no vehicle pose"):
        provide()
    # 2 m east of the origin in the local frame, 1.5 m above its ground, heading east (+ a little roll).
    tel.arrive([10.0, 7.0, -1.9], [0.05, -0.02, math.pi / 2], at_s=99.95)
    pose, t = provide()
    assert t == 99.95
    np.testing.assert_allclose(pose.position_ned_m, (2.0, 0.0, -1.5), atol=1e-12)  # 2 m along the course
    assert pose.yaw_rad == pytest.approx(0.0, abs=1e-12)
    assert (pose.roll_rad, pose.pitch_rad) == (0.05, -0.02)
    provide.placement = CoursePlacement((8.0, 7.0, -0.4), 0.0)  # re-placed live (set_config)
    np.testing.assert_allclose(provide()[0].position_ned_m, (2.0, 0.0, -1.5), atol=1e-12)
    now[0] = 100.4  # telemetry stopped 0.45 s ago
    with pytest.raises(PoseUnavailable, match="0.45 s old"):
        provide()


def test_sim_camera_on_telemetry_waits_for_a_pose_then_reports_it_missing() -> None:
    from companion.service.camera_sim import TelemetryPose
    from companion.core.placement import CoursePlacement

    cfg = parse_config(
        {"camera": {"fps_hz": 100.0, "width_px": 160, "height_px": 120, "sim_world": "course", "sim_course": "head-on", "sim_pose": "telemetry"}}
    )
    tel = _Telemetry()
    provider = TelemetryPose(tel, CoursePlacement(), 0.3, time.monotonic)
    cam = sim_camera_from_config(cfg, pose_provider=provider)
    cam.pose_wait_s = 0.1
    cam.open()
    t0 = time.monotonic()
    with pytest.raises(CameraError, match="no vehicle pose from telemetry yet"):
        cam.read()
    assert time.monotonic() - t0 >= 0.1  # retried for pose_wait_s before giving up
    tel.arrive([0.0, 0.0, -1.5], [0.0, 0.0, 0.0], at_s=time.monotonic())
    far = cam.read()
    tel.arrive([3.5, 0.0, -1.5], [0.0, 0.0, 0.0], at_s=time.monotonic())
    near = cam.read()  # the head-on box (5 m north) now fills more of the view
    assert not np.array_equal(far.image, near.image)
    cam.close()


# ---------------------------------------------------------------------------------------------- mailbox


def _frame(seq: int) -> Frame:
    return Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=float(seq), seq=seq)


def test_mailbox_holds_only_the_newest_and_never_hands_a_frame_twice() -> None:
    box = FrameMailbox()
    assert box.take() is None
    assert box.put(_frame(1)) is False
    assert box.put(_frame(2)) is True  # frame 1 dropped
    assert box.take().seq == 2
    assert box.take() is None
    assert box.counts() == (2, 1, 1)


def test_mailbox_under_a_fast_producer_and_a_slow_consumer() -> None:
    box = FrameMailbox()
    taken: list[int] = []
    done = threading.Event()

    def consume() -> None:
        while not done.is_set() or box.counts()[0] > box.counts()[1] + box.counts()[2]:
            f = box.take()
            if f is not None:
                taken.append(f.seq)
            time.sleep(0.001)

    t = threading.Thread(target=consume)
    t.start()
    for i in range(1, 3001):
        box.put(_frame(i))
    done.set()
    t.join(5)
    put, took, overwritten = box.counts()
    assert put == 3000 and took == len(taken) and took + overwritten == 3000
    assert taken == sorted(set(taken))  # strictly increasing: never twice, never out of order
    assert taken[-1] == 3000


# ---------------------------------------------------------------------------------------------- capture thread


class _FlakyCamera:
    """Delivers frames at 200 Hz; `unplug()` makes reads and opens fail until `plug()`."""

    name = "flaky"
    eye_size_px = (2, 2)

    def __init__(self) -> None:
        self.present = threading.Event()
        self.present.set()
        self.opens = 0
        self.seq = 0

    def open(self) -> None:
        if not self.present.is_set():
            raise CameraError("flaky: no such device")
        self.opens += 1

    def read(self) -> Frame:
        time.sleep(0.005)
        if not self.present.is_set():
            raise CameraError("flaky: device gone")
        self.seq += 1
        return _frame(self.seq)

    def close(self) -> None:
        pass

    def unplug(self) -> None:
        self.present.clear()

    def plug(self) -> None:
        self.present.set()


def test_capture_thread_reconnects_with_back_off_and_reports_it() -> None:
    cam = _FlakyCamera()
    box = FrameMailbox()
    states: list[str] = []
    cap = CaptureThread(cam, box, on_status=states.append, reconnect_initial_s=0.02, reconnect_max_s=0.08)
    cap.start()
    assert cap.wait_first_frame(2.0)
    time.sleep(0.05)
    assert cap.status().ok and cap.status().frames > 3
    cam.unplug()
    time.sleep(0.4)
    st = cap.status()
    assert st.state == "reconnecting" and not st.ok and "flaky" in (st.last_error or "")
    frames_while_gone = st.frames
    cam.plug()
    time.sleep(0.3)
    st = cap.status()
    assert st.ok and st.reconnects == 1 and st.frames > frames_while_gone
    cap.stop()
    assert cap.status().state == "stopped"
    assert states[:3] == ["streaming", "reconnecting", "streaming"]
    # Back-off doubled: far fewer open attempts than 0.4 s / 0.02 s.
    assert cam.opens == 2


# ---------------------------------------------------------------------------------------------- pipeline thread


def _processing_thread(now: list[float], interval_s: float = 0.01):
    from companion.service.capture import ProcessingThread

    box = FrameMailbox()
    for i in range(3):  # establishes the camera's interval (frames at 0.96, 0.97, 0.98 s)
        box.put(Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=0.96 + i * interval_s, seq=i + 1))
    box.take()
    return box, ProcessingThread(box, lambda f: f.seq, lambda *a: None, clock=lambda: now[0])


def test_a_late_frame_is_skipped_when_the_next_is_due_sooner() -> None:
    now = [1.0]
    box, proc = _processing_thread(now)
    assert box.interval_s == pytest.approx(0.01)
    assert proc._fresher(Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=0.998, seq=9)).seq == 9
    late = Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=0.992, seq=10)  # waited 8 ms > 5 ms
    box.put(Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=0.999, seq=11))  # the next one
    assert proc._fresher(late).seq == 11 and proc.skipped == 1
    fresh = Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=0.997, seq=12)  # waited 3 ms
    assert proc._fresher(fresh) is fresh and proc.skipped == 1


def test_a_late_frame_is_kept_when_no_newer_one_comes() -> None:
    now = [1.0]
    box, proc = _processing_thread(now)
    late = Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=0.992, seq=10)
    assert proc._fresher(late) is late and proc.skipped == 0  # it waited (a bounded wait) and kept it


def test_pipeline_thread_processes_each_frame_once_and_runs_jobs_between_frames() -> None:
    from companion.service.capture import ProcessingThread

    box = FrameMailbox()
    done: list[int] = []
    errors: list[BaseException] = []

    def process(frame: Frame) -> int:
        time.sleep(0.004)
        if frame.seq == 7:
            raise ValueError("broken frame")
        return frame.seq

    def report(frame: Frame, result, err) -> None:
        if err is not None:
            errors.append(err)
        else:
            done.append(result)

    proc = ProcessingThread(box, process, report, skip_late_frames=False)
    proc.start()
    assert proc.submit(lambda: "built").result(1.0) == "built"
    proc.processing_enabled.set()
    for i in range(1, 200):
        box.put(Frame(image=np.zeros((2, 4, 3), np.uint8), timestamp_s=time.monotonic(), seq=i))
        time.sleep(0.001)
        if i == 100:
            assert proc.submit(lambda x: x * 2, 21).result(1.0) == 42
    time.sleep(0.05)
    proc.stop()
    assert done == sorted(set(done)) and done[-1] == 199
    assert len(done) + len(errors) + box.overwritten == 199
    assert proc.submit(lambda: 1).exception(0.1) is not None  # stopped: refuses new jobs
