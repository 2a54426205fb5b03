"""The frame every camera source hands over: a uint8 side-by-side image of the configured eye size.

:func:`check_frame` holds a decoded image against that contract and names what is wrong with it; the
V4L2 and replay sources use it on every frame.
"""

from __future__ import annotations

import numpy as np

from companion.errors import CameraError


def check_frame(image: object, source: str, width_px: int, height_px: int, yuyv: bool = False) -> np.ndarray:
    """A frame as the pipeline needs it, or a CameraError naming what is wrong with it.

    ``yuyv``: the capture was asked for its bytes undecoded: a uint8 (H, 2W, 2) YUYV frame (one that
    comes flat, (1, H·2W·2), is reshaped), or BGR where the backend decoded it anyway."""
    if yuyv and isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 2 \
            and image.shape[0] == 1 and image.size == height_px * 2 * width_px * 2:
        image = image.reshape(height_px, 2 * width_px, 2)
    channels = (2, 3) if yuyv else (3,)
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in channels:
        shape = getattr(image, "shape", None)
        dtype = getattr(image, "dtype", type(image).__name__)
        expected = "(H, 2W, 2) YUYV or (H, 2W, 3) BGR" if yuyv else "(H, 2W, 3) BGR"
        raise CameraError(f"{source}: frame is {dtype} {shape}, expected uint8 {expected}")
    if image.shape[:2] != (height_px, 2 * width_px):
        raise CameraError(
            f"{source}: frame is {image.shape[1]}x{image.shape[0]}, expected side-by-side "
            f"{2 * width_px}x{height_px} (two {width_px}x{height_px} eyes)"
        )
    return image
