"""A small SVG plotter for ``companion review``: time series, bands, a top-down path. No dependency.

A :class:`Plot` maps data coordinates to an SVG viewport with margins for its axes; every method
appends elements, and :meth:`Plot.svg` returns the ``<svg>`` text (scales with the page's width).
``None`` in a series breaks its line.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from html import escape

#: Colours shared by the review's plots (decision kinds, states).
KIND_COLOUR = {"clear": "#2e9e44", "avoid": "#e89a00", "brake": "#d93025"}
STATE_COLOUR = {
    "engaged": "#2e9e44", "override": "#57b86a", "engaging": "#e8c100", "paused": "#e89a00",
    "degraded": "#d93025", "failsafe": "#8b0000", "passive": "#9aa3ad", "disengaged": "#5a6675",
    "replay": "#1f5fd1",
}


def nice_ticks(lo: float, hi: float, target: int = 6) -> list[float]:
    """Round tick values (1, 2, 5 × 10^k apart) covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / max(1, target)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    out = []
    v = first
    while v <= hi + 1e-9 * step:
        out.append(round(v, 10))
        v += step
    return out


def _fmt(v: float) -> str:
    return f"{v:g}" if abs(v) >= 1e-9 else "0"


class Plot:
    """One panel.

    Args:
        width, height: the viewport, SVG units (pixels at 100 %).
        x_range, y_range: data ranges shown.
        title: drawn above the panel; ``x_label``/``y_label`` beside the axes.
        equal_aspect: one data unit the same length on both axes (a map); the ranges grow to fit.
    """

    def __init__(
        self,
        width: int,
        height: int,
        x_range: tuple[float, float],
        y_range: tuple[float, float],
        *,
        title: str = "",
        x_label: str = "",
        y_label: str = "",
        equal_aspect: bool = False,
        margin: tuple[int, int, int, int] = (26, 14, 34, 52),  # top, right, bottom, left
    ) -> None:
        self.width, self.height = width, height
        self.top, self.right, self.bottom, self.left = margin
        x0, x1 = x_range
        y0, y1 = y_range
        if x1 <= x0:
            x0, x1 = x0 - 1.0, x0 + 1.0
        if y1 <= y0:
            y0, y1 = y0 - 1.0, y0 + 1.0
        pw, ph = self.plot_w, self.plot_h
        if equal_aspect:
            scale = max((x1 - x0) / pw, (y1 - y0) / ph)
            cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
            x0, x1 = cx - scale * pw / 2, cx + scale * pw / 2
            y0, y1 = cy - scale * ph / 2, cy + scale * ph / 2
        self.x0, self.x1, self.y0, self.y1 = x0, x1, y0, y1
        self.parts: list[str] = []
        self.legend_items: list[tuple[str, str, str]] = []
        self._axes(title, x_label, y_label)

    @property
    def plot_w(self) -> float:
        return self.width - self.left - self.right

    @property
    def plot_h(self) -> float:
        return self.height - self.top - self.bottom

    def X(self, x: float) -> float:
        return self.left + (x - self.x0) / (self.x1 - self.x0) * self.plot_w

    def Y(self, y: float) -> float:
        return self.top + (self.y1 - y) / (self.y1 - self.y0) * self.plot_h

    def _axes(self, title: str, x_label: str, y_label: str) -> None:
        p = self.parts
        p.append(f'<rect x="{self.left}" y="{self.top}" width="{self.plot_w:.1f}" height="{self.plot_h:.1f}" fill="#fff" stroke="#c9ced6"/>')
        for v in nice_ticks(self.x0, self.x1, 8):
            x = self.X(v)
            p.append(f'<line x1="{x:.1f}" y1="{self.top}" x2="{x:.1f}" y2="{self.top + self.plot_h:.1f}" stroke="#eceff3"/>')
            p.append(f'<text x="{x:.1f}" y="{self.height - self.bottom + 14}" text-anchor="middle" class="tick">{_fmt(v)}</text>')
        for v in nice_ticks(self.y0, self.y1, 5):
            y = self.Y(v)
            p.append(f'<line x1="{self.left}" y1="{y:.1f}" x2="{self.left + self.plot_w:.1f}" y2="{y:.1f}" stroke="#eceff3"/>')
            p.append(f'<text x="{self.left - 5}" y="{y + 4:.1f}" text-anchor="end" class="tick">{_fmt(v)}</text>')
        if title:
            p.append(f'<text x="{self.left}" y="{self.top - 9}" class="ptitle">{escape(title)}</text>')
        if x_label:
            p.append(f'<text x="{self.left + self.plot_w / 2:.1f}" y="{self.height - 4}" text-anchor="middle" class="label">{escape(x_label)}</text>')
        if y_label:
            cy = self.top + self.plot_h / 2
            p.append(f'<text x="12" y="{cy:.1f}" transform="rotate(-90 12 {cy:.1f})" text-anchor="middle" class="label">{escape(y_label)}</text>')

    def line(
        self, xs: Sequence[float | None], ys: Sequence[float | None], colour: str, *, width: float = 1.5,
        dash: str | None = None, label: str | None = None, clip: bool = True,
    ) -> None:
        """A polyline; a None (or NaN) breaks it; values are clipped to the panel."""
        segments: list[list[str]] = [[]]
        for x, y in zip(xs, ys):
            if x is None or y is None or not math.isfinite(x) or not math.isfinite(y):
                if segments[-1]:
                    segments.append([])
                continue
            if clip:
                y = min(max(y, self.y0), self.y1)
            segments[-1].append(f"{self.X(x):.1f},{self.Y(y):.1f}")
        style = f' stroke-dasharray="{dash}"' if dash else ""
        for seg in segments:
            if len(seg) == 1:
                seg.append(seg[0])
            if seg:
                self.parts.append(f'<polyline points="{" ".join(seg)}" fill="none" stroke="{colour}" stroke-width="{width}"{style}/>')
        if label:
            self.legend_items.append((label, colour, dash or ""))

    def hline(self, y: float, colour: str, label: str = "", dash: str = "5 3") -> None:
        if not self.y0 <= y <= self.y1:
            return
        yy = self.Y(y)
        self.parts.append(f'<line x1="{self.left}" y1="{yy:.1f}" x2="{self.left + self.plot_w:.1f}" y2="{yy:.1f}" stroke="{colour}" stroke-dasharray="{dash}"/>')
        if label:
            self.parts.append(f'<text x="{self.left + self.plot_w - 4:.1f}" y="{yy - 3:.1f}" text-anchor="end" class="tick" fill="{colour}">{escape(label)}</text>')

    def band(self, xs: Sequence[float], values: Sequence[str | None], colours: dict[str, str], y_lo: float, y_hi: float,
             opacity: float = 1.0) -> None:
        """Coloured spans: ``values[i]`` from ``xs[i]`` to ``xs[i + 1]``, between data heights ``y_lo`` and ``y_hi``."""
        top, bottom = self.Y(y_hi), self.Y(y_lo)
        i = 0
        n = len(xs)
        while i < n:
            j = i
            while j + 1 < n and values[j + 1] == values[i]:
                j += 1
            colour = colours.get(values[i] or "")
            x_end = xs[j + 1] if j + 1 < n else xs[j]
            if colour is not None:
                a, b = self.X(max(xs[i], self.x0)), self.X(min(x_end, self.x1))
                if b > a:
                    self.parts.append(
                        f'<rect x="{a:.1f}" y="{top:.1f}" width="{max(0.6, b - a):.1f}" height="{bottom - top:.1f}" fill="{colour}" opacity="{opacity}"/>'
                    )
            i = j + 1

    def marker(self, x: float, y: float, colour: str, title: str = "", r: float = 4.0, shape: str = "circle") -> None:
        tip = f"<title>{escape(title)}</title>" if title else ""
        if shape == "square":
            self.parts.append(f'<rect x="{self.X(x) - r:.1f}" y="{self.Y(y) - r:.1f}" width="{2 * r}" height="{2 * r}" fill="{colour}">{tip}</rect>')
        else:
            self.parts.append(f'<circle cx="{self.X(x):.1f}" cy="{self.Y(y):.1f}" r="{r}" fill="{colour}" stroke="#fff">{tip}</circle>')

    def text(self, x: float, y: float, text: str, colour: str = "#15181d") -> None:
        self.parts.append(f'<text x="{self.X(x) + 5:.1f}" y="{self.Y(y) - 5:.1f}" class="tick" fill="{colour}">{escape(text)}</text>')

    def svg(self) -> str:
        # The legend sits in the title's row, right-aligned, outside the data.
        legend = []
        x = self.left + self.plot_w - sum(28 + 6.0 * len(label) for label, _, _ in self.legend_items)
        y = self.top - 9
        for label, colour, dash in self.legend_items:
            style = f' stroke-dasharray="{dash}"' if dash else ""
            legend.append(f'<line x1="{x:.1f}" y1="{y - 4}" x2="{x + 16:.1f}" y2="{y - 4}" stroke="{colour}" stroke-width="2.5"{style}/>')
            legend.append(f'<text x="{x + 20:.1f}" y="{y}" class="tick">{escape(label)}</text>')
            x += 28 + 6.0 * len(label)
        return (
            f'<svg viewBox="0 0 {self.width} {self.height}" width="100%" role="img" xmlns="http://www.w3.org/2000/svg">'
            + "".join(self.parts) + "".join(legend) + "</svg>"
        )
