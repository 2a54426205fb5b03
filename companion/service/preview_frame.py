"""The preview image and the preview message on the wire.

The image is the paper's Fig. 10 view at the preview's size: the left eye with the 9 regions, their
depths (coloured near/far) and the command arrow (:func:`companion.core.overlay.draw_overlay`), plus the
disparity map as an inset in the lower right corner with a colour legend in metres, and the frame's
time in the upper right corner. Pure drawing over arrays: it runs in the service's preview thread (or
the simulator's), never in the flight path.

A preview message is three ZeroMQ frames: ``[b"preview", header, jpeg]``. The header is one JSON
object (``type`` "preview", ``seq``, ``frame_seq``, ``time_s`` the frame's capture time on the
service's monotonic clock, ``unix_time_s``, ``width_px``, ``height_px``, ``encode_ms``,
``near_m``/``far_m`` (the controller's near and far thresholds), ``decision`` (the frame's kind),
``subscribed_s``); the jpeg is a baseline JPEG.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.core.overlay import draw_overlay
from companion.core.regions import RegionLayout
from companion.core.stereo import split_side_by_side, to_bgr
from companion.core.types import Decision
from companion.errors import ProtocolError
from companion.service.protocol import encode

#: The ZeroMQ topic (first frame) of preview messages.
PREVIEW_TOPIC = b"preview"

_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class PreviewInputs:
    """What one preview image is drawn from (references, nothing copied).

    Attributes:
        image: the side-by-side frame, uint8 ``(H, 2W, 3)`` BGR or ``(H, 2W)`` grey (left eye first).
        timestamp_s: the frame's capture time, seconds (the service's monotonic clock).
        seq: the frame's sequence number.
        depth_m: float ``(9,)`` refined region depths, metres, NaN = unknown.
        decision: the controller's decision for the frame.
        disparity: float32 ``(h, w)`` disparity, pixels, NaN invalid (any size: a GPU backend gives a
            downsampled one), or None.
        layout: the region layout at the eye's size.
        focal_baseline_px_m: f·B of the rig, pixel·metres (depth = f·B / disparity).
        near_m, far_m: the controller's near and far thresholds, metres (label colours, legend).
        max_disparity_px: the disparity at the top of the inset's colour scale, pixels.
    """

    image: np.ndarray
    timestamp_s: float
    seq: int
    depth_m: np.ndarray
    decision: Decision
    disparity: np.ndarray | None
    layout: RegionLayout
    focal_baseline_px_m: float
    near_m: float
    far_m: float
    max_disparity_px: float


def thresholds_m(cfg: Any) -> dict[str, float]:
    """Health's ``thresholds_m``: the controller's near and far thresholds of ``cfg`` (metres), which
    the view draws its region bars against."""
    near_m, far_m = near_far_m(cfg)
    return {"near_m": near_m, "far_m": far_m}


def near_far_m(cfg: Any) -> tuple[float, float]:
    """The controller's thresholds: where 'near' stops being total and where 'far' becomes total, metres."""
    near = cfg.controller.input_terms.get("near")
    far = cfg.controller.input_terms.get("far")
    near_m = near.params_m[0] if near is not None else 0.75
    far_m = far.params_m[-1] if far is not None else 2.25
    return float(near_m), float(far_m)


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, colour: tuple[int, int, int]) -> None:
    """``text`` once, on a darkened box (an outline drawn with a thicker stroke does not line up with
    the text at every OpenCV version and size)."""
    (tw, th), base = cv2.getTextSize(text, _FONT, scale, 1)
    x, y = org
    y0, y1 = max(0, y - th - 3), min(img.shape[0], y + base)
    x0, x1 = max(0, x - 3), min(img.shape[1], x + tw + 3)
    if y1 > y0 and x1 > x0:
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] * 0.35).astype(np.uint8)
    cv2.putText(img, text, org, _FONT, scale, colour, 1, cv2.LINE_AA)


def _disparity_inset(out: np.ndarray, inp: PreviewInputs) -> None:
    """The disparity map (turbo: red near, blue far, black invalid) in the lower right quarter, with a
    legend bar above it labelled in metres."""
    disparity = inp.disparity
    assert disparity is not None
    h, w = out.shape[:2]
    inset_w = max(16, w // 4)
    inset_h = max(8, int(round(disparity.shape[0] * inset_w / disparity.shape[1])))
    small = cv2.resize(disparity, (inset_w, inset_h), interpolation=cv2.INTER_NEAREST)  # NaN stays NaN
    invalid = np.isnan(small)
    d8 = np.clip(np.nan_to_num(small, nan=0.0) * (255.0 / inp.max_disparity_px), 0, 255).astype(np.uint8)
    colour = cv2.applyColorMap(d8, cv2.COLORMAP_TURBO)
    colour[invalid] = 0
    x0, y0 = w - inset_w, h - inset_h
    out[y0:h, x0:w] = colour
    cv2.rectangle(out, (x0, y0), (w - 1, h - 1), (255, 255, 255), 1)
    # Legend: the same colour scale, far (left) to near (right), with the depths at both ends.
    bar_h = max(5, h // 60)
    scale = max(0.4, w / 1400.0)
    label_h = int(22 * scale) + 6
    by0 = y0 - bar_h - label_h
    if by0 < 0:
        return
    ramp = np.linspace(0, 255, inset_w).astype(np.uint8)[None, :].repeat(bar_h, axis=0)
    out[by0 + label_h : by0 + label_h + bar_h, x0:w] = cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO)
    fb = inp.focal_baseline_px_m
    near_text = f"{fb / inp.max_disparity_px:.1f}m" if inp.max_disparity_px > 0 else "near"
    far_d = inp.max_disparity_px / 8.0
    far_text = f"{fb / far_d:.0f}m+" if far_d > 0 else "far"
    _text(out, f"depth {far_text}", (x0 + 2, by0 + label_h - 4), scale, (255, 255, 255))
    (tw, _), _ = cv2.getTextSize(near_text, _FONT, scale, 1)
    _text(out, near_text, (w - tw - 4, by0 + label_h - 4), scale, (255, 255, 255))


def _scaled_edges(edges: np.ndarray, k: float, size_px: int) -> np.ndarray:
    """Region edges scaled by ``k``, kept strictly increasing and ending at ``size_px``."""
    out = np.round(edges * k).astype(np.int64)
    out[-1] = size_px
    for i in range(1, 4):
        out[i] = max(out[i], out[i - 1] + 1)
    return out


def render_preview(inp: PreviewInputs, width_px: int) -> np.ndarray:
    """The preview image: the Fig. 10 overlay at ``width_px`` wide, the disparity inset with its legend
    and the frame's time.

    Returns:
        BGR uint8 ``(round(H * width_px / W), width_px, 3)`` for an eye of ``W`` x ``H``.
    """
    left, _ = split_side_by_side(inp.image)
    left = to_bgr(left)  # a YUYV camera's eye decoded here, off the hot path
    eye_h, eye_w = left.shape[:2]
    k = width_px / eye_w
    height_px = max(1, int(round(eye_h * k)))
    # INTER_AREA only where it matters (a large shrink): it is several times slower than linear.
    small = cv2.resize(left, (width_px, height_px), interpolation=cv2.INTER_AREA if k < 0.75 else cv2.INTER_LINEAR)
    layout = inp.layout
    if k != 1.0:
        layout = RegionLayout(
            _scaled_edges(layout.row_edges, height_px / eye_h, height_px),
            _scaled_edges(layout.col_edges, k, width_px),
        )
    out = draw_overlay(small, layout, np.asarray(inp.depth_m, np.float64), inp.decision, near_m=inp.near_m, far_m=inp.far_m)
    if inp.disparity is not None and inp.disparity.size:
        _disparity_inset(out, inp)
    scale = max(0.4, width_px / 1400.0)
    stamp = f"#{inp.seq}  t {inp.timestamp_s:.2f}s"
    (tw, _), _ = cv2.getTextSize(stamp, _FONT, scale, 1)
    _text(out, stamp, (width_px - tw - 6, int(22 * scale) + 4), scale, (255, 255, 255))
    return out


def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """``image`` (BGR uint8) as baseline JPEG bytes at ``quality`` (10-95).

    Raises:
        ValueError: OpenCV could not encode it.
    """
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("OpenCV could not encode the preview as JPEG")
    return buf.tobytes()


def pack(header: dict[str, Any], jpeg: bytes) -> list[bytes]:
    """A preview message's ZeroMQ frames."""
    return [PREVIEW_TOPIC, encode(header), jpeg]


def unpack(frames: list[bytes]) -> tuple[dict[str, Any], bytes]:
    """(header, jpeg) of a preview message.

    Raises:
        ProtocolError: not three frames, not the preview topic, a header that is not a JSON object, or
            a body that is not a JPEG.
    """
    if len(frames) != 3 or frames[0] != PREVIEW_TOPIC:
        raise ProtocolError(f"preview: expected [b'preview', header, jpeg], got {len(frames)} frames")
    try:
        header = json.loads(frames[1])
    except ValueError as err:
        raise ProtocolError(f"preview: header is not JSON: {err}") from None
    if not isinstance(header, dict):
        raise ProtocolError("preview: header is not a JSON object")
    if not frames[2].startswith(b"\xff\xd8"):
        raise ProtocolError("preview: body is not a JPEG")
    return header, frames[2]


def finite_or_none(x: float | None) -> float | None:
    """``x`` when it is a finite number, else None (JSON has no NaN)."""
    return x if x is not None and math.isfinite(x) else None
