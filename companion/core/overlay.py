"""The paper's Fig. 10 view: the 9 regions with their depths and the command as an arrow.

Pure drawing over arrays (OpenCV primitives), used by ``companion process --overlay``, the demo and
the simulator. Text sits on a dark box sized by ``cv2.getTextSize`` at the thickness it is drawn
with, so it reads the same under every OpenCV (OpenCV 5's text advances with the stroke thickness, so
a thicker "shadow" string came out wider than the text it was behind). An optional legend panel below
the image says what the colours, the marks, the arrow and the disparity inset mean.
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
_NEAR = (40, 40, 230)
_MID = (0, 160, 230)  # amber: between near and far
_FAR = (80, 200, 80)
_BOX = (20, 20, 20)
_TEXT = (235, 235, 235)


def _depth_colour(depth_m: float, near_m: float, far_m: float) -> tuple[int, int, int]:
    """Red when near (or unknown), green when far, amber between (BGR): the legend's three swatches and
    the view's bars, exactly (a gradient matched no swatch)."""
    if not np.isfinite(depth_m) or depth_m <= near_m:
        return _NEAR
    if depth_m >= far_m:
        return _FAR
    return _MID


def _text_size(text: str, font_scale: float, thick: int) -> tuple[int, int, int]:
    (tw, th), base = cv2.getTextSize(text, _FONT, font_scale, thick)
    return tw, th, base


def _label(
    out: np.ndarray, text: str, org: tuple[int, int], font_scale: float, colour: tuple[int, int, int], thick: int,
    pad: int = 2, alpha: float = 0.65,
) -> int:
    """Draw ``text`` with its baseline at ``org`` on a dark translucent box as wide as the text is
    drawn; returns the box's right edge (x), pixels."""
    tw, th, base = _text_size(text, font_scale, thick)
    x0, y0 = max(0, org[0] - pad), max(0, org[1] - th - pad)
    x1, y1 = min(out.shape[1], org[0] + tw + pad), min(out.shape[0], org[1] + base + pad)
    if x1 > x0 and y1 > y0:
        roi = out[y0:y1, x0:x1]
        np.copyto(roi, (roi * (1.0 - alpha) + np.asarray(_BOX, np.float64) * alpha).astype(np.uint8))
    cv2.putText(out, text, org, _FONT, font_scale, colour, thick, cv2.LINE_AA)
    return x1


def _sign(v: float) -> str:
    """``+0.42``; never ``-0.00``."""
    r = round(v, 2)
    return f"{0.0 if r == 0 else r:+.2f}"


def draw_overlay(
    image: np.ndarray,
    layout: RegionLayout,
    depth_m: np.ndarray,
    decision: Decision,
    near_m: float = 0.75,
    far_m: float = 2.25,
    disparity: np.ndarray | None = None,
    max_disparity_px: float = 64.0,
    *,
    filtered: np.ndarray | None = None,
    legend: bool = False,
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
        filtered: optional bool (9,): regions whose depth is the release filter's output, no frame's
            measurement (health's ``regions_filtered``), drawn with a leading "~".
        legend: add a panel below the image that explains the colours, marks, arrow and inset.

    Returns:
        A new BGR uint8 image: (H, W, 3), or (H + panel, W, 3) with the legend.
    """
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    h, w = out.shape[:2]
    scale = max(0.35, min(w, h) / 700.0)
    thick = max(1, int(round(scale * 2)))
    font = 0.6 * scale * 1.4
    if disparity is not None:
        inset_w = w // 4
        inset_h = max(1, int(round(disparity.shape[0] * inset_w / disparity.shape[1])))
        d = np.nan_to_num(disparity, nan=0.0)
        d8 = np.clip(d * (255.0 / max_disparity_px), 0, 255).astype(np.uint8)
        colour = cv2.applyColorMap(cv2.resize(d8, (inset_w, inset_h), interpolation=cv2.INTER_NEAREST), cv2.COLORMAP_TURBO)
        invalid = cv2.resize(np.isnan(disparity).astype(np.uint8), (inset_w, inset_h), interpolation=cv2.INTER_NEAREST)
        colour[invalid.astype(bool)] = 0
        out[h - inset_h : h, w - inset_w : w] = colour
        cv2.rectangle(out, (w - inset_w, h - inset_h), (w - 1, h - 1), (255, 255, 255), 1)
    for x in layout.col_edges[1:-1]:
        cv2.line(out, (int(x), 0), (int(x), h - 1), (255, 255, 255), 1, cv2.LINE_AA)
    for y in layout.row_edges[1:-1]:
        cv2.line(out, (0, int(y)), (w - 1, int(y)), (255, 255, 255), 1, cv2.LINE_AA)
    _, text_h, _ = _text_size("0", font, thick)
    for i, _name in enumerate(REGION_NAMES):
        rows, cols = layout.region_slices(i)
        value = float(depth_m[i])
        label = "?" if np.isnan(value) else f"{value:.2f}m"
        if filtered is not None and bool(filtered[i]) and not np.isnan(value):
            label = "~" + label
        org = (cols.start + 4, rows.start + text_h + 5)
        _label(out, label, org, font, _depth_colour(value, near_m, far_m), thick)
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
    caption = f"{decision.kind.value.upper()}  yaw {_sign(decision.yaw)}  pitch {_sign(decision.pitch)}"
    _label(out, caption, (6, h - 8), font, colour, thick)
    if legend:
        out = np.concatenate([out, _legend_panel(w, font, thick, near_m, far_m, disparity is not None)], axis=0)
    return out


def _legend_panel(
    width: int, font: float, thick: int, near_m: float, far_m: float, with_inset: bool
) -> np.ndarray:
    """A dark panel ``width`` wide explaining the overlay, items wrapped onto as many lines as needed."""
    items: list[tuple[tuple[int, int, int] | None, str]] = [
        (_NEAR, f"near (< {near_m:g} m) or unknown '?'"),
        (_MID, "between"),
        (_FAR, f"far (> {far_m:g} m)"),
        (None, "'~' filtered, not measured"),
        (None, "arrow: the command (right: yaw right, up: climb), by decision:"),
        (_DECISION_COLOUR[DecisionKind.CLEAR], "clear"),
        (_DECISION_COLOUR[DecisionKind.AVOID], "avoid"),
        (_DECISION_COLOUR[DecisionKind.BRAKE], "brake (a circle: hold)"),
    ]
    if with_inset:
        items.append((None, "inset: disparity (blue far .. red near, black no match)"))
    _, th, base = _text_size("Ag", font, thick)
    line_h = th + base + 8
    box = th
    gap = 12
    # Lay out left to right, wrapping; then draw.
    lines: list[list[tuple[tuple[int, int, int] | None, str, int]]] = [[]]
    x = 6
    for colour, text in items:
        tw, _, _ = _text_size(text, font, thick)
        item_w = (box + 4 if colour is not None else 0) + tw
        if lines[-1] and x + item_w > width - 6:
            lines.append([])
            x = 6
        lines[-1].append((colour, text, x))
        x += item_w + gap
    panel = np.full((len(lines) * line_h + 6, width, 3), _BOX, np.uint8)
    for row, line in enumerate(lines):
        y = 4 + row * line_h + th + 2
        for colour, text, x0 in line:
            x = x0
            if colour is not None:
                cv2.rectangle(panel, (x, y - th), (x + box, y), colour, -1)
                x += box + 4
            cv2.putText(panel, text, (x, y), _FONT, font, _TEXT, thick, cv2.LINE_AA)
    return panel
