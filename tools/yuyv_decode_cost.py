"""What `camera.pixels = "luma"` saves the host per frame (docs/benchmarks.md).

Times, on one OpenCV thread, the two ways a YUYV side-by-side frame becomes the pipeline's two grey
eyes: OpenCV's decoding to BGR (what ``CAP_PROP_CONVERT_RGB`` on does inside the capture) followed by
:func:`companion.core.stereo.to_grey`, against ``to_grey`` of the YUYV eyes (their Y plane).

    python tools/yuyv_decode_cost.py [--frames 200] [--threads 1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    import cv2

    from companion.core.stereo import split_side_by_side, to_grey

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200, help="timed frames per size and path")
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads")
    args = parser.parse_args()
    cv2.setNumThreads(args.threads)
    rng = np.random.default_rng(0)
    for w, h in ((672, 376), (1280, 720)):
        bgr = cv2.GaussianBlur(rng.integers(0, 256, (h, 2 * w, 3), dtype=np.uint8), (5, 5), 1)
        yuyv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_YUYV)
        grey_l, grey_r = np.empty((h, w), np.uint8), np.empty((h, w), np.uint8)

        def decoded(frame: np.ndarray = yuyv) -> None:
            left, right = split_side_by_side(cv2.cvtColor(frame, cv2.COLOR_YUV2BGR_YUYV))
            to_grey(left, out=grey_l)
            to_grey(right, out=grey_r)

        def luma(frame: np.ndarray = yuyv) -> None:
            left, right = split_side_by_side(frame)
            to_grey(left, out=grey_l)
            to_grey(right, out=grey_r)

        for name, step in (("decode to BGR, then grey", decoded), ("luma as it comes", luma)):
            times = []
            for i in range(30 + args.frames):
                t0 = time.perf_counter()
                step()
                if i >= 30:
                    times.append((time.perf_counter() - t0) * 1e3)
            print(f"{w}x{h} {name}: median {np.median(times):.2f} ms, p90 {np.percentile(times, 90):.2f} ms")


if __name__ == "__main__":
    main()
