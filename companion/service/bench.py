"""``companion bench --e2e``: the service's frame-to-setpoint latency over a replayed 60 fps stream.

For each size (and backend): rendered ZED-like frames are written as a recording with 60 fps
timestamps, and the real service (capture thread, one-slot mailbox, pipeline worker, control loop,
supervisor) replays it, engaged (autostart) on an in-memory vehicle link that accepts offboard at once.
The latency of a frame is from its capture timestamp (the replay source stamps it when it hands the
frame over, as the UVC source does at read) to the moment the setpoint derived from it has been handed
to the vehicle link. The service counts frames it never processed (dropped: replaced in the mailbox
before the pipeline was free) and proves that no frame was processed twice (strictly increasing
sequence numbers).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import logging
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from companion.core.types import VelocitySetpoint
from companion.errors import CompanionError
from companion.interfaces import VehicleState

log = logging.getLogger(__name__)

STREAM_FPS_HZ = 60.0


class BenchVehicleLink:
    """An in-memory vehicle: connected, armed, and in OFFBOARD as soon as it is asked."""

    def __init__(self) -> None:
        self._state = VehicleState(connected=True, armed=True, flight_mode="POSCTL", in_offboard=False)
        self.setpoints = 0

    async def connect(self, timeout_s: float) -> None:
        self._state = replace(self._state, timestamp_s=time.monotonic())

    async def send_setpoint(self, setpoint: VelocitySetpoint) -> None:
        self.setpoints += 1

    async def start_offboard(self) -> None:
        self._state = replace(self._state, flight_mode="OFFBOARD", in_offboard=True, timestamp_s=time.monotonic())

    async def hold(self) -> None:
        self._state = replace(self._state, flight_mode="HOLD", in_offboard=False, timestamp_s=time.monotonic())

    async def stop_setpoints(self) -> None:
        pass

    def state(self) -> VehicleState:
        return self._state

    async def close(self) -> None:
        pass


def _write_recording(folder: Path, frames: list[np.ndarray]) -> None:
    from companion.service.recording import RecordingWriter

    with RecordingWriter(folder, STREAM_FPS_HZ) as writer:
        for i, image in enumerate(frames):
            writer.write(image, i / STREAM_FPS_HZ, i + 1)


def measure_e2e(
    size: Any,
    backend: str,
    frames: int,
    warmup: int,
    workdir: Path,
    max_wall_s: float = 120.0,
    service_options: dict[str, Any] | None = None,
    viewer: bool = False,
) -> dict[str, Any]:
    """Run the service on a replayed 60 fps recording at ``size`` with ``backend``; return the figures.

    ``service_options`` override fields of the ``[service]`` section (e.g. skip_late_frames).
    ``viewer``: a preview subscriber watches the whole run (what ``companion view`` costs the service).
    """
    from companion.bench import rendered_frames, stats_ms
    from companion.config import parse_config
    from companion.service.daemon import Service

    _, images = rendered_frames(size, n=min(60, frames + warmup))
    rec = workdir / f"rec_{size.width_px}x{size.height_px}"
    if not rec.exists():
        _write_recording(rec, images)
    cfg = parse_config(
        {
            "camera": {
                "source": "replay",
                "width_px": size.width_px,
                "height_px": size.height_px,
                "fps_hz": STREAM_FPS_HZ,
                "replay_path": str(rec),
                "replay_loop": True,
                "replay_preload": True,
            },
            "calibration": {"ideal_hfov_deg": 87.0},
            "stereo": {"backend": backend, "num_disparities": size.num_disparities},
            "bus": {
                "health_endpoint": f"ipc://{workdir}/health.sock",
                "control_endpoint": f"ipc://{workdir}/control.sock",
            },
            "view": {"preview_endpoint": f"ipc://{workdir}/preview.sock"},
            "service": {"autostart": True, **(service_options or {})},
            "vehicle": {"offboard_prestream_s": 0.1},
        },
        source="e2e bench",
    )
    link = BenchVehicleLink()
    service = Service(cfg, link=link, install_signals=False, notifier=None, environ={})
    collections = {0: 0, 1: 0, 2: 0}
    gc_ms: list[float] = []
    gc_t0: list[float] = [0.0]

    def on_gc(phase: str, info: dict) -> None:
        # Diagnostics: how often, and how long, the collector paused the process during the run.
        if phase == "start":
            gc_t0[0] = time.perf_counter()
        else:
            collections[info["generation"]] += 1
            gc_ms.append((time.perf_counter() - gc_t0[0]) * 1e3)

    service.record_latencies = True
    service.record_seqs = True
    result: dict[str, Any] = {}

    def run() -> None:
        result["exit"] = asyncio.run(service.run())

    thread = threading.Thread(target=run, name="e2e-service", daemon=True)
    t0 = time.monotonic()
    thread.start()
    previews = [0]
    viewing = threading.Event()

    def watch() -> None:
        import zmq

        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"preview")
        sub.connect(cfg.view.preview_endpoint)
        while viewing.is_set():
            if sub.poll(100):
                sub.recv_multipart()
                previews[0] += 1
        sub.close(0)
        ctx.term()

    watcher = threading.Thread(target=watch, name="e2e-viewer", daemon=True)
    if viewer:
        viewing.set()
        watcher.start()
    try:
        deadline = time.monotonic() + 60.0
        while not service.ready.wait(0.1):
            if not thread.is_alive():
                raise CompanionError(
                    f"e2e bench: the service exited during start-up (exit code {result.get('exit')}); "
                    "its log above says why"
                )
            if time.monotonic() > deadline:
                raise CompanionError("e2e bench: the service did not start within 60 s")
        t_ready = time.monotonic()
        # Warm up, then count from a clean slate.
        while len(service.latencies_s) < warmup and time.monotonic() - t_ready < max_wall_s:
            time.sleep(0.01)
        health0 = service.health_message()
        gc.callbacks.append(on_gc)
        n0 = len(service.latencies_s)
        seq0 = len(service.processed_seqs)
        t_start = time.monotonic()
        while len(service.latencies_s) - n0 < frames and time.monotonic() - t_start < max_wall_s:
            time.sleep(0.01)
        t_stop = time.monotonic()
        health1 = service.health_message()
        latencies = list(service.latencies_s[n0 : n0 + frames])
        seqs = list(service.processed_seqs[seq0:])
    finally:
        viewing.clear()
        if watcher.is_alive():
            watcher.join(2.0)
        if on_gc in gc.callbacks:
            gc.callbacks.remove(on_gc)
        service.request_shutdown_threadsafe("bench done")
        thread.join(30.0)
    if not latencies:
        raise CompanionError(f"no frame-to-setpoint latency measured (service state {health1['state']}: {health1['reason']})")
    seq_arr = np.asarray(seqs, np.int64)
    processed = int(health1["processed_frames"] - health0["processed_frames"])
    dropped = int(health1["dropped_frames"] - health0["dropped_frames"])
    captured = int(health1["camera"]["frames"] - health0["camera"]["frames"])
    stats = stats_ms(np.asarray(latencies) * 1e3)
    return {
        "backend": service.config.stereo.backend,
        "stream_fps": STREAM_FPS_HZ,
        "latency_ms": stats,
        "samples": len(latencies),
        "captured_frames": captured,
        "processed_frames": processed,
        "dropped_frames": dropped,
        "processed_twice": int(health1["processed_twice"]) + int(np.sum(np.diff(seq_arr) <= 0)) if seq_arr.size > 1 else 0,
        "processing_fps": processed / max(1e-9, t_stop - t_start),
        "pipeline_total_ms_last": health1["stages_ms"].get("total_ms"),
        "wall_s": time.monotonic() - t0,
        "gc_collections": {f"gen{g}": n for g, n in collections.items()},
        "gc_pause_max_ms": max(gc_ms, default=0.0),
        "latencies_ms": [round(x * 1e3, 4) for x in latencies],
        "viewer": viewer,
        "previews_received": previews[0],
    }


def run_e2e_bench(args: argparse.Namespace, sizes: list[Any]) -> dict[str, Any]:
    """Frame-to-setpoint latency for each size with ``args.backend`` (and cupy too when CUDA is there)."""
    from companion.bench import format_table, machine_description
    from companion.backends import cuda_available

    backends = [args.backend]
    if args.backend != "cupy" and cuda_available():
        backends.append("cupy")
    report: dict[str, Any] = {"machine": machine_description(), "stream_fps": STREAM_FPS_HZ, "runs": {}}
    print(f"machine: {report['machine']}")
    watched = " with a preview viewer subscribed" if getattr(args, "viewer", False) else ", nobody watching the preview"
    print(f"e2e: frame-to-setpoint over a replayed {STREAM_FPS_HZ:g} fps stream ({args.frames} frames after {args.warmup} warm-up){watched}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="companion-e2e-") as tmp:
        for size in sizes:
            for backend in backends:
                fig = measure_e2e(size, backend, args.frames, args.warmup, Path(tmp), viewer=getattr(args, "viewer", False))
                key = f"{size.label}/{backend}"
                report["runs"][key] = fig
                lat = fig["latency_ms"]
                rows.append(
                    [
                        size.label,
                        backend,
                        f"{lat['median_ms']:.2f}",
                        f"{lat['p99_ms']:.2f}",
                        f"{lat['max_ms']:.2f}",
                        f"{fig['processing_fps']:.1f}",
                        str(fig["captured_frames"]),
                        str(fig["processed_frames"]),
                        str(fig["dropped_frames"]),
                        str(fig["processed_twice"]),
                    ]
                )
    print(
        format_table(
            rows,
            ["size/disp", "backend", "median ms", "p99 ms", "max ms", "proc fps", "captured", "processed", "dropped", "twice"],
        )
    )
    for key, fig in report["runs"].items():
        if fig["viewer"]:
            print(f"{key}: {fig['previews_received']} preview frames received by the viewer")
        gcs = fig["gc_collections"]
        print(
            f"{key}: garbage collections during the run gen0/1/2 = {gcs['gen0']}/{gcs['gen1']}/{gcs['gen2']}, "
            f"longest {fig['gc_pause_max_ms']:.2f} ms"
        )
    return report
