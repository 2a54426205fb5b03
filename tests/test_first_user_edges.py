"""The rough edges of a first hour, each as a new user hit it: health's made-up depths, log lines every 10 s
forever, a missing replay retried for 10 s, install-service without a confirmation, the overlay's text
under OpenCV 5, and the cameras beyond the ZED."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion import exitcodes
from companion.cli import main
from companion.config import CompanionConfig, parse_config
from companion.core.geometry import StereoGeometry
from companion.core.pipeline import Pipeline
from companion.core.regions import region_layout
from companion.core.types import REGION_NAMES, Decision, DecisionKind, RegionDepths
from companion.errors import CameraError, ConfigError, VehicleError
from companion.interfaces import Frame
from companion.service.backoff import LogBackoff
from companion.service.camera import make_camera
from companion.service.camera_v4l2 import PairCamera, UvcCamera
from companion.service.capture import CaptureThread, FrameMailbox
from companion.service.health import _regions

# ---------------------------------------------------------------------------------------------- health


class _ScriptedEstimator:
    """An estimator that returns the given centre depths, one per frame (NaN = unknown)."""

    name = "scripted"

    def __init__(self, centre_m: list[float]) -> None:
        self.geometry = StereoGeometry.ideal(64, 48, 90.0, 0.12)
        self.layout = region_layout(self.geometry, CompanionConfig().regions)
        self._centre = iter(centre_m)

    def estimate(self, frame, want_disparity: bool = False, near_block_px: int = 0, near_erode_px: int = 0):
        from companion.core.estimator import RegionEstimate

        depth = np.full(9, 5.0)
        depth[REGION_NAMES.index("center")] = next(self._centre)
        return RegionEstimate(RegionDepths(depth, np.ones(9)), {})


def test_health_shows_unknown_as_null_and_marks_what_the_release_filter_made() -> None:
    cfg = parse_config({})
    nan = float("nan")
    centre = [3.0, 3.0, 3.0, nan, nan, 3.0, 3.0, 3.0, 3.0]
    pipe = Pipeline(cfg, 64, 48, make_estimator=None, estimator=_ScriptedEstimator(centre))  # type: ignore[arg-type]
    frame = np.zeros((48, 128, 3), np.uint8)
    rows = [_regions(pipe.process(frame, 0.1 * k)) for k in range(len(centre))]
    shown = [r["regions_m"]["center"] for r in rows]
    measured = [r["regions_measured_m"]["center"] for r in rows]
    filtered = [r["regions_filtered"]["center"] for r in rows]
    assert measured == [3.0, 3.0, 3.0, None, None, 3.0, 3.0, 3.0, 3.0]
    # Unknown twice, then the median's 0 m stand-in for it (unknown history counts as near): null,
    # never "0.00" (the controller still takes it as near).
    assert shown[:6] == [3.0, 3.0, 3.0, None, None, None]
    assert filtered[:6] == [False] * 6
    # Then the release filter's ramp back up (0.29, 0.54, ...): values, marked as filtered.
    assert all(0.0 < v < 3.0 for v in shown[6:]) and shown[6:] == sorted(shown[6:]) and filtered[6:] == [True] * 3
    assert rows[0]["regions_m"]["up"] == 5.0 and rows[0]["regions_filtered"]["up"] is False
    empty = _regions(None)
    assert set(empty) == {"regions_m", "regions_measured_m", "regions_filtered"}
    assert all(v is None for v in empty["regions_m"].values())


# ---------------------------------------------------------------------------------------------- log back-off


def test_log_backoff_first_at_once_then_doubling_to_a_cap() -> None:
    b = LogBackoff(first_interval_s=10.0, max_interval_s=60.0)
    logged = [t for t in range(0, 400, 10) if b.due(float(t))]
    assert logged == [0, 10, 30, 70, 130, 190, 250, 310, 370]  # 10, 20, 40, then every 60 s
    assert b.suppressed == 5 and b.elapsed_s(400.0) == 400.0
    b.reset()
    assert b.due(1000.0)


def test_no_autopilot_is_reported_less_and_less_often(caplog: pytest.LogCaptureFixture) -> None:
    from companion.service.daemon import Service

    now = [0.0]

    class _Silent:
        calls = 0

        async def connect(self, timeout_s: float) -> None:
            now[0] += timeout_s
            self.calls += 1
            if self.calls <= 100:  # 1000 s without a heartbeat
                raise VehicleError(f"no autopilot heard on udpin://0.0.0.0:14540 within {timeout_s:g} s", kind="timeout")

        def state(self):
            from companion.interfaces import VehicleState

            return VehicleState()

    link = _Silent()
    service = Service(CompanionConfig(), link=link, clock=lambda: now[0], install_signals=False, environ={})
    with caplog.at_level(logging.INFO, logger="companion.service.connection"):
        asyncio.run(service.vehicle.run())
    lines = [r.getMessage() for r in caplog.records if "still waiting" in r.getMessage()]
    assert link.calls == 101 and service.vehicle.status == "connected"
    assert 5 <= len(lines) <= 8, lines  # was 100
    assert "10 s so far" in lines[0] and "next report in 20 s" in lines[1]


class _NeverThere:
    name = "gone"
    eye_size_px = (2, 2)

    def __init__(self, ended: bool = False) -> None:
        self.opens = 0
        self.ended = ended

    def open(self) -> None:
        self.opens += 1
        raise CameraError("gone: no such device", ended=self.ended)

    def read(self) -> Frame:  # pragma: no cover - never opened
        raise AssertionError

    def close(self) -> None:
        pass


def test_camera_reopen_failures_are_reported_less_and_less_often(caplog: pytest.LogCaptureFixture) -> None:
    cam = _NeverThere()
    fake = [0.0]

    def clock() -> float:
        fake[0] += 1.0  # a second per look at the clock: the back-off sees minutes pass
        return fake[0]

    cap = CaptureThread(cam, FrameMailbox(), reconnect_initial_s=0.001, reconnect_max_s=0.002, clock=clock)
    with caplog.at_level(logging.DEBUG, logger="companion.service.capture"):
        cap.start()
        deadline = time.monotonic() + 5.0
        while cam.opens < 200 and time.monotonic() < deadline:
            time.sleep(0.01)
        cap.stop()
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "gone" in r.getMessage()]
    assert cam.opens >= 200 and len(warnings) <= 12, (cam.opens, len(warnings))


def test_a_recording_that_is_not_there_fails_at_once(tmp_path: Path) -> None:
    from companion.service.daemon import Service

    from peers.fakes import FakeLink, service_config, wait_until

    cfg = service_config(tmp_path, camera={"source": "replay", "replay_path": str(tmp_path / "nope")})
    with pytest.raises(CameraError, match="no such recording"):
        make_camera(cfg)
    # In the service: a startup failure at once, not after camera.open_timeout_s (10 s) of retries.
    t0 = time.monotonic()
    code = asyncio.run(Service(cfg, link=FakeLink(), install_signals=False, environ={}).run())
    # at once: well before the 10 s of retries it would take (generous for a loaded machine)
    assert code == exitcodes.STARTUP_FAILURE and time.monotonic() - t0 < cfg.camera.open_timeout_s
    # And a source that says so is not reopened by the capture thread.
    cam = _NeverThere(ended=True)
    cap = CaptureThread(cam, FrameMailbox(), reconnect_initial_s=0.001, reconnect_max_s=0.002)
    cap.start()
    assert wait_until(lambda: cap.status().state == "ended", 30.0)
    time.sleep(0.2)
    assert cam.opens == 1 and cap.status().state == "ended"
    cap.stop()


# ---------------------------------------------------------------------------------------------- install-service


def test_install_service_prints_the_plan_and_needs_yes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["install-service", "--root", str(tmp_path), "--no-user"]) == exitcodes.BAD_INPUT
    captured = capsys.readouterr()
    assert "would write" in captured.out and "companion.service" in captured.out and "--yes" in captured.err
    assert list(tmp_path.iterdir()) == []  # nothing changed
    assert main(["install-service", "--root", str(tmp_path), "--no-user", "--yes"]) == 0
    assert (tmp_path / "etc/systemd/system/companion.service").is_file()
    assert (tmp_path / "etc/companion/companion.toml").is_file()


# ---------------------------------------------------------------------------------------------- overlay


def test_overlay_text_stays_inside_its_box_and_the_legend_explains_it() -> None:
    from companion.core.overlay import _label, draw_overlay

    # Every pixel the text touches lies inside its box (OpenCV 5 draws thicker text wider: a thicker
    # "shadow" string used to stick out past the text).
    canvas = np.full((60, 400, 3), 128, np.uint8)
    right = _label(canvas, "BRAKE  yaw +0.00  pitch +0.00", (6, 40), 0.6, (40, 40, 230), 1)
    changed = np.any(canvas != 128, axis=2)
    cols = np.flatnonzero(changed.any(axis=0))
    assert cols.min() >= 4 and cols.max() < right
    geometry = StereoGeometry.ideal(672, 376, 90.0, 0.12)
    layout = region_layout(geometry, CompanionConfig().regions)
    decision = Decision(DecisionKind.AVOID, 0.4, 0.0, 0.5, "test")
    image = np.full((376, 672), 100, np.uint8)
    plain = draw_overlay(image, layout, np.full(9, 2.0), decision)
    assert plain.shape == (376, 672, 3)  # no legend unless asked: callers keep their image size
    filtered = np.zeros(9, bool)
    filtered[4] = True
    with_legend = draw_overlay(image, layout, np.full(9, 2.0), decision, filtered=filtered, legend=True,
                               disparity=np.full((376, 672), 20.0, np.float32))
    assert with_legend.shape[1] == 672 and with_legend.shape[0] > 376
    assert np.array_equal(with_legend[:376, :, :], draw_overlay(image, layout, np.full(9, 2.0), decision, filtered=filtered,
                                                                  disparity=np.full((376, 672), 20.0, np.float32)))


# ---------------------------------------------------------------------------------------------- cameras


def test_camera_models_are_validated() -> None:
    sbs = parse_config({"camera": {"source": "uvc", "model": "sbs", "width_px": 640, "height_px": 480, "fps_hz": 25}})
    assert (sbs.camera.width_px, sbs.camera.height_px) == (640, 480)  # any mode the camera offers
    with pytest.raises(ConfigError, match="not a ZED mode.*model = 'sbs'"):
        parse_config({"camera": {"source": "uvc", "width_px": 640, "height_px": 480}})
    with pytest.raises(ConfigError, match="needs device_right"):
        parse_config({"camera": {"source": "uvc", "model": "pair"}})
    with pytest.raises(ConfigError, match="a pair needs two cameras"):
        parse_config({"camera": {"source": "uvc", "model": "pair", "device_right": "/dev/video0"}})
    with pytest.raises(ConfigError, match="fourcc"):
        parse_config({"camera": {"fourcc": "YU V"}})


def test_a_camera_other_than_the_zed_needs_a_calibration(tmp_path: Path) -> None:
    for model in ("sbs", "pair"):
        cfg = parse_config({"camera": {"source": "uvc", "model": model, "device_right": "/dev/video2",
                                       "width_px": 640, "height_px": 480}})
        with pytest.raises(CameraError, match="needs a stereo calibration.*companion calibrate stereo"):
            make_camera(cfg)
        assert make_camera(cfg, require_calibration=False) is not None  # to capture the views that make one
    cfg = parse_config({"calibration": {"file": str(tmp_path / "c.yaml")},
                        "camera": {"source": "uvc", "model": "pair", "device_right": "/dev/video2"}})
    assert isinstance(make_camera(cfg), PairCamera)


class _FakeCapture:
    """A cv2.VideoCapture stand-in: grab/retrieve with given driver timestamps (ms)."""

    def __init__(self, width: int, height: int, stamps_ms: list[float], value: int) -> None:
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: width, cv2.CAP_PROP_FRAME_HEIGHT: height, cv2.CAP_PROP_FPS: 30.0}
        self.stamps = list(stamps_ms)
        self.value = value
        self.grabs = 0
        self.released = False

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            return True  # the driver keeps its own size
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.stamps[min(self.grabs, len(self.stamps)) - 1] if self.grabs else 0.0
        return float(self.props.get(prop, 0.0))

    def grab(self) -> bool:
        self.grabs += 1
        return True

    def retrieve(self):
        h, w = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
        return True, np.full((h, w, 3), self.value, np.uint8)

    def release(self) -> None:
        self.released = True


def test_a_pair_of_cameras_is_joined_side_by_side_and_its_skew_measured() -> None:
    left = _FakeCapture(64, 48, [1000.0, 1033.0, 1066.0], 10)
    right = _FakeCapture(64, 48, [1002.0, 1050.0, 1067.0], 200)
    devices = {"/dev/video0": left, "/dev/video2": right}
    cam = PairCamera("/dev/video0", "/dev/video2", 64, 48, 30.0, max_skew_ms=8.0, capture_factory=devices.__getitem__)
    cam.open()
    frame = cam.read()
    assert frame.image.shape == (48, 128, 3)
    assert (frame.image[:, :64] == 10).all() and (frame.image[:, 64:] == 200).all()
    assert cam.skew_status()["last"] == pytest.approx(2.0) and cam.skew_status()["source"] == "driver"
    # 1033 vs 1050: 17 ms apart, over 8: the left (earlier) camera's next frame, 1066, is taken instead.
    cam.read()
    status = cam.skew_status()
    assert status["last"] == pytest.approx(-16.0) and status["regrabs"] == 1 and left.grabs == 3
    assert status["max"] == pytest.approx(16.0)
    cam.close()
    assert left.released and right.released


def test_a_side_by_side_camera_in_a_mode_it_does_not_give_is_named() -> None:
    fake = _FakeCapture(1280, 720, [0.0], 0)
    cam = UvcCamera("/dev/video0", 640, 480, 30.0, model="sbs", capture_factory=lambda d: fake)
    with pytest.raises(CameraError, match=r"asked /dev/video0 for 1280x480 \(YUYV\) but the driver gives 1280x720") as info:
        cam.open()
    assert "ZED" not in str(info.value) and "--list-formats-ext" in str(info.value)
    assert fake.released


def test_health_reports_the_pair_skew(tmp_path: Path) -> None:
    from companion.service.daemon import Service

    from peers.fakes import Client, FakeLink, ServiceRunner, avoid_scene_camera, service_config

    class _Skewed:
        def __init__(self, inner) -> None:
            self.inner, self.name = inner, "pair:fake"

        eye_size_px = property(lambda self: self.inner.eye_size_px)

        def open(self) -> None:
            self.inner.open()

        def read(self) -> Frame:
            return self.inner.read()

        def close(self) -> None:
            self.inner.close()

        def skew_status(self) -> dict:
            return {"last": 1.5, "median": 1.2, "max": 3.0, "source": "driver", "regrabs": 0}

    cfg = service_config(tmp_path)
    service = Service(cfg, camera=_Skewed(avoid_scene_camera(15.0)), link=FakeLink(), install_signals=False, environ={})
    with ServiceRunner(service):
        client = Client(cfg.bus.control_endpoint)
        try:
            health = client.call("status")["result"]
        finally:
            client.close()
    assert health["camera"]["skew_ms"]["median"] == 1.2
    assert set(health["regions_filtered"]) == set(REGION_NAMES) and "regions_measured_m" in health
