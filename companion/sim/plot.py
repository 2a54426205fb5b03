"""Plots of a flight drawn with OpenCV only (no matplotlib: ``companion demo`` runs on the base install).

:func:`plot_flight` returns a BGR uint8 image: a **top view** (north to the right, east downwards, so
the map is the usual north-up map turned a quarter clockwise) with the obstacles' footprints, the
vehicle's swept width, the path coloured by what drove the setpoint (CLEAR green, AVOID amber, BRAKE
red, stale/none grey, HOLD purple), brake markers, start, goal and the end; optionally a **side
view** below it sharing the north axis: altitude along the path and the vertical extent of every
obstacle whose footprint came within the collision radius of the path, horizontally (what the vehicle
flew over, under or into).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from companion.sim.render import Box, Obstacle
from companion.sim.loop import FlightResult, LogKind
from companion.sim.scoring import Outcome

_FONT = cv2.FONT_HERSHEY_SIMPLEX
#: BGR colours.
KIND_COLOUR: dict[int, tuple[int, int, int]] = {
    LogKind.NONE: (150, 150, 150),
    LogKind.CLEAR: (60, 170, 60),
    LogKind.AVOID: (0, 165, 255),
    LogKind.BRAKE: (40, 40, 220),
    LogKind.STALE: (120, 120, 120),
    LogKind.HOLD: (170, 60, 170),
    LogKind.DETOUR: (200, 170, 0),
}
_OBSTACLE = (95, 95, 95)
_LOW = (70, 110, 150)  # entirely below the start altitude: brownish
_HIGH = (170, 120, 80)  # entirely above: bluish
_SWEPT = (235, 215, 200)


def footprint_ne_m(ob: Obstacle) -> np.ndarray:
    """The obstacle's footprint polygon, float64 ``(K, 2)`` (north, east) metres."""
    if isinstance(ob, Box):
        ax = ob.axes()
        hx, hy = 0.5 * ob.size_m[0], 0.5 * ob.size_m[1]
        c = np.asarray(ob.centre_ned_m[:2])
        corners = [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
        return np.array([c + a * ax[0, :2] + b * ax[1, :2] for a, b in corners])
    step = 2.0 * math.pi / ob.sides
    rc = ob.radius_m / math.cos(0.5 * step)
    ang = (np.arange(ob.sides) + 0.5) * step
    return np.stack([ob.centre_ned_m[0] + rc * np.cos(ang), ob.centre_ned_m[1] + rc * np.sin(ang)], axis=1)


def altitude_range_m(ob: Obstacle) -> tuple[float, float]:
    """(bottom, top) altitude of the obstacle, metres."""
    half = 0.5 * (ob.size_m[2] if isinstance(ob, Box) else ob.height_m)
    z = ob.centre_ned_m[2]
    return (-z - half, -z + half)


def _horizontal_distance_m(ob: Obstacle, ne: np.ndarray) -> np.ndarray:
    """Horizontal distance from (north, east) points ``(N, 2)`` to the obstacle's footprint."""
    z = np.full((ne.shape[0], 1), ob.centre_ned_m[2])
    return ob.signed_distance_m(np.hstack([ne, z]))


class _Axes:
    """Metres -> pixels for one panel: x = north; y = east (top view) or altitude (side view)."""

    def __init__(self, north: tuple[float, float], y: tuple[float, float], scale: float, origin: tuple[int, int], y_up: bool):
        self.n0, self.n1 = north
        self.y0, self.y1 = y
        self.s = scale
        self.ox, self.oy = origin
        self.y_up = y_up

    @property
    def size_px(self) -> tuple[int, int]:
        return int(round((self.n1 - self.n0) * self.s)), int(round((self.y1 - self.y0) * self.s))

    def px(self, north: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        n = np.asarray(north, dtype=np.float64)
        v = np.asarray(y, dtype=np.float64)
        x = self.ox + (n - self.n0) * self.s
        yy = self.oy + ((self.y1 - v) if self.y_up else (v - self.y0)) * self.s
        return np.stack([x, yy], axis=-1)

    def pt(self, north: float, y: float) -> tuple[int, int]:
        p = self.px(north, y)
        return int(round(float(p[0]))), int(round(float(p[1])))


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.5, colour=(30, 30, 30), thick: int = 1) -> None:
    cv2.putText(img, text, org, _FONT, scale, (255, 255, 255), thick + 3, cv2.LINE_AA)
    cv2.putText(img, text, org, _FONT, scale, colour, thick, cv2.LINE_AA)


def _grid(img: np.ndarray, ax: _Axes, y_label: str) -> None:
    w, h = ax.size_px
    cv2.rectangle(img, (ax.ox, ax.oy), (ax.ox + w, ax.oy + h), (120, 120, 120), 1)
    for n in range(math.ceil(ax.n0), math.floor(ax.n1) + 1):
        x = ax.pt(n, ax.y0)[0]
        major = n % 5 == 0
        cv2.line(img, (x, ax.oy), (x, ax.oy + h), (205, 205, 205) if major else (232, 232, 232), 1)
        if major:
            _text(img, f"{n}", (x - 6, ax.oy + h + 16), 0.45)
    for v in range(math.ceil(ax.y0), math.floor(ax.y1) + 1):
        y = ax.pt(ax.n0, v)[1]
        cv2.line(img, (ax.ox, y), (ax.ox + w, y), (232, 232, 232), 1)
        _text(img, f"{v:+d}" if y_label == "east" else f"{v}", (ax.ox - 34, y + 5), 0.42)
    _text(img, "north (m)", (ax.ox + w - 80, ax.oy + h + 32), 0.45)
    _text(img, f"{y_label} (m)", (4, ax.oy - 6), 0.45)


def _path_segments(img: np.ndarray, pts: np.ndarray, kinds: np.ndarray, thick: int) -> None:
    for i in range(len(pts) - 1):
        colour = KIND_COLOUR[int(kinds[i])]
        a = (int(round(pts[i, 0])), int(round(pts[i, 1])))
        b = (int(round(pts[i + 1, 0])), int(round(pts[i + 1, 1])))
        cv2.line(img, a, b, colour, thick, cv2.LINE_AA)


def _clip_to(img: np.ndarray, before: np.ndarray, ax: _Axes) -> None:
    """Keep what was drawn inside the panel of ``ax``; restore ``before`` outside it."""
    w, h = ax.size_px
    keep = img[ax.oy : ax.oy + h + 1, ax.ox : ax.ox + w + 1].copy()
    img[:] = before
    img[ax.oy : ax.oy + h + 1, ax.ox : ax.ox + w + 1] = keep


def _brake_starts(kinds: np.ndarray) -> np.ndarray:
    k = kinds.astype(np.int64)
    is_brake = k == LogKind.BRAKE
    return np.flatnonzero(is_brake & ~np.concatenate([[False], is_brake[:-1]]))


def plot_flight(result: FlightResult, side_view: bool = False, px_per_m: float | None = None) -> np.ndarray:
    """Draw ``result`` (top view, and a side view below it when ``side_view``).

    Args:
        result: a finished flight (with its log).
        side_view: add the altitude profile panel.
        px_per_m: scale; default: fit the course into about 1400 px of width.

    Returns:
        BGR uint8 image ``(H, W, 3)``.
    """
    log = result.log
    if log is None:
        raise ValueError("the flight has no log to plot")
    course = result.course
    pos = log.position_ned_m
    radius = result.collision_radius_m
    n0 = min(-1.5, float(pos[:, 0].min()) - 1.0)
    n1 = max(course.goal_north_m + 1.5, float(pos[:, 0].max()) + 1.0)
    east_lo = max(course.bounds_min_ned_m[1], min(-3.0, float(pos[:, 1].min()) - 2.0))
    east_hi = min(course.bounds_max_ned_m[1], max(3.0, float(pos[:, 1].max()) + 2.0))
    scale = px_per_m if px_per_m is not None else max(20.0, min(90.0, 1400.0 / (n1 - n0)))
    margin_l, margin_t, margin_b = 48, 92, 44
    top = _Axes((n0, n1), (east_lo, east_hi), scale, (margin_l, margin_t), y_up=False)
    tw, th = top.size_px
    height = margin_t + th + margin_b
    side = None
    if side_view:
        alt_hi = max(4.0, float(-pos[:, 2].max()) + 1.0)
        side = _Axes((n0, n1), (0.0, alt_hi), scale, (margin_l, height + 28), y_up=True)
        height += 28 + side.size_px[1] + margin_b
    width = margin_l + tw + 24
    img = np.full((height, max(width, 760), 3), 255, np.uint8)

    # -- top view (drawn over a copy, then clipped to the panel)
    _grid(img, top, "east")
    before = img.copy()
    start_alt = -course.start.position_ned_m[2]
    overlay = img.copy()
    for ob in course.scene.obstacles:
        bottom, top_alt = altitude_range_m(ob)
        colour = _LOW if top_alt < start_alt - radius else _HIGH if bottom > start_alt + radius else _OBSTACLE
        poly = top.px(*footprint_ne_m(ob).T)
        cv2.fillPoly(overlay, [np.round(poly).astype(np.int32)], colour, cv2.LINE_AA)
    cv2.addWeighted(overlay, 0.75, img, 0.25, 0.0, dst=img)
    path_px = top.px(pos[:, 0], pos[:, 1])
    swept = np.round(path_px).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(img, [swept], False, _SWEPT, max(1, int(round(2 * radius * scale))), cv2.LINE_AA)
    g0, g1 = course.goal_east_m
    gx = top.pt(course.goal_north_m, 0.0)[0]
    cv2.line(img, (gx, top.pt(0, max(g0, east_lo))[1]), (gx, top.pt(0, min(g1, east_hi))[1]), (60, 170, 60), 2)
    _text(img, "goal", (gx + 4, margin_t + 16), 0.5, (40, 130, 40))
    _path_segments(img, path_px, log.kind, 2)
    for i in _brake_starts(log.kind):
        x, y = (int(round(v)) for v in path_px[i])
        cv2.drawMarker(img, (x, y), KIND_COLOUR[LogKind.BRAKE], cv2.MARKER_TILTED_CROSS, 12, 2, cv2.LINE_AA)
    sx, sy = top.pt(course.start.position_ned_m[0], course.start.position_ned_m[1])
    cv2.circle(img, (sx, sy), 7, (200, 90, 30), -1, cv2.LINE_AA)
    yaw = course.start.yaw_rad
    cv2.arrowedLine(img, (sx, sy), (int(sx + 24 * math.cos(yaw)), int(sy + 24 * math.sin(yaw))), (200, 90, 30), 2, cv2.LINE_AA)
    ex, ey = (int(round(v)) for v in path_px[-1])
    if result.outcome is Outcome.COLLISION:
        cv2.drawMarker(img, (ex, ey), (0, 0, 230), cv2.MARKER_STAR, 22, 2, cv2.LINE_AA)
    elif result.outcome is Outcome.HELD:
        cv2.rectangle(img, (ex - 7, ey - 7), (ex + 7, ey + 7), (170, 60, 170), 2, cv2.LINE_AA)
    else:
        cv2.circle(img, (ex, ey), 6, (30, 30, 30), 2, cv2.LINE_AA)
    mx, my = top.pt(result.min_clearance_at_ned_m[0], result.min_clearance_at_ned_m[1])
    cv2.circle(img, (mx, my), max(3, int(round(radius * scale))), (0, 0, 200), 1, cv2.LINE_AA)
    _text(img, f"min {result.min_clearance_m:.2f} m", (mx + 8, my - 8), 0.45, (0, 0, 170))
    _clip_to(img, before, top)

    # -- header and legend
    verdict = "SUCCESS" if result.success else "FAIL"
    _text(img, f"{course.name}: {result.outcome.value} ({verdict})  min clearance {result.min_clearance_m:.2f} m  "
               f"path {result.path_length_m:.1f} m  time {result.time_s:.1f} s", (8, 22), 0.6, (20, 20, 20), 1)
    _text(img, course.description, (8, 44), 0.45, (60, 60, 60))
    x = 8
    for label, colour in (("clear", KIND_COLOUR[LogKind.CLEAR]), ("avoid", KIND_COLOUR[LogKind.AVOID]),
                          ("brake", KIND_COLOUR[LogKind.BRAKE]), ("stale/none", KIND_COLOUR[LogKind.NONE]),
                          ("hold", KIND_COLOUR[LogKind.HOLD]), ("detour", KIND_COLOUR[LogKind.DETOUR])):
        cv2.line(img, (x, 64), (x + 22, 64), colour, 3, cv2.LINE_AA)
        _text(img, label, (x + 26, 69), 0.45)
        x += 34 + 10 * len(label)
    cv2.line(img, (x, 64), (x + 22, 64), _SWEPT, 8)
    _text(img, "swept width", (x + 26, 69), 0.45)
    x += 140
    for label, colour in (("obstacle", _OBSTACLE), ("low", _LOW), ("overhead", _HIGH)):
        cv2.rectangle(img, (x, 58), (x + 14, 70), colour, -1)
        _text(img, label, (x + 18, 69), 0.45)
        x += 30 + 10 * len(label)

    # -- side view
    if side is not None:
        _grid(img, side, "altitude")
        before = img.copy()
        overlay = img.copy()
        for ob in course.scene.obstacles:
            # Only what the path passed over, under or close beside: walls alongside would hide it.
            near = _horizontal_distance_m(ob, pos[:, :2]) < radius
            if not near.any():
                continue
            fp = footprint_ne_m(ob)
            bottom, top_alt = altitude_range_m(ob)
            a = side.pt(float(fp[:, 0].min()), min(top_alt, side.y1))
            b = side.pt(float(fp[:, 0].max()), max(bottom, 0.0))
            cv2.rectangle(overlay, a, b, _OBSTACLE, -1)
        cv2.addWeighted(overlay, 0.6, img, 0.4, 0.0, dst=img)
        alt_px = side.px(pos[:, 0], -pos[:, 2])
        band = np.round(alt_px).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [band], False, _SWEPT, max(1, int(round(2 * radius * scale))), cv2.LINE_AA)
        _path_segments(img, alt_px, log.kind, 2)
        _clip_to(img, before, side)
        _text(img, "side view: obstacles the vehicle flew over, under or into", (side.ox + 6, side.oy + 18), 0.45)
    return img

