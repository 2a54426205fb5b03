"""Self-check of the CUDA kernels on the CPU: ``python -m companion.gpu.hostemu`` (needs g++)."""

from __future__ import annotations

import sys

import numpy as np

from companion.config.core import RegionsConfig
from companion.core.disparity.reference import sad_block_match
from companion.core.regions import RegionLayout, reduce_regions_from_disparity
from companion.gpu.hostemu import HostKernels

CASES = [  # (w, h, D, b, u, t, rows per block, bands)
    (200, 90, 128, 9, 10, 3, 11, 1),
    (200, 90, 128, 9, 10, 3, 7, 2),
    (190, 70, 16, 11, 0, 0, 5, 3),
    (250, 80, 112, 15, 5, 2, 20, 1),
    (150, 60, 32, 17, 10, 3, 9, 1),  # fallback kernel
]


def main() -> int:
    rng = np.random.default_rng(0)
    failures = 0
    for w, h, D, b, u, t, rows, bands in CASES:
        left = rng.integers(0, 256, (h, w), dtype=np.uint8)
        right = np.roll(left, -int(rng.integers(3, 20)), axis=1)
        right = np.clip(right.astype(int) + rng.integers(-3, 4, right.shape), 0, 255).astype(np.uint8)
        re, ce = [0, h // 3, 2 * h // 3, h], [0, w // 3, 2 * w // 3, w]
        k = HostKernels(w, h, D, b, u, t, re, ce)
        disp, res = k.disparity(left, right, rows_per_block=rows, bands=bands)
        ref = sad_block_match(left, right, D, b, u, t)
        fd = ref.astype(np.float32)
        fd[ref < 0] = np.nan
        exp = reduce_regions_from_disparity(fd, RegionLayout(np.array(re), np.array(ce)), RegionsConfig(), 50.0)
        ok = np.array_equal(disp, ref) and np.array_equal(res[:9], exp.depth_m, equal_nan=True)
        ok = ok and np.array_equal(res[9:], exp.valid_fraction)
        failures += not ok
        print(f"{w}x{h} D={D} b={b} u={u} t={t} bands={bands}: {'exact' if ok else 'MISMATCH'}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
