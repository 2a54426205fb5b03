"""The paper's Fig. 10 view: the 9 regions with their depths and the command as an arrow.

Pure drawing over arrays (OpenCV primitives), used by ``companion process --overlay``, the demo and
the simulator.
"""

from __future__ import annotations

import cv2
import numpy as np

from companion.core.regions import RegionLayout
from companion.core.types import REGION_NAMES, Decision, DecisionKind

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_DECISION_COLOUR = {  # BGR
    DecisionKind.CLEAR: (80, 200, 80),
    DecisionKind.AVOID: (0, 200, 255),
    DecisionKind.BRAKE: (40, 40, 230),
}


def _depth_colour(depth_m: float, near_m: float, far_m: float) -> tuple[int, int, int]:
    """Red when near (or unknown), green when far, amber between (BGR)."""
    if not np.isfinite(depth_m) or depth_m <= near_m:
        return (40, 40, 230)
    if depth_m >= far_m:
        return (80, 200, 80)
    t = (depth_m - near_m) / (far_m - near_m)
    return (int(40 + 40 * t), int(40 + 160 * t), int(230 - 150 * t))


def draw_overlay(
    image: np.ndarray,
    layout: RegionLayout,
    depth_m: np.ndarray,
    decision: Decision,
    near_m: float = 0.75,
    far_m: float = 2.25,
    disparity: np.ndarray | None = None,
    max_disparity_px: float = 64.0,
) -> np.ndarray:
    """Draw the region grid, each region's depth and the command arrow.

    Args:
        image: the left eye, uint8 (H, W) grey or (H, W, 3) BGR. Not modified.
        layout: the region layout for this image size.
        depth_m: float (9,) region depths in metres, NaN = unknown (drawn as "?" in red).
        decision: the controller's decision; the arrow points (yaw, pitch) from the image centre.
        near_m, far_m: colour thresholds for the depth labels.
        disparity: optional float32 (H, W) disparity (NaN invalid) drawn as a small inset.
        max_disparity_px: disparity mapped to the top of the inset's colour scale.

    Returns:
        A new BGR uint8 image (H, W, 3).
    """
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    h, w = out.shape[:2]
    scale = max(0.35, min(w, h) / 700.0)
    thick = max(1, int(round(scale * 2)))
    if disparity is not None:
        inset_w = w // 4
        inset_h = max(1, int(round(disparity.shape[0] * inset_w / disparity.shape[1])))
        d = np.nan_to_num(disparity, nan=0.0)
        d8 = np.clip(d * (255.0 / max_disparity_px), 0, 255).astype(np.uint8)
        colour = cv2.applyColorMap(cv2.resize(d8, (inset_w, inset_h), interpolation=cv2.INTER_NEAREST), cv2.COLORMAP_TURBO)
        invalid = cv2.resize(np.isnan(disparity).astype(np.uint8), (inset_w, inset_h), interpolation=cv2.INTER_NEAREST)
        colour[invalid.astype(bool)] = 0
        out[h - inset_h : h, w - inset_w : w] = colour
    for x in layout.col_edges[1:-1]:
        cv2.line(out, (int(x), 0), (int(x), h - 1), (255, 255, 255), 1, cv2.LINE_AA)
    for y in layout.row_edges[1:-1]:
        cv2.line(out, (0, int(y)), (w - 1, int(y)), (255, 255, 255), 1, cv2.LINE_AA)
    for i, name in enumerate(REGION_NAMES):
        rows, cols = layout.region_slices(i)
        value = float(depth_m[i])
        label = "?" if np.isnan(value) else f"{value:.2f}m"
        org = (cols.start + 4, rows.start + int(22 * scale) + 2)
        cv2.putText(out, label, org, _FONT, 0.6 * scale * 1.4, (0, 0, 0), thick + 2, cv2.LINE_AA)
        cv2.putText(out, label, org, _FONT, 0.6 * scale * 1.4, _depth_colour(value, near_m, far_m), thick, cv2.LINE_AA)
    colour = _DECISION_COLOUR[decision.kind]
    cx, cy = w // 2, h // 2
    arrow_len = 0.4 * min(w, h)
    tip = (int(round(cx + decision.yaw * arrow_len)), int(round(cy - decision.pitch * arrow_len)))
    if decision.kind is DecisionKind.BRAKE:
        cv2.circle(out, (cx, cy), int(0.08 * min(w, h)), colour, thick + 2, cv2.LINE_AA)
        cv2.line(out, (cx - int(0.05 * min(w, h)), cy), (cx + int(0.05 * min(w, h)), cy), colour, thick + 2, cv2.LINE_AA)
    elif tip == (cx, cy):
        cv2.circle(out, (cx, cy), max(3, thick * 2), colour, -1, cv2.LINE_AA)
    else:
        cv2.arrowedLine(out, (cx, cy), tip, colour, thick + 2, cv2.LINE_AA, tipLength=0.25)
    caption = f"{decision.kind.value.upper()} yaw {decision.yaw:+.2f} pitch {decision.pitch:+.2f}"
    org = (6, h - 8)
    cv2.putText(out, caption, org, _FONT, 0.6 * scale * 1.4, (0, 0, 0), thick + 2, cv2.LINE_AA)
    cv2.putText(out, caption, org, _FONT, 0.6 * scale * 1.4, colour, thick, cv2.LINE_AA)
    return out
