"""An instrumented fake vehicle link, a camera that can be stopped, and an in-process service runner."""

from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
import zmq

from companion.config import CompanionConfig, parse_config
from companion.core.types import VelocitySetpoint
from companion.errors import BackendError, CameraError, VehicleError
from companion.interfaces import Frame, VehicleState


@dataclass(frozen=True)
class Sent:
    t_s: float
    setpoint: VelocitySetpoint


class FakeLink:
    """A VehicleLink that behaves like PX4 behind MAVSDK (offboard accepted after a setpoint, mode
    changes on request or by the 'pilot') and records every call with its monotonic time. The vehicle
    hovers at 1.5 m at the origin, facing north (it does not fly the setpoints)."""

    def __init__(self, mode: str = "POSCTL", armed: bool = True, refuse_offboard: bool = False) -> None:
        self._lock = threading.Lock()
        self._state = VehicleState(
            connected=False, armed=armed, flight_mode=mode, in_offboard=mode == "OFFBOARD",
            position_ned_m=np.array([0.0, 0.0, -1.5]), velocity_ned_m_s=np.zeros(3), attitude_rad=np.zeros(3),
        )
        self.refuse_offboard = refuse_offboard
        self.sent: list[Sent] = []
        self.calls: list[tuple[float, str]] = []
        self.streaming = False
        self.closed = False

    async def connect(self, timeout_s: float) -> None:
        with self._lock:
            self._state = replace(self._state, connected=True, timestamp_s=time.monotonic())

    async def send_setpoint(self, setpoint: VelocitySetpoint) -> None:
        with self._lock:
            self.sent.append(Sent(time.monotonic(), setpoint))
            self.streaming = True

    async def start_offboard(self) -> None:
        await asyncio.sleep(0.01)
        with self._lock:
            self.calls.append((time.monotonic(), "start_offboard"))
            if self.refuse_offboard or not self.streaming:
                raise VehicleError("offboard start refused: DENIED")
            self._set_mode_locked("OFFBOARD")

    async def hold(self) -> None:
        await asyncio.sleep(0.01)
        with self._lock:
            self.calls.append((time.monotonic(), "hold"))
            self._set_mode_locked("HOLD")

    async def stop_setpoints(self) -> None:
        with self._lock:
            self.calls.append((time.monotonic(), "stop_setpoints"))
            self.streaming = False

    def state(self) -> VehicleState:
        with self._lock:
            return self._state

    async def close(self) -> None:
        self.closed = True

    # the test's side
    def _set_mode_locked(self, mode: str) -> None:
        self._state = replace(self._state, flight_mode=mode, in_offboard=mode == "OFFBOARD", timestamp_s=time.monotonic())

    def pilot_sets_mode(self, mode: str) -> None:
        with self._lock:
            self.calls.append((time.monotonic(), f"pilot:{mode}"))
            self._set_mode_locked(mode)

    def sent_since(self, t_s: float) -> list[Sent]:
        with self._lock:
            return [s for s in self.sent if s.t_s >= t_s]

    def call_names(self) -> list[str]:
        with self._lock:
            return [c for _, c in self.calls]


class GatedCamera:
    """Wraps a camera source; ``freeze()`` makes read() block (frames stop) until ``thaw()``;
    ``fail()`` makes the next read raise (the camera unplugged) until ``thaw()``. ``last_timestamp_s``:
    the capture time (s, the service's clock) of the newest frame handed out; a freeze lets a read
    already past the gate finish, so the newest frame can be up to one frame period younger than it."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.name = f"gated:{inner.name}"
        self._open = threading.Event()
        self._open.set()
        self._fail = False
        self._closed = threading.Event()
        self.last_timestamp_s: float | None = None

    @property
    def eye_size_px(self):
        return self.inner.eye_size_px

    def open(self) -> None:
        if self._fail:
            raise CameraError(f"{self.name}: unplugged")
        self._closed.clear()
        self.inner.open()

    def read(self) -> Frame:
        while not self._open.is_set():
            if self._closed.is_set():
                raise CameraError(f"{self.name}: closed")
            self._open.wait(0.02)
        if self._fail:
            raise CameraError(f"{self.name}: unplugged")
        frame = self.inner.read()
        self.last_timestamp_s = frame.timestamp_s
        return frame

    def close(self) -> None:
        self._closed.set()
        self.inner.close()

    def freeze(self) -> None:
        self._open.clear()

    def fail(self) -> None:
        self._fail = True

    def thaw(self) -> None:
        self._fail = False
        self._open.set()


def service_config(tmp_path, **sections) -> CompanionConfig:
    """Defaults with ipc endpoints in ``tmp_path`` and the given section overrides. The request budgets
    are raised: these tests poll ``status`` at 100 Hz (the budgets have tests of their own)."""
    data = {
        "bus": {
            "health_endpoint": f"ipc://{tmp_path}/health.sock",
            "control_endpoint": f"ipc://{tmp_path}/control.sock",
            "requests_per_s_per_client": 1000.0,
            "max_requests_per_s": 10000.0,
        },
        "camera": {"source": "sim", "fps_hz": 15.0},
        "stereo": {"backend": "opencv-bm"},
        "view": {"preview_endpoint": f"ipc://{tmp_path}/preview.sock"},
    }
    for key, value in sections.items():
        data.setdefault(key, {}).update(value)
    return parse_config(data)


class ServiceRunner:
    """Runs a Service on its own event loop in a background thread."""

    def __init__(self, service) -> None:
        self.service = service
        self.exit_code: int | None = None
        self._thread = threading.Thread(target=self._run, name="service", daemon=True)

    def _run(self) -> None:
        self.exit_code = asyncio.run(self.service.run())

    def start(self, timeout_s: float = 30.0) -> ServiceRunner:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.service.ready.is_set():
            if self.service.stopped.is_set() or time.monotonic() > deadline:
                raise AssertionError(f"service did not start (exit {self.exit_code})")
            time.sleep(0.01)
        return self

    def stop(self, timeout_s: float = 15.0) -> int | None:
        self.service.request_shutdown_threadsafe("test done")
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            import faulthandler
            import sys

            faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        assert not self._thread.is_alive(), "service did not stop"
        return self.exit_code

    def __enter__(self) -> ServiceRunner:
        return self.start()

    def __exit__(self, *exc) -> None:
        if self._thread.is_alive():
            self.stop()


class StallMeter:
    """A thread of the test process that wakes every ``period_s`` and stamps the monotonic clock: where
    its stamps are far apart, the whole process was held (a garbage collection, the test's own work
    holding the interpreter lock, the machine's scheduler), not any one part of it.

    An in-process service shares the interpreter with the test: ``held_s(a, b)`` is how much of the
    interval [a, b] (monotonic seconds) this process was held, which the service could not have used.
    """

    def __init__(self, period_s: float = 0.02) -> None:
        self.period_s = period_s
        self.stamps: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stall-meter", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.stamps.append(time.monotonic())

    def start(self) -> StallMeter:
        self.stamps.append(time.monotonic())
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def held_s(self, a: float, b: float) -> float:
        """The longest stretch inside [a, b] (seconds) between two stamps, less one period."""
        t = np.asarray(self.stamps + [time.monotonic()] if self._thread.is_alive() else self.stamps)
        lo, hi = np.maximum(t[:-1], a), np.minimum(t[1:], b)
        overlap = np.clip(hi - lo, 0.0, None)
        return float(max(overlap.max(initial=0.0) - self.period_s, 0.0))


class Client:
    """A synchronous ZeroMQ control client (REQ or DEALER) and health subscriber."""

    def __init__(self, control: str, health: str | None = None, kind: int = zmq.REQ) -> None:
        self.ctx = zmq.Context()
        self.kind = kind
        self.control_endpoint = control
        self.sock = self._new_sock()
        self.sub = None
        if health is not None:
            self.sub = self.ctx.socket(zmq.SUB)
            self.sub.setsockopt(zmq.LINGER, 0)
            self.sub.setsockopt(zmq.SUBSCRIBE, b"")
            self.sub.connect(health)

    def _new_sock(self):
        sock = self.ctx.socket(self.kind)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVTIMEO, 5000)
        sock.connect(self.control_endpoint)
        return sock

    def raw(self, payload: bytes) -> dict:
        import json

        if self.kind == zmq.DEALER:
            self.sock.send_multipart([payload])
        else:
            self.sock.send(payload)
        return json.loads(self.sock.recv())

    def call(self, cmd: str, **fields) -> dict:
        import json

        return self.raw(json.dumps({"cmd": cmd, **fields}).encode())

    def health(self, timeout_s: float = 3.0, predicate=None) -> dict:
        """The next health message published after this call that satisfies ``predicate``."""
        import json

        assert self.sub is not None
        while self.sub.poll(0):
            self.sub.recv()  # drop the backlog: only messages from now on count
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.sub.poll(50):
                msg = json.loads(self.sub.recv())
                if predicate is None or predicate(msg):
                    return msg
        raise AssertionError("no (matching) health message")

    def close(self) -> None:
        self.sock.close(0)
        if self.sub is not None:
            self.sub.close(0)
        self.ctx.destroy(linger=0)


def avoid_scene_camera(fps_hz: float = 15.0, width_px: int = 672, height_px: int = 376):
    """A sim camera (ideal 90-degree rig, as the default calibration) 1.5 m from a wall on the
    left-front: the default controller avoids to the right (AVOID, yaw about +0.4)."""
    from companion.core.geometry import StereoGeometry
    from companion.sim.render import Box, Pose, Scene
    from companion.service.camera_sim import SimCamera

    geometry = StereoGeometry.ideal(width_px, height_px, hfov_deg=90.0, baseline_m=0.12)
    scene = Scene(
        obstacles=(Box.on_ground(1.5, -0.6, (0.3, 1.2, 3.0)),),
        backdrop_centre_ne_m=(0.0, 0.0),
        backdrop_half_size_m=30.0,
    )
    return SimCamera(geometry, scene, fps_hz, pose=Pose.at(0.0, 0.0, 1.5))


def expected_result(cfg: CompanionConfig, camera):
    """What the pipeline decides for the (fixed) frame of ``camera``: (FrameResult, setpoint)."""
    from companion.core.direct import decision_setpoint
    from companion.backends import make_pipeline

    camera.open()
    frame = camera.read()
    w, h = camera.eye_size_px
    result = make_pipeline(cfg, w, h).process(frame.image, 0.0)
    return result, decision_setpoint(result.decision, cfg)


def avoid_scene_preview_inputs(cfg: CompanionConfig):
    """What the service's preview of :func:`avoid_scene_camera`'s frame is drawn from (with its
    disparity): a :class:`companion.service.preview_frame.PreviewInputs` at time 1.5 s, frame 7."""
    from companion.backends import make_pipeline
    from companion.service.preview_frame import PreviewInputs, near_far_m

    camera = avoid_scene_camera()
    camera.open()
    frame = camera.read()
    pipeline = make_pipeline(cfg, 672, 376)
    result = pipeline.process(frame.image, 0.0, want_disparity=True)
    near, far = near_far_m(cfg)
    return PreviewInputs(
        frame.image, 1.5, 7, result.refined.depth_m, result.decision, result.disparity, pipeline.estimator.layout,
        pipeline.geometry.focal_baseline_px_m, near, far, 64.0,
    )  # fmt: skip


#: The least a test waits for an eventual state, seconds: the suite runs on loaded machines (two busy
#: processes on two cores), where "within 3 s" is a budget, not a behaviour. Only a failing wait is slower.
EVENTUAL_TIMEOUT_S = 30.0


def engage_when_ready(client: "Client", timeout_s: float = 60.0, **goal) -> dict:
    """``engage``, asked again every 0.5 s while the service refuses it for a reason that passes (no
    frame processed yet, frames stale: a loaded machine's first seconds), as an operator would;
    returns the last reply."""
    deadline = time.monotonic() + timeout_s
    while True:
        reply = client.call("engage", **goal)
        message = "" if reply["ok"] else str(reply["error"]["message"])
        passing = any(w in message for w in ("no frame processed yet", "s old", "not delivering", "not known yet", "RateLimited"))
        if reply["ok"] or not passing or time.monotonic() > deadline:
            return reply
        time.sleep(0.5)


def engage_and_wait(client: "Client", link, timeout_s: float = 90.0, **goal) -> None:
    """Engage and wait until the vehicle is in offboard and the service engaged; an engage that the
    service gave up on the way (frames went stale while it engaged: a loaded machine) is asked again."""
    deadline = time.monotonic() + timeout_s
    while True:
        reply = engage_when_ready(client, max(1.0, deadline - time.monotonic()), **goal)
        assert reply["ok"] or "already" in str(reply.get("error")), reply
        t_end = time.monotonic() + 20.0
        while time.monotonic() < min(t_end, deadline):
            state = client.call("status")["result"]["state"]
            if state == "engaged" and link.state().in_offboard:
                return
            if state not in ("engaging", "engaged"):
                break  # given up (stale frames, a refusal): ask again
            time.sleep(0.05)
        assert time.monotonic() < deadline, f"not engaged within {timeout_s} s ({state})"


def wait_until(predicate, timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll ``predicate()`` until it is true or ``timeout_s`` (at least :data:`EVENTUAL_TIMEOUT_S`)
    passes; returns the last value. For eventual states only: never ``assert not wait_until(...)``."""
    deadline = time.monotonic() + max(timeout_s, EVENTUAL_TIMEOUT_S)
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())


class FaultingEstimator:
    """Stands in for the GPU estimator: matches with ``inner`` for ``good_frames`` frames, then every
    frame raises the error a CUDA fault becomes (``device_lost``: a sticky one such as an illegal
    address, which leaves the context unusable)."""

    name = "cupy"

    def __init__(self, inner, good_frames: int, device_lost: bool) -> None:
        self._inner = inner
        self.geometry, self.layout = inner.geometry, inner.layout
        self._left = good_frames
        self._device_lost = device_lost
        self.closed = False

    def estimate(self, frame, **kwargs):
        if self._left > 0:
            self._left -= 1
            return self._inner.estimate(frame, **kwargs)
        raise BackendError(
            "CUDA error in the GPU estimator: cudaErrorIllegalAddress: an illegal memory access was encountered",
            device_lost=self._device_lost,
        )

    def close(self) -> None:
        self.closed = True
