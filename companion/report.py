"""Plain-text reports: fixed-width tables and the one line that names the machine a figure comes from."""

from __future__ import annotations

import os
import platform
from collections.abc import Iterable, Sequence

import cv2
import numpy as np


def machine_description() -> str:
    """One line: CPU model, core count, Python and OpenCV versions."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads), NumPy {np.__version__}"
    )


def format_table(rows: Iterable[Sequence[object]], header: Sequence[str]) -> str:
    """A plain fixed-width text table."""
    rows = [[str(c) for c in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]
    line = "  ".join(h.ljust(w) for h, w in zip(header, widths))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows]
    return "\n".join(out)
