"""``companion process --sequence PATH``: the options and the run (kept here so that the single-frame
command stays as it is)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from companion.errors import InputError


def add_sequence_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--sequence`` options of ``companion process``."""
    g = p.add_argument_group("recorded flights (--sequence)")
    g.add_argument("--out", type=Path, metavar="DIR", help="--sequence: the output folder (records, overlay frames, review.html)")
    g.add_argument("--format", choices=["jsonl", "csv"], default="jsonl", help="--sequence: per-frame records as JSON lines or CSV")
    g.add_argument("--realtime", action="store_true", help="--sequence: at the recorded rate (default: as fast as it runs)")
    g.add_argument("--left-topic", help="--sequence, a rosbag: the left eye's image topic (default: found by name)")
    g.add_argument("--right-topic", help="--sequence, a rosbag: the right eye's image topic")
    g.add_argument("--max-skew-ms", type=float, default=5.0, help="--sequence: the most a left and right frame's times may differ (default 5)")
    g.add_argument("--overlay-every-s", type=float, default=1.0, help="--sequence: recorded seconds between overlay frames in the report (default 1)")
    g.add_argument("--limit", type=int, metavar="N", help="--sequence: stop after N pairs")
    g.add_argument("--json", action="store_true", help="--sequence: print the summary as JSON")


def run_sequence(args: argparse.Namespace, cfg: Any) -> int:
    """Replay ``args.sequence`` under ``cfg``; print the summary."""
    from companion.view.replay import print_summary, replay_sequence
    from companion.recorded.sequence import open_sequence

    if args.right is not None or args.overlay is not None:
        raise InputError("--sequence writes its overlays into --out; leave out --right and --overlay")
    if not args.max_skew_ms > 0:
        raise InputError(f"--max-skew-ms {args.max_skew_ms}: must be above 0")
    if args.limit is not None and args.limit < 1:
        raise InputError(f"--limit {args.limit}: must be at least 1")
    if args.overlay_every_s < 0:
        raise InputError(f"--overlay-every-s {args.overlay_every_s}: must be 0 or more")
    if args.out is None:
        raise InputError("--sequence needs --out DIR (the records, overlay frames and review.html go there)")
    seq = open_sequence(args.sequence, left_topic=args.left_topic, right_topic=args.right_topic, max_skew_ms=args.max_skew_ms)
    out = args.out
    summary = replay_sequence(
        seq,
        cfg,
        out,
        fmt=args.format,
        realtime=args.realtime,
        overlay_every_s=args.overlay_every_s,
        limit=args.limit,
        progress=sys.stderr,
    )
    if args.json:
        json.dump(summary.as_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print_summary(summary)
    return 0
