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

from companion.backends import cuda_available
from companion.bench.common import rendered_frames, stats_ms
from companion.config import parse_config
from companion.core.types import VelocitySetpoint
from companion.errors import CompanionError
from companion.interfaces import VehicleState
from companion.report import format_table, machine_description
from companion.service.daemon import Service
from companion.service.recording import RecordingWriter

log = logging.getLogger(__name__)

STREAM_FPS_HZ = 60.0


class BenchVehicleLink:
    """An in-memory vehicle: connected, armed, and in OFFBOARD as soon as it is asked."""

    def __init__(self) -> None:
        self._state = VehicleState(connected=True, armed=True, flight_mode="POSCTL", in_offboard=False)
        self.setpoints = 0
        self._last_setpoint_s: float | None = None
        self._longest_gap_s = 0.0

    def take_longest_gap_s(self) -> float:
        """The longest time between two setpoints since the last call, seconds (then starts again)."""
        gap, self._longest_gap_s = self._longest_gap_s, 0.0
        return gap

    async def connect(self, timeout_s: float) -> None:
        self._state = replace(self._state, timestamp_s=time.monotonic())

    async def send_setpoint(self, setpoint: VelocitySetpoint) -> None:
        now = time.monotonic()
        if self._last_setpoint_s is not None:
            self._longest_gap_s = max(self._longest_gap_s, now - self._last_setpoint_s)
        self._last_setpoint_s = now
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


def _write_recording(folder: Path, frames: list[np.ndarray], fps_hz: float) -> None:
    with RecordingWriter(folder, fps_hz) as writer:
        for i, image in enumerate(frames):
            writer.write(image, i / fps_hz, i + 1)


#: ``--viewer alternate``: seconds of each window with and without a subscriber.
VIEWER_WINDOW_S = 2.0
#: Latencies skipped after each change of subscription (the preview thread changing state).
_SETTLE_SAMPLES = 6


def measure_e2e(
    size: Any,
    backend: str,
    frames: int,
    warmup: int,
    workdir: Path,
    max_wall_s: float = 120.0,
    service_options: dict[str, Any] | None = None,
    viewer: bool | str = False,
    window_s: float = VIEWER_WINDOW_S,
    stream_fps_hz: float = STREAM_FPS_HZ,
) -> dict[str, Any]:
    """Run the service on a replayed recording (``stream_fps_hz``, 60 by default) at ``size`` with
    ``backend``; return the figures.

    ``service_options`` override fields of the ``[service]`` section (e.g. skip_late_frames).
    ``viewer``: ``"on"`` (or True): a preview subscriber watches the whole run (what ``companion view``
    costs the service); ``"alternate"``: it subscribes and unsubscribes every ``window_s`` seconds, and
    each latency is counted with the state of its window (:func:`viewer_cost`), so that both states see
    the same machine; ``"off"`` (or False): nobody watches.
    """
    mode = ("on" if viewer else "off") if isinstance(viewer, bool) else viewer
    if mode not in ("off", "on", "alternate"):
        raise ValueError(f"viewer must be off, on or alternate, not {viewer!r}")

    _, images = rendered_frames(size, n=min(60, frames + warmup))
    rec = workdir / f"rec_{size.width_px}x{size.height_px}_{stream_fps_hz:g}fps"
    if not rec.exists():
        _write_recording(rec, images, stream_fps_hz)
    cfg = parse_config(
        {
            "camera": {
                "source": "replay",
                "width_px": size.width_px,
                "height_px": size.height_px,
                "fps_hz": stream_fps_hz,
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
    # (index into service.latencies_s, subscribed) at every change of the viewer's subscription.
    toggles: list[tuple[int, bool]] = []

    def watch() -> None:
        import zmq

        ctx = zmq.Context()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.connect(cfg.view.preview_endpoint)
        subscribed = False
        next_toggle = 0.0
        while viewing.is_set():
            now = time.monotonic()
            if now >= next_toggle and (mode == "alternate" or not subscribed):
                subscribed = not subscribed
                sub.setsockopt(zmq.SUBSCRIBE if subscribed else zmq.UNSUBSCRIBE, b"preview")
                toggles.append((len(service.latencies_s), subscribed))
                next_toggle = now + window_s
            if sub.poll(20):
                sub.recv_multipart()
                previews[0] += 1
        sub.close(0)
        ctx.destroy(linger=0)

    watcher = threading.Thread(target=watch, name="e2e-viewer", daemon=True)
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
        if mode != "off":
            # The preview worker's start-up (seconds on a busy machine) is no part of the viewer's cost.
            if service.view is not None and service.view.publisher is not None:
                service.view.publisher.warm_up()
            viewing.set()
            watcher.start()
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
    cost = viewer_cost(service.latencies_s, toggles, n0, n0 + len(latencies)) if mode == "alternate" else None
    return {
        "backend": service.config.stereo.backend,
        "stream_fps": stream_fps_hz,
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
        "viewer": mode,
        "previews_received": previews[0],
        "viewer_cost": cost,
    }


def viewer_cost(
    latencies_s: list[float], toggles: list[tuple[int, bool]], start: int, stop: int, resamples: int = 2000, seed: int = 0
) -> dict[str, Any]:
    """Split latencies ``[start, stop)`` by the viewer's subscription when each frame's setpoint was
    handed over (``toggles``: (index, subscribed) at every change; the first few after each change are
    skipped), and compare: medians, p99s, and the p99 difference with a 95 % bootstrap interval.

    Returns:
        ``{"watched": stats, "unwatched": stats, "p99_diff_ms", "p99_diff_ci95_ms": [lo, hi],
        "median_diff_ms", "windows": n}`` (milliseconds; diff = watched - unwatched).
    """
    lat = np.asarray(latencies_s, dtype=np.float64) * 1e3
    state = np.zeros(len(lat), dtype=np.int8)  # 0 none yet, 1 watched, 2 unwatched, 3 settling
    for k, (idx, sub) in enumerate(toggles):
        end = toggles[k + 1][0] if k + 1 < len(toggles) else len(lat)
        state[idx:end] = 1 if sub else 2
        state[idx : min(end, idx + _SETTLE_SAMPLES)] = 3
    sel = slice(start, stop)
    on, off = lat[sel][state[sel] == 1], lat[sel][state[sel] == 2]
    if on.size < 10 or off.size < 10:
        raise CompanionError(f"e2e bench: too few samples to compare ({on.size} watched, {off.size} unwatched)")
    rng = np.random.default_rng(seed)
    diffs = np.percentile(rng.choice(on, (resamples, on.size)), 99, axis=1) - np.percentile(
        rng.choice(off, (resamples, off.size)), 99, axis=1
    )
    return {
        "watched": {"n": int(on.size), **stats_ms(on)},
        "unwatched": {"n": int(off.size), **stats_ms(off)},
        "median_diff_ms": float(np.median(on) - np.median(off)),
        "p99_diff_ms": float(np.percentile(on, 99) - np.percentile(off, 99)),
        "p99_diff_ci95_ms": [float(x) for x in np.percentile(diffs, [2.5, 97.5])],
        "windows": len(toggles),
    }


def run_e2e_bench(args: argparse.Namespace, sizes: list[Any]) -> dict[str, Any]:
    """Frame-to-setpoint latency for each size with ``args.backend`` (and cupy too when CUDA is there)."""
    backends = [args.backend]
    if args.backend != "cupy" and cuda_available():
        backends.append("cupy")
    fps = float(getattr(args, "stream_fps", None) or STREAM_FPS_HZ)
    report: dict[str, Any] = {"machine": machine_description(), "stream_fps": fps, "runs": {}}
    print(f"machine: {report['machine']}")
    viewer = getattr(args, "viewer", "off")
    watched = {
        "on": " with a preview viewer subscribed",
        "alternate": f", a preview viewer subscribed in every other {VIEWER_WINDOW_S:g} s window",
    }.get(viewer, ", nobody watching the preview")
    print(f"e2e: frame-to-setpoint over a replayed {fps:g} fps stream ({args.frames} frames after {args.warmup} warm-up){watched}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="companion-e2e-") as tmp:
        for size in sizes:
            for backend in backends:
                fig = measure_e2e(
                    size, backend, args.frames, args.warmup, Path(tmp), viewer=viewer,
                    max_wall_s=max(120.0, 3.0 * args.frames / fps), stream_fps_hz=fps,
                )  # fmt: skip
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
        if fig["viewer"] != "off":
            print(f"{key}: {fig['previews_received']} preview frames received by the viewer")
        cost = fig["viewer_cost"]
        if cost is not None:
            w, u = cost["watched"], cost["unwatched"]
            lo, hi = cost["p99_diff_ci95_ms"]
            print(
                f"{key}: watched {w['n']} frames median {w['median_ms']:.2f} p99 {w['p99_ms']:.2f} ms; unwatched {u['n']} "
                f"median {u['median_ms']:.2f} p99 {u['p99_ms']:.2f} ms; the viewer's cost: median "
                f"{cost['median_diff_ms']:+.2f} ms, p99 {cost['p99_diff_ms']:+.2f} ms (95 % interval {lo:+.2f} .. {hi:+.2f})"
            )
        gcs = fig["gc_collections"]
        print(
            f"{key}: garbage collections during the run gen0/1/2 = {gcs['gen0']}/{gcs['gen1']}/{gcs['gen2']}, "
            f"longest {fig['gc_pause_max_ms']:.2f} ms"
        )
    return report
