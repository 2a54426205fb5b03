"""A simulated flight shown by ``companion view``: ``companion demo --view`` and ``companion sim --view``.

:class:`SimViewBridge` publishes the flight as the service would: health messages (the service's
fields, from the simulator's setpoint ticks) on a PUB socket and the preview on the service's own
:class:`~companion.service.preview.PreviewPublisher` (drawn in its thread, only while the page
watches), both on private localhost endpoints, and runs ``companion view`` on them as a child process
(read-only: a simulation has no control socket). After the flight the page shows the outcome.
"""

from __future__ import annotations

import logging
import re
import subprocess
import sys
import threading
import time
from types import SimpleNamespace
from typing import Any

from companion.core.geometry import StereoGeometry
from companion.core.regions import region_layout
from companion.core.types import REGION_NAMES
from companion.core.words import decision_words
from companion.errors import InputError
from companion.service.preview import PreviewPublisher
from companion.service.preview_frame import thresholds_m
from companion.service.protocol import encode
from companion.sim.loop import fly, simulator_config

log = logging.getLogger(__name__)


class SimViewBridge:
    """Publishes one simulated flight for the web view, and serves the view.

    Args:
        cfg: the flight's whole config (as :func:`companion.sim.loop.fly` gets it).
        course_name: shown in the state's reason.
        host, port: where ``companion view`` serves (``--host``/``--port``).
        title: the page's title.
    """

    def __init__(self, cfg: Any, course_name: str, *, host: str = "127.0.0.1", port: int = 8080, title: str = "companion sim") -> None:
        self.cfg = simulator_config(cfg)
        sim = self.cfg.sim
        geometry = StereoGeometry.ideal(
            sim.eye_width_px, sim.eye_height_px, self.cfg.calibration.ideal_hfov_deg, self.cfg.calibration.ideal_baseline_m
        )
        # What the preview draws with: the same rig and layout as the flight's pipeline.
        self._pipeline_info = SimpleNamespace(
            config=self.cfg, geometry=geometry, estimator=SimpleNamespace(layout=region_layout(geometry, self.cfg.regions))
        )
        self.course_name = course_name
        self.host, self.port, self.title = host, port, title
        self._ctx: Any = None
        self._pub: Any = None
        self.publisher: Any = None
        self._proc: subprocess.Popen[str] | None = None
        self.urls: list[str] = []
        self._seq = 0
        self._frames: list[float] = []
        self._processed = 0
        self._sent = 0
        self._last_step: Any = None
        self._state, self._reason = "engaged", f"simulation: flying {course_name}"
        self._lock = threading.Lock()
        self._linger: threading.Thread | None = None
        self._stop = threading.Event()
        self._finished_at: float | None = None

    def start(self, timeout_s: float = 20.0) -> list[str]:
        """Bind the sockets, start ``companion view``; returns the URLs it serves.

        Raises:
            InputError: the view did not start (its output in the message).
        """
        import zmq

        self._ctx = zmq.Context()
        self._pub = self._ctx.socket(zmq.PUB)
        self._pub.setsockopt(zmq.LINGER, 0)
        self._pub.setsockopt(zmq.SNDHWM, 100)
        self._pub.bind("tcp://127.0.0.1:*")
        health_endpoint = self._pub.getsockopt_string(zmq.LAST_ENDPOINT)
        self.publisher = PreviewPublisher(lambda: self.cfg.view, "tcp://127.0.0.1:*", clock=time.monotonic)
        self.publisher.start(warm_up=True)  # the page is about to watch: no start-up before its first picture
        cmd = [
            sys.executable, "-m", "companion", "view", "--no-control",
            "--health-endpoint", health_endpoint, "--preview-endpoint", self.publisher.endpoint,
            "--host", self.host, "--port", str(self.port), "--title", self.title, "--until-input-closes",
        ]
        # Its input is a pipe this process holds: however this process ends (killed too), the pipe
        # closes and the page goes with it, instead of serving on with nobody feeding it.
        self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.PIPE, text=True)
        lines: list[str] = []
        found = threading.Event()

        def follow() -> None:
            assert self._proc is not None and self._proc.stdout is not None
            for line in self._proc.stdout:
                line = line.rstrip("\n")
                lines.append(line)
                m = re.search(r"companion view: open (\S+)", line)
                if m:
                    self.urls.append(m.group(1))
                    found.set()
                elif "ERROR" in line or "error:" in line:
                    log.warning("view: %s", line)

        threading.Thread(target=follow, name="view-output", daemon=True).start()
        deadline = time.monotonic() + timeout_s
        while not found.wait(0.05):
            if self._proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise InputError("companion view did not start:\n" + "\n".join(lines[-15:]))
        time.sleep(0.1)  # the rest of its addresses
        return list(self.urls)

    # ------------------------------------------------------------------ fed by the flight

    def on_frame(self, frame: Any, result: Any) -> None:
        """``fly(on_frame=...)``: count the frame and offer it to the preview when one is due."""
        self._processed += 1
        self._frames.append(float(frame.timestamp_s))
        if self.publisher is not None and self.publisher.wants_frame():
            self.publisher.offer(frame, result, self._pipeline_info)

    def on_step(self, step: Any) -> None:
        """``fly(on_step=...)``: every setpoint tick; a health message at 10 Hz of simulated time."""
        self._sent += 1
        self._last_step = step
        if self._sent % 2 == 1:
            self._publish(step)

    def finish(self, result: Any) -> None:
        """The flight is over: say how it ended, and keep the page alive (health at 2 Hz) until :meth:`close`."""
        self._state = "finished"
        self._finished_at = time.monotonic()
        self._reason = f"simulation over: {result.outcome.value} ({'success' if result.success else 'FAIL'}): {result.reason}"
        step = self._last_step

        def linger() -> None:
            while not self._stop.wait(0.5):
                self._publish(step, wall=True)

        self._publish(step)
        self._linger = threading.Thread(target=linger, name="view-linger", daemon=True)
        self._linger.start()

    def view_alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def close(self) -> None:
        self._stop.set()
        if self._linger is not None:
            self._linger.join(2.0)
        if self._proc is not None and self._proc.stdin is not None:
            self._proc.stdin.close()
        if self._proc is not None and self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        if self.publisher is not None:
            self.publisher.close()
            self.publisher = None
        if self._pub is not None:
            self._pub.close(0)
            self._pub = None
        if self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None

    # ------------------------------------------------------------------ the health message

    def _publish(self, step: Any, wall: bool = False) -> None:
        import zmq

        if self._pub is None or step is None:
            return
        with self._lock:
            self._seq += 1
            message = self._health(step)
            if wall and self._finished_at is not None:  # lingering: the clock goes on, the timeline scrolls
                message["time_s"] = step.t_s + (time.monotonic() - self._finished_at)
        try:
            self._pub.send(encode(message), flags=zmq.NOBLOCK)
        except zmq.Again:
            pass

    def _health(self, step: Any) -> dict[str, Any]:
        res = step.result
        decision = res.decision if res is not None else None
        publisher = self.publisher
        preview = publisher.status() if publisher is not None else {"published": 0, "errors": 0, "failing": None}
        recent = [t for t in self._frames[-64:] if step.t_s - t <= 1.0]
        sp = step.setpoint
        engaged = self._state == "engaged" and step.in_offboard
        return {
            "type": "health",
            "seq": self._seq,
            "time_s": step.t_s,
            "unix_time_s": time.time(),
            "state": self._state if step.in_offboard or self._state == "finished" else "failsafe",
            "reason": self._reason,
            "engaged": engaged,
            "config_version": 1,
            "fps": float(len(recent)),
            "frame_age_ms": step.frame_age_s * 1e3 if step.frame_age_s is not None else None,
            "stages_ms": dict(res.timings_ms) if res is not None else {},
            "frame_to_setpoint_ms": {
                "last": self.cfg.sim.processing_latency_s * 1e3,
                "median": self.cfg.sim.processing_latency_s * 1e3,
                "p99": self.cfg.sim.processing_latency_s * 1e3,
                "samples": self._processed,
            },
            "regions_m": res.refined.as_dict() if res is not None else {n: None for n in REGION_NAMES},
            "yaw": decision.yaw if decision is not None else None,
            "pitch": decision.pitch if decision is not None else None,
            "decision": (
                {"kind": decision.kind.value, "speed_fraction": decision.speed_fraction, "reason": decision.reason,
                 "words": decision_words(decision.kind, decision.yaw, decision.pitch, res.refined.depth_m,
                                         decision.speed_fraction)}
                if decision is not None
                else None
            ),
            "setpoint": {
                "forward_m_s": sp.forward_m_s,
                "right_m_s": sp.right_m_s,
                "down_m_s": sp.down_m_s,
                "yaw_rate_deg_s": sp.yaw_rate_deg_s,
            },
            "setpoint_age_ms": 0.0,
            "setpoints_sent": self._sent,
            "override": None,
            "camera": {
                "source": "sim (simulated flight)",
                "status": "streaming" if self._state == "engaged" else "stopped",
                "fps": float(len(recent)),
                "frames": self._processed,
                "reconnects": 0,
                "last_error": None,
            },
            "vehicle": {
                "link": "simulated",
                "flight_mode": "OFFBOARD" if step.in_offboard else "HOLD",
                "armed": True,
                "in_offboard": bool(step.in_offboard),
                "position_ned_m": step.position_ned_m.tolist(),
                "attitude_rad": step.attitude_rad.tolist(),
                "velocity_ned_m_s": step.velocity_ned_m_s.tolist(),
            },
            "processed_frames": self._processed,
            "dropped_frames": 0,
            "processed_twice": 0,
            "frame_errors": 0,
            "last_error": preview["failing"] and f"preview: {preview['failing']}",
            "thresholds_m": thresholds_m(self.cfg),
            "preview": preview,
        }


def fly_with_view(course: Any, cfg: Any, *, host: str, port: int, title: str, on_frame: Any = None, on_urls: Any = None) -> Any:
    """Fly ``course`` in real time with the web view; returns (FlightResult, bridge): the page stays
    up, showing the outcome, until :func:`linger` closes it."""
    bridge = SimViewBridge(cfg, course.name, host=host, port=port, title=title)
    urls = bridge.start()
    if on_urls is not None:
        on_urls(urls)

    def frame_hook(frame: Any, result: Any) -> None:
        bridge.on_frame(frame, result)
        if on_frame is not None:
            on_frame(frame, result)

    try:
        result = fly(course, cfg, realtime=True, want_disparity=True, on_frame=frame_hook, on_step=bridge.on_step)
        bridge.finish(result)
        return result, bridge
    except BaseException:
        bridge.close()
        raise


def linger(bridge: SimViewBridge, linger_s: float | None) -> None:
    """Keep the page up ``linger_s`` seconds (None: until Ctrl-C), then close it."""
    try:
        deadline = None if linger_s is None else time.monotonic() + linger_s
        while (deadline is None or time.monotonic() < deadline) and bridge.view_alive():
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        bridge.close()
