"""A recorded sequence run through the pipeline: what the service would have decided, frame by frame.

:func:`replay_sequence` takes the pairs of an :mod:`~companion.recorded.sequence` sequence through the
configured pipeline (calibration, matcher, regions, LUT and filters, the fuzzy controller) and the
decision's direct setpoint (:func:`~companion.core.direct.decision_setpoint`), and writes into one folder:

* ``frames.jsonl`` (or ``frames.csv``): one record per pair: its time, the 9 region depths (metres,
  null/empty = unknown), the decision, yaw, pitch, the setpoint and the pipeline's time;
* ``health.jsonl``, ``preview/`` (overlay frames: the regions, depths and command arrow on the rectified
  left eye, every ``overlay_every_s`` of recorded time and at each brake or avoid episode's first frame)
  and ``config.toml``: a run folder ``companion review`` reads; ``review.html``, its report;
* ``calibration.yaml`` when the sequence's own calibration (``sensor.yaml``, ``camera_info``) was used.

Time in all of them is the recording's, in seconds from the first pair. The local planner is not
replayed: its map and goal need the vehicle's pose, which a camera recording does not hold; the
setpoint is the decision flown directly at the planner's limits.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from companion.core.rig_check import check_rig, rig_check_lines
from companion.core.types import REGION_NAMES
from companion.errors import FrameError, InputError

__all__ = ["ReplaySummary", "replay_sequence"]

log = logging.getLogger(__name__)

_CSV_FIELDS = (
    ["frame", "time_s", "timestamp_ns", "decision", "yaw", "pitch", "speed_fraction"]
    + [f"{name}_m" for name in REGION_NAMES]
    + ["forward_m_s", "right_m_s", "down_m_s", "yaw_rate_deg_s", "pipeline_ms", "reason"]
)


@dataclass
class ReplaySummary:
    """What a replay did (the figures ``process --sequence`` prints).

    Attributes:
        source: the sequence's name; backend: the disparity backend.
        eye_size_px: ``(width, height)``; calibration: the file used (None: the ideal rig).
        frames: pairs processed; decisions: decision kind -> frames.
        recorded_s: the recording's span, seconds; wall_s: the replay's, seconds.
        pipeline_ms: median and 99th percentile of the pipeline's time per frame, milliseconds.
        sequence: the reader's one-line report (pairs, rate, unmatched frames, gaps, bad frames).
        skipped: frames the pipeline refused (one line each, at most 20 kept).
        out: the output folder; records, review: the records file and the HTML report.
    """

    source: str
    backend: str = ""
    eye_size_px: tuple[int, int] | None = None
    calibration: str | None = None
    frames: int = 0
    decisions: dict[str, int] = field(default_factory=dict)
    recorded_s: float = 0.0
    wall_s: float = 0.0
    pipeline_ms: dict[str, float] = field(default_factory=dict)
    sequence: str = ""
    skipped: list[str] = field(default_factory=list)
    out: Path | None = None
    records: Path | None = None
    review: Path | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "backend": self.backend,
            "eye_size_px": list(self.eye_size_px) if self.eye_size_px else None,
            "calibration": self.calibration,
            "frames": self.frames,
            "decisions": self.decisions,
            "recorded_s": round(self.recorded_s, 3),
            "wall_s": round(self.wall_s, 3),
            "frames_per_s": round(self.frames / self.wall_s, 2) if self.wall_s > 0 else None,
            "pipeline_ms": {k: round(v, 2) for k, v in self.pipeline_ms.items()},
            "sequence": self.sequence,
            "skipped": self.skipped,
            "out": str(self.out) if self.out else None,
            "records": str(self.records) if self.records else None,
            "review": str(self.review) if self.review else None,
        }


class _Progress:
    """A one-line progress bar on a terminal (nothing otherwise)."""

    def __init__(self, stream: IO[str] | None, total: int | None) -> None:
        self.stream = stream if stream is not None and stream.isatty() else None
        self.total = total
        self._last = 0.0

    def update(self, done: int, kind: str, now: float) -> None:
        if self.stream is None or (now - self._last < 0.2 and done != self.total):
            return
        self._last = now
        if self.total:
            frac = min(1.0, done / self.total)
            bar = "#" * int(30 * frac)
            self.stream.write(f"\r[{bar:<30}] {done}/{self.total} {kind:<6}")
        else:
            self.stream.write(f"\r{done} frames {kind:<6}")
        self.stream.flush()

    def close(self) -> None:
        if self.stream is not None:
            self.stream.write("\n")
            self.stream.flush()


def _num(x: float) -> float | None:
    return round(float(x), 4) if math.isfinite(x) else None


def replay_sequence(
    sequence: Any,
    cfg: Any,
    out_dir: Path,
    *,
    fmt: str = "jsonl",
    realtime: bool = False,
    overlay_every_s: float = 1.0,
    limit: int | None = None,
    progress: IO[str] | None = None,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    make_pipeline: Callable[..., Any] | None = None,
) -> ReplaySummary:
    """Run ``sequence`` through the pipeline of ``cfg`` and write the outputs of the module doc.

    Args:
        sequence: an :class:`~companion.recorded.sequence.AslSequence` or ``BagSequence``.
        cfg: the config; without ``calibration.file`` the sequence's own calibration is used when it has
            one (written to ``out_dir/calibration.yaml``), else the ideal rig (a warning is logged).
        out_dir: the output folder (created).
        fmt: ``jsonl`` or ``csv`` for the per-frame records.
        realtime: deliver the pairs at the recorded rate (else as fast as the pipeline runs).
        overlay_every_s: recorded seconds between overlay frames (0: only the brake/avoid moments).
        limit: stop after this many pairs.
        progress: where the progress bar goes when it is a terminal (e.g. ``sys.stderr``).
        clock, sleep: wall clock and sleep, for the recorded rate and the wall time.
        make_pipeline: ``(cfg, width, height) -> Pipeline``; :func:`companion.backends.make_pipeline`.

    Raises:
        InputError: the output folder cannot be written, or the sequence has no pair.
        CalibrationError, ConfigError: the calibration does not fit the frames.
    """
    import cv2

    from companion.config import apply_patch
    from companion.config.document import render_config_toml
    from companion.core.calibration_files import save_calibration
    from companion.core.direct import decision_setpoint
    from companion.core.overlay import draw_overlay
    from companion.core.rectifier import make_rectifier
    from companion.service.preview_frame import near_far_m
    from companion.view.review import write_review

    if fmt not in ("jsonl", "csv"):
        raise InputError(f"records format {fmt!r}: jsonl or csv")
    if make_pipeline is None:
        from companion.backends import make_pipeline as _make

        make_pipeline = _make
    out_dir = Path(out_dir).expanduser().resolve()  # the run's config.toml names its calibration.yaml by this
    preview_dir = out_dir / "preview"
    try:
        preview_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{out_dir}: cannot create the output folder: {err.strerror or err}") from None
    summary = ReplaySummary(source=sequence.name, out=out_dir)
    calib_file = cfg.calibration.file
    if calib_file is None:
        own = sequence.calibration()
        if own is not None:
            calib_file = save_calibration(
                own, out_dir / "calibration.yaml", metadata={"tool": "companion process --sequence", "imported_from": own.source}
            )
    else:
        calib_file = Path(calib_file)
    summary.calibration = str(calib_file) if calib_file is not None else None
    near_m, far_m = near_far_m(cfg)

    records_path = out_dir / f"frames.{fmt}"
    health_path = out_dir / "health.jsonl"
    pipeline = rectifier = None
    decisions: dict[str, int] = {}
    totals_ms: list[float] = []
    recent_ms: deque[float] = deque(maxlen=500)
    t_first_ns: int | None = None
    t_last_ns = 0
    last_overlay_s = -math.inf
    prev_kind: str | None = None
    bar = _Progress(progress, sequence.frame_count if limit is None else min(limit, sequence.frame_count))
    wall0 = clock()
    pairs = None
    try:
        records = records_path.open("w", encoding="utf-8", newline="")
        health = health_path.open("w", encoding="utf-8")
        index_file = (preview_dir / "index.jsonl").open("w", encoding="utf-8")
    except OSError as err:
        raise InputError(f"{out_dir}: cannot write there: {err.strerror or err}") from None
    try:
        writer = csv.DictWriter(records, fieldnames=_CSV_FIELDS) if fmt == "csv" else None
        if writer is not None:
            writer.writeheader()
        pairs = sequence.pairs()
        for pair in pairs:
            if limit is not None and summary.frames >= limit:
                break
            try:
                frame = _side_by_side(pair)
            except FrameError as err:
                _skip(summary, f"pair {pair.index}: {err}")
                continue
            h, w = pair.left.shape[:2]
            if pipeline is None:
                # The run's config is that of the service replaying this recording (its config.toml runs it).
                camera: dict[str, Any] = {
                    "source": "replay", "replay_path": str(Path(sequence.path).resolve()), "width_px": w, "height_px": h,
                    "replay_max_skew_ms": sequence.max_skew_ns / 1e6,
                }
                if sequence.kind == "rosbag":
                    camera["replay_left_topic"], camera["replay_right_topic"] = sequence.topics
                patch: dict[str, Any] = {"camera": camera}
                if calib_file is not None:
                    patch["calibration"] = {"file": str(calib_file)}
                cfg = apply_patch(cfg, patch)
                pipeline = make_pipeline(cfg, w, h)
                # The same rig check, in the same words, as every other tool, on the rig these frames were seen with.
                for line in rig_check_lines(check_rig(pipeline.geometry, cfg.stereo, cfg.regions, cfg.controller)):
                    log.warning("%s: %s", sequence.name, line)
                rectifier = make_rectifier(cfg.calibration, w, h)
                summary.backend = pipeline.estimator.name
                summary.eye_size_px = (w, h)
                if cfg.calibration.file is None:
                    log.warning(
                        "%s: no calibration (none given, none in the recording): the frames are taken as rectified by "
                        "an ideal %.3f m rig; depths are off by as much as the camera differs",
                        sequence.name, cfg.calibration.ideal_baseline_m,
                    )
                (out_dir / "config.toml").write_text(
                    render_config_toml(cfg, [f"# the config of `companion process --sequence {sequence.path}`"]), encoding="utf-8"
                )
            if t_first_ns is None:
                t_first_ns = pair.timestamp_ns
            t_s = (pair.timestamp_ns - t_first_ns) / 1e9
            if realtime:
                due = wall0 + t_s
                now = clock()
                if due > now:
                    sleep(due - now)
            if summary.eye_size_px != (w, h):
                _skip(summary, f"pair {pair.index}: {w}x{h}, not the {summary.eye_size_px[0]}x{summary.eye_size_px[1]} of the first")
                continue
            kind_now = prev_kind
            want_overlay = t_s - last_overlay_s >= overlay_every_s > 0
            try:
                result = pipeline.process(frame, timestamp_s=t_s, want_disparity=want_overlay)
            except FrameError as err:
                _skip(summary, f"pair {pair.index}: {err}")
                continue
            d = result.decision
            kind = d.kind.value
            setpoint = decision_setpoint(d, cfg)
            total_ms = float(result.timings_ms.get("total_ms", 0.0))
            totals_ms.append(total_ms)
            recent_ms.append(total_ms)
            decisions[kind] = decisions.get(kind, 0) + 1
            shown = result.shown_depths_m()
            regions = {name: _num(v) for name, v in zip(REGION_NAMES, shown)}
            sp = {
                "forward_m_s": round(setpoint.forward_m_s, 4),
                "right_m_s": round(setpoint.right_m_s, 4),
                "down_m_s": round(setpoint.down_m_s, 4),
                "yaw_rate_deg_s": round(setpoint.yaw_rate_deg_s, 4),
            }
            rec = {
                "frame": summary.frames,
                "time_s": round(t_s, 6),
                "timestamp_ns": pair.timestamp_ns,
                "decision": kind,
                "yaw": round(d.yaw, 4),
                "pitch": round(d.pitch, 4),
                "speed_fraction": round(d.speed_fraction, 4),
            }
            if writer is not None:
                writer.writerow(
                    {**rec, **{f"{k}_m": ("" if v is None else v) for k, v in regions.items()}, **sp,
                     "pipeline_ms": round(total_ms, 3), "reason": d.reason}
                )
            else:
                records.write(json.dumps({**rec, "regions_m": regions, "setpoint": sp, "pipeline_ms": round(total_ms, 3), "reason": d.reason}) + "\n")
            moment = kind in ("brake", "avoid") and kind != kind_now
            prev_kind = kind
            if want_overlay or moment:
                left_view, _ = rectifier.rectify(pair.left, pair.right)
                image = draw_overlay(
                    left_view, pipeline.estimator.layout, shown, d, near_m=near_m, far_m=far_m,
                    disparity=result.disparity, max_disparity_px=float(cfg.stereo.num_disparities), filtered=result.filtered,
                )
                name = f"{summary.frames:06d}.jpg"
                if cv2.imwrite(str(preview_dir / name), image, [cv2.IMWRITE_JPEG_QUALITY, 80]):
                    index_file.write(json.dumps({"time_s": round(t_s, 6), "file": name}) + "\n")
                if want_overlay:
                    last_overlay_s = t_s
            summary.frames += 1
            wall = clock() - wall0
            report = sequence.report
            health.write(
                json.dumps(
                    {
                        "type": "health",
                        "time_s": round(t_s, 6),
                        "state": "replay",
                        "reason": f"replay of {sequence.name}",
                        "decision": {"kind": kind, "reason": d.reason, "speed_fraction": round(d.speed_fraction, 4)},
                        "yaw": round(d.yaw, 4),
                        "pitch": round(d.pitch, 4),
                        "regions_m": regions,
                        "setpoint": sp,
                        "frame_to_setpoint_ms": {"last": round(total_ms, 3), "p99": round(float(np.percentile(recent_ms, 99)), 3)},
                        "fps": round(summary.frames / wall, 2) if wall > 0 else None,
                        "processed_frames": summary.frames,
                        "dropped_frames": report.unmatched_left + report.unmatched_right + len(report.bad_frames) + len(summary.skipped),
                    }
                )
                + "\n"
            )
            t_last_ns = pair.timestamp_ns
            bar.update(summary.frames, kind, clock())
    finally:
        if pairs is not None:
            pairs.close()  # a replay stopped early (limit, an error) still closes the bag
        bar.close()
        records.close()
        health.close()
        index_file.close()
        sequence.close()
    summary.wall_s = clock() - wall0
    sequence.report.finish()
    summary.sequence = sequence.report.summary()
    if summary.frames == 0:
        first = (sequence.report.bad_frames or summary.skipped or [""])[0]
        raise InputError(
            f"{sequence.name}: no stereo pair could be processed ({summary.sequence})" + (f"; the first: {first}" if first else "")
        )
    summary.decisions = dict(sorted(decisions.items()))
    summary.recorded_s = (t_last_ns - (t_first_ns or t_last_ns)) / 1e9
    summary.pipeline_ms = {"median": float(np.median(totals_ms)), "p99": float(np.percentile(totals_ms, 99))}
    summary.records = records_path
    summary.review = write_review(out_dir, out_dir / "review.html")
    return summary


def _side_by_side(pair: Any) -> np.ndarray:
    from companion.recorded.sequence import side_by_side

    return side_by_side(pair.left, pair.right)


def _skip(summary: ReplaySummary, line: str) -> None:
    log.warning("%s", line)
    if len(summary.skipped) < 20:
        summary.skipped.append(line)


def print_summary(summary: ReplaySummary, stream: IO[str] = sys.stdout) -> None:
    """The figures of a replay as a few lines for a person."""
    s = summary
    w, h = s.eye_size_px or (0, 0)
    decisions = ", ".join(f"{k} {v}" for k, v in s.decisions.items())
    rate = f"{s.frames / s.wall_s:.1f} frames/s" if s.wall_s > 0 else ""
    lines = [
        f"replayed {s.source}: {s.sequence}",
        f"  {s.frames} frames of {w}x{h} in {s.wall_s:.1f} s ({rate}; recorded span {s.recorded_s:.1f} s), backend {s.backend}, "
        f"pipeline median {s.pipeline_ms.get('median', 0):.1f} ms, p99 {s.pipeline_ms.get('p99', 0):.1f} ms",
        f"  decisions: {decisions}",
        f"  calibration: {s.calibration or 'none (ideal rig)'}",
        f"  records {s.records}, report {s.review}",
    ]
    lines += [f"  skipped: {line}" for line in s.skipped[:5]]
    stream.write("\n".join(lines) + "\n")
