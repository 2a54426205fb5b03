"""``companion bench --soak``: the service running for a long time, engaged, with operator traffic.

The real service (capture thread, mailbox, pipeline thread, control loop, control server, health) replays
rendered frames at the camera rate (``--sizes``' first size; 30 fps), engaged (autostart) on an in-memory
vehicle link, while an operator's client asks ``status`` every second, a subscriber reads every health
message, and a ``set_config`` changes a fuzzy controller setting every 30 s. Every ``--sample-s`` seconds it
records the process's resident memory, the setpoints handed over per second, the frame-to-setpoint
latency percentiles of that window, the longest gap between two setpoints handed to the vehicle, and
the frames dropped; the summary says whether memory grew. With ``--flood`` another process floods the
control socket the whole time (:mod:`companion.bench.flood`): what a flood costs the flight path.

The service runs in this process, so the resident size includes the benchmark's own few megabytes.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.bench.common import rendered_frames, rss_bytes, stats_ms
from companion.bench.e2e import BenchVehicleLink, _write_recording
from companion.config import parse_config
from companion.errors import CompanionError
from companion.report import format_table, machine_description
from companion.service.daemon import Service

#: The replayed camera rate, frames per second (a ZED at 672x376 runs at 15 to 100).
SOAK_FPS_HZ = 30.0
#: How often the operator's client changes a fuzzy controller setting (a live tuning change), seconds.
SET_CONFIG_EVERY_S = 30.0


class _Operator:
    """The operator's traffic in a thread: status every second, every health message read, a
    set_config every :data:`SET_CONFIG_EVERY_S`."""

    def __init__(self, control: str, health: str) -> None:
        import zmq

        self._ctx = zmq.Context()
        self._control, self._health = control, health
        self._stop = threading.Event()
        self.health_messages = 0
        self.replies = 0
        self.errors: list[str] = []
        self._thread = threading.Thread(target=self._run, name="soak operator", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._ctx.destroy(linger=0)

    def _run(self) -> None:
        import zmq

        sub = self._ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.connect(self._health)
        req = self._ctx.socket(zmq.DEALER)
        req.connect(self._control)
        next_status = next_set = time.monotonic()
        fractions = (0.1, 0.2)
        n = 0
        while not self._stop.is_set():
            while sub.poll(0):
                sub.recv()
                self.health_messages += 1
            now = time.monotonic()
            if now >= next_status:
                next_status += 1.0
                req.send(json.dumps({"cmd": "status", "id": n}).encode())
                n += 1
            if now >= next_set:
                next_set += SET_CONFIG_EVERY_S
                patch = {"controller": {"avoid_speed_fraction": fractions[n % 2]}}
                req.send(json.dumps({"cmd": "set_config", "id": n, "patch": patch}).encode())
                n += 1
            while req.poll(0):
                reply = json.loads(req.recv())
                self.replies += 1
                if not reply.get("ok"):
                    self.errors.append(reply["error"]["message"])
            sub.poll(50)


def run_soak(args: argparse.Namespace, sizes: list[Any]) -> dict[str, Any]:
    """Run the soak for ``args.duration_s``; prints a row per sample and a summary; returns the figures."""
    size = sizes[0]
    report: dict[str, Any] = {
        "machine": machine_description(),
        "size": size.label,
        "backend": args.backend,
        "fps": SOAK_FPS_HZ,
        "duration_s": args.duration_s,
        "flood": bool(getattr(args, "flood", False)),
        "samples": [],
    }
    print(f"machine: {report['machine']}")
    print(
        f"soak: {size.label}, {args.backend}, {SOAK_FPS_HZ:g} fps replay, {args.duration_s:g} s, a row every "
        f"{args.sample_s:g} s{', the control socket flooded by another process' if report['flood'] else ''}"
    )
    with tempfile.TemporaryDirectory(prefix="companion-soak-") as tmp:
        workdir = Path(tmp)
        _, images = rendered_frames(size, n=60)
        rec = workdir / "rec"
        _write_recording(rec, images, SOAK_FPS_HZ)
        cfg = parse_config(
            {
                "camera": {
                    "source": "replay",
                    "width_px": size.width_px,
                    "height_px": size.height_px,
                    "fps_hz": SOAK_FPS_HZ,
                    "replay_path": str(rec),
                    "replay_rate_hz": SOAK_FPS_HZ,
                    "replay_loop": True,
                    "replay_preload": True,
                    "open_timeout_s": 120.0,  # preloading is slow on a busy machine; the soak measures after
                },
                "calibration": {"ideal_hfov_deg": 87.0},
                "stereo": {"backend": args.backend, "num_disparities": size.num_disparities},
                "bus": {"health_endpoint": f"ipc://{workdir}/health.sock", "control_endpoint": f"ipc://{workdir}/control.sock"},
                "view": {"preview_endpoint": f"ipc://{workdir}/preview.sock"},
                "service": {"autostart": True},
                "vehicle": {"offboard_prestream_s": 0.1},
            },
            source="soak",
        )
        link = BenchVehicleLink()
        service = Service(cfg, link=link, install_signals=False, notifier=None, environ={})
        service.record_latencies = True
        result: dict[str, Any] = {}
        thread = threading.Thread(target=lambda: result.update(exit=asyncio.run(service.run())), name="soak-service", daemon=True)
        thread.start()
        operator = None
        flood = None
        try:
            if not service.ready.wait(60.0):
                raise CompanionError(f"soak: the service did not start (exit code {result.get('exit')})")
            operator = _Operator(service.bus.control_endpoint, service.bus.health_endpoint)
            operator.start()
            if report["flood"]:
                from companion.bench.flood import Flood

                flood = Flood(service.bus.control_endpoint)
                flood.start()
            time.sleep(min(10.0, args.sample_s))  # warm up
            link.take_longest_gap_s()
            rows = []
            t_start = time.monotonic()
            h_prev, t_prev, n_prev = service.health_message(), time.monotonic(), len(service.latencies_s)
            while time.monotonic() - t_start < args.duration_s:
                time.sleep(min(args.sample_s, max(0.0, args.duration_s - (time.monotonic() - t_start))))
                h, t, n = service.health_message(), time.monotonic(), len(service.latencies_s)
                window = np.asarray(service.latencies_s[n_prev:n]) * 1e3
                del service.latencies_s[: max(0, n - 10)]  # keep the list small over an hour
                n = len(service.latencies_s)
                lat = stats_ms(window) if window.size else {"median_ms": float("nan"), "p99_ms": float("nan"), "max_ms": float("nan")}
                sample = {
                    "t_s": round(t - t_start, 1),
                    "rss_mib": rss_bytes() / 2**20,
                    "setpoints_per_s": (h["setpoints_sent"] - h_prev["setpoints_sent"]) / (t - t_prev),
                    "processed_fps": (h["processed_frames"] - h_prev["processed_frames"]) / (t - t_prev),
                    "dropped": h["dropped_frames"] - h_prev["dropped_frames"],
                    "longest_setpoint_gap_ms": link.take_longest_gap_s() * 1e3,
                    "latency_ms": lat,
                    "state": h["state"],
                }
                report["samples"].append(sample)
                rows.append(
                    [
                        f"{sample['t_s']:.0f}",
                        f"{sample['rss_mib']:.1f}",
                        f"{sample['setpoints_per_s']:.1f}",
                        f"{sample['processed_fps']:.1f}",
                        str(sample["dropped"]),
                        f"{sample['longest_setpoint_gap_ms']:.0f}",
                        f"{lat['median_ms']:.1f}",
                        f"{lat['p99_ms']:.1f}",
                        f"{lat['max_ms']:.1f}",
                        sample["state"],
                    ]
                )
                print(" ".join(rows[-1]), flush=True)
                h_prev, t_prev, n_prev = h, t, n
            final = service.health_message()
        finally:
            if flood is not None:
                report["flood_sent"] = flood.stop()
            if operator is not None:
                operator.stop()
            service.request_shutdown_threadsafe("soak done")
            thread.join(30.0)
    samples = report["samples"]
    if not samples:
        raise CompanionError("soak: no sample taken (duration shorter than the warm-up?)")
    rss = [s["rss_mib"] for s in samples]
    report["summary"] = {
        "rss_first_mib": rss[0],
        "rss_last_mib": rss[-1],
        "rss_max_mib": max(rss),
        "setpoints_per_s_min": min(s["setpoints_per_s"] for s in samples),
        "setpoints_per_s_mean": float(np.mean([s["setpoints_per_s"] for s in samples])),
        "latency_p99_ms_max": max(s["latency_ms"]["p99_ms"] for s in samples),
        "longest_setpoint_gap_ms": max(s["longest_setpoint_gap_ms"] for s in samples),
        "latency_median_ms_mean": float(np.nanmean([s["latency_ms"]["median_ms"] for s in samples])),
        "dropped_frames": int(sum(s["dropped"] for s in samples)),
        "processed_frames": int(final["processed_frames"]),
        "processed_twice": int(final["processed_twice"]),
        "frame_errors": int(final["frame_errors"]),
        "operator_replies": operator.replies if operator else 0,
        "operator_errors": operator.errors[:5] if operator else [],
        "health_messages_read": operator.health_messages if operator else 0,
        "states": sorted({s["state"] for s in samples}),
    }
    print(format_table(rows, ["t s", "RSS MiB", "setpoints/s", "proc fps", "dropped", "gap ms", "median ms", "p99 ms", "max ms", "state"]))
    s = report["summary"]
    print(
        f"summary: RSS {s['rss_first_mib']:.1f} -> {s['rss_last_mib']:.1f} MiB (max {s['rss_max_mib']:.1f}); setpoints "
        f"{s['setpoints_per_s_min']:.1f}/s at least, {s['setpoints_per_s_mean']:.1f}/s mean, longest gap "
        f"{s['longest_setpoint_gap_ms']:.0f} ms; latency p99 at most "
        f"{s['latency_p99_ms_max']:.1f} ms; {s['dropped_frames']} frames dropped of {s['processed_frames']} processed; "
        f"{s['processed_twice']} twice; {s['frame_errors']} frame errors; operator {s['operator_replies']} replies, "
        f"{len(s['operator_errors'])} errors; states {', '.join(s['states'])}"
        + (f"; flood sent {report.get('flood_sent')}" if report["flood"] else "")
    )
    return report
