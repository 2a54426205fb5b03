#!/usr/bin/env python3
"""Regenerate samples/ (the small captures README and docs/first-flight.md run their commands on) with
the project's own renderer: a side-by-side frame and its calibration, chessboard views, LUT captures.

    python tools/gen-samples.py            # writes samples/ next to this folder
"""

import sys
from pathlib import Path

from companion.sim.render.samples import write_samples

#: The most one sample file may weigh, bytes (a test keeps them under it).
MAX_BYTES = 200_000

root = Path(__file__).resolve().parent.parent
files = write_samples(root / "samples")
for path in files:
    size = path.stat().st_size
    print(f"{path.relative_to(root)}  {size / 1000:.0f} kB")
    if size > MAX_BYTES:
        sys.exit(f"{path}: {size} bytes, over {MAX_BYTES}")
