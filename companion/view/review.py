"""``companion review RUN``: one self-contained HTML report of a recorded flight.

Input (``RUN``): a folder with ``health.jsonl`` (a flight of ``companion sitl --workdir``, or a run the
service recorded under ``view.record_dir``, which adds ``preview/`` frames and ``config.toml``), a folder
of such folders (a sitl suite's workdir, or ``record_dir`` itself), or a ``health.jsonl`` file. The
controller's near/far thresholds come from the run's ``config.toml`` or ``companion.toml`` (the
defaults otherwise).

Output: one HTML file (inline SVG plots and, where recorded, JPEG frames; nothing loaded from
anywhere else) per review: a summary of each flight (states, decisions, latency, dropped frames,
errors), its decisions and region depths over time, the setpoints against the vehicle's velocity (in
the body frame, from the reported attitude), frame age and latency, the path from above when the
position is known, and a contact sheet of the moments the decision turned to brake or avoid (the
nearest recorded preview frame, or the 9 region depths drawn from the health message).
Needs nothing beyond ``pip install .``.
"""

from __future__ import annotations

import base64
import json
import logging
import math
from dataclasses import dataclass, field
from html import escape
from pathlib import Path
from typing import Any

from companion.config import load_config
from companion.core.types import REGION_NAMES
from companion.errors import ConfigError, InputError
from companion.service.preview_frame import near_far_m
from companion.view.svg import KIND_COLOUR, STATE_COLOUR, Plot

log = logging.getLogger(__name__)

_WIDTH = 960


@dataclass
class Run:
    """One recorded flight.

    Attributes:
        name: shown as its title (the folder's name).
        folder: where it was read from.
        health: the health messages, in order.
        previews: (time_s on the service's clock, JPEG file) of the recorded preview frames, in order.
        near_m, far_m: the controller's thresholds, metres.
        thresholds_from: where they came from (a file, or "defaults").
    """

    name: str
    folder: Path
    health: list[dict[str, Any]]
    previews: list[tuple[float, Path]] = field(default_factory=list)
    near_m: float = 0.75
    far_m: float = 2.25
    thresholds_from: str = "defaults"


def _read_health(path: Path) -> list[dict[str, Any]]:
    out = []
    try:
        with path.open(encoding="utf-8") as f:
            for n, line in enumerate(f, start=1):
                line = line.strip()
                if not line:
                    continue
                try:
                    h = json.loads(line)
                except ValueError:
                    log.warning("%s:%d: not JSON, skipped", path, n)  # a line cut by a full disk or a kill
                    continue
                if isinstance(h, dict) and h.get("type", "health") == "health" and isinstance(h.get("time_s"), (int, float)):
                    out.append(h)
    except OSError as err:
        raise InputError(f"{path}: cannot read it: {err.strerror or err}") from None
    return out


def _read_previews(folder: Path) -> list[tuple[float, Path]]:
    index = folder / "preview" / "index.jsonl"
    out = []
    if index.is_file():
        for line in index.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                item = json.loads(line)
                path = folder / "preview" / str(item["file"])
                if path.is_file():
                    out.append((float(item["time_s"]), path))
            except (ValueError, KeyError, TypeError):
                continue
    return sorted(out)


def _thresholds(folder: Path) -> tuple[float, float, str]:
    for name in ("config.toml", "companion.toml"):
        path = folder / name
        if path.is_file():
            try:
                near, far = near_far_m(load_config(path))
                return near, far, name
            except ConfigError as err:
                log.warning("%s: %s; using the default thresholds", path, err)
    return 0.75, 2.25, "defaults"


def load_runs(path: Path) -> list[Run]:
    """The flights under ``path`` (see the module doc).

    Raises:
        InputError: no health stream there, or one without a message.
    """
    path = path.expanduser()
    if path.is_file():
        folders = [(path.parent, path)]
    elif (path / "health.jsonl").is_file():
        folders = [(path, path / "health.jsonl")]
    elif path.is_dir():
        folders = sorted((p.parent, p) for p in path.glob("*/health.jsonl"))
    else:
        raise InputError(f"{path}: no such file or folder")
    if not folders:
        raise InputError(f"{path}: no health.jsonl here or in its folders (a `companion sitl --workdir` or view.record_dir run)")
    runs = []
    for folder, health_path in folders:
        health = _read_health(health_path)
        if not health:
            log.warning("%s: no health message; skipped", health_path)
            continue
        near, far, source = _thresholds(folder)
        runs.append(Run(folder.name, folder, health, _read_previews(folder), near, far, source))
    if not runs:
        raise InputError(f"{path}: its health.jsonl files hold no health message")
    return runs


# ---------------------------------------------------------------------------------------------- helpers


def _num(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else None


def _get(h: dict[str, Any], *keys: str) -> Any:
    for k in keys:
        if not isinstance(h, dict):
            return None
        h = h.get(k)  # type: ignore[assignment]
    return h


def _kind(h: dict[str, Any]) -> str | None:
    return _get(h, "decision", "kind")


def moments(health: list[dict[str, Any]]) -> list[int]:
    """Indices of the messages where the decision became brake or avoid (the first of each episode)."""
    out = []
    prev = None
    for i, h in enumerate(health):
        kind = _kind(h)
        if kind in ("brake", "avoid") and kind != prev:
            out.append(i)
        prev = kind
    return out


def _body_velocity(h: dict[str, Any]) -> tuple[float | None, float | None, float | None]:
    v = _get(h, "vehicle", "velocity_ned_m_s")
    att = _get(h, "vehicle", "attitude_rad")
    if not (isinstance(v, list) and len(v) == 3 and isinstance(att, list) and len(att) == 3):
        return None, None, None
    vn, ve, vd = (_num(x) for x in v)
    yaw = _num(att[2])
    if None in (vn, ve, vd, yaw):
        return None, None, None
    c, s = math.cos(yaw), math.sin(yaw)  # type: ignore[arg-type]
    return vn * c + ve * s, -vn * s + ve * c, vd  # type: ignore[operator]


# ---------------------------------------------------------------------------------------------- sections


def _summary(run: Run, t: list[float]) -> str:
    h0, h1 = run.health[0], run.health[-1]
    duration = t[-1] - t[0] if len(t) > 1 else 0.0
    state_time: dict[str, float] = {}
    kind_count: dict[str, int] = {}
    for i, h in enumerate(run.health):
        dt = t[i + 1] - t[i] if i + 1 < len(t) else 0.0
        state_time[str(h.get("state"))] = state_time.get(str(h.get("state")), 0.0) + dt
        k = _kind(h)
        if k:
            kind_count[k] = kind_count.get(k, 0) + 1
    p99s = [_num(_get(h, "frame_to_setpoint_ms", "p99")) for h in run.health]
    p99s = [p for p in p99s if p is not None]
    ages = [a for a in (_num(h.get("frame_age_ms")) for h in run.health) if a is not None]
    dropped = (_num(h1.get("dropped_frames")) or 0) - (_num(h0.get("dropped_frames")) or 0)
    processed = (_num(h1.get("processed_frames")) or 0) - (_num(h0.get("processed_frames")) or 0)
    errors: list[str] = []
    for h in run.health:
        e = h.get("last_error")
        if e and e not in errors:
            errors.append(str(e))
    changes = []
    prev = None
    for i, h in enumerate(run.health):
        if h.get("state") != prev:
            changes.append(f"<li><b>{t[i] - t[0]:.1f} s</b> {escape(str(h.get('state')))}: {escape(str(h.get('reason') or ''))}</li>")
            prev = h.get("state")
    rows = [
        ("duration", f"{duration:.1f} s, {len(run.health)} health messages"),
        ("time in each state", ", ".join(f"{escape(k)} {v:.1f} s" for k, v in state_time.items())),
        ("decisions (per health message)", ", ".join(f"{escape(k)} {v}" for k, v in sorted(kind_count.items())) or "none"),
        ("brake / avoid moments", str(len(moments(run.health)))),
        ("frame → setpoint p99", f"{max(p99s):.1f} ms at worst" if p99s else "not engaged"),
        ("frame age", f"median {sorted(ages)[len(ages) // 2]:.0f} ms, max {max(ages):.0f} ms" if ages else "–"),
        ("frames", f"{processed:.0f} processed, {dropped:.0f} dropped"),
        ("thresholds", f"near ≤ {run.near_m:g} m, far ≥ {run.far_m:g} m ({escape(run.thresholds_from)})"),
        ("preview frames", str(len(run.previews)) if run.previews else "none recorded"),
    ]
    table = "".join(f"<tr><th>{a}</th><td>{b}</td></tr>" for a, b in rows)
    err_html = (
        "<h4>Errors reported</h4><ul>" + "".join(f"<li>{escape(e)}</li>" for e in errors[:20]) + "</ul>" if errors else ""
    )
    return f'<table class="summary">{table}</table><h4>State changes</h4><ul class="changes">{"".join(changes[:60])}</ul>{err_html}'


def _decisions_plot(run: Run, t: list[float]) -> str:
    x = (t[0], t[-1])
    p = Plot(_WIDTH, 250, x, (-1.1, 1.45), title="Decisions: state (top band), decision (second band), yaw and pitch", x_label="time, s", y_label="[-1, 1]")
    p.band(t, [h.get("state") for h in run.health], STATE_COLOUR, 1.3, 1.43)
    p.band(t, [_kind(h) for h in run.health], KIND_COLOUR, 1.13, 1.26)
    p.line(t, [_num(h.get("yaw")) for h in run.health], "#1f5fd1", label="yaw (+ right)")
    p.line(t, [_num(h.get("pitch")) for h in run.health], "#9b2fc9", label="pitch (+ up)")
    p.line(t, [_num(_get(h, "decision", "speed_fraction")) for h in run.health], "#111", width=1.0, dash="4 3", label="speed fraction")
    top = p.svg()
    max_m = max(6.0, 2.5 * run.far_m)
    q = Plot(_WIDTH, 270, x, (0.0, max_m), title=f"Region depths (clipped at {max_m:g} m; unknown drawn at 0 = near)", x_label="time, s", y_label="m")
    colours = {"center": "#d93025", "left": "#1f5fd1", "right": "#2e9e44", "up": "#9b2fc9", "down": "#8a5a00"}
    for name in REGION_NAMES:
        ys = [_get(h, "regions_m", name) for h in run.health]
        ys = [0.0 if v is None else _num(v) for v in ys]
        q.line(t, ys, colours.get(name, "#b0b6bf"), width=2.0 if name in colours else 0.8, label=name if name in colours else None)
    q.hline(run.near_m, "#d93025", f"near {run.near_m:g} m")
    q.hline(run.far_m, "#2e9e44", f"far {run.far_m:g} m")
    return top + q.svg()


def _setpoint_plots(run: Run, t: list[float]) -> str:
    body = [_body_velocity(h) for h in run.health]
    have_velocity = any(b[0] is not None for b in body)
    out = []
    for title, key, idx, unit in (
        ("forward", "forward_m_s", 0, "m/s"),
        ("right", "right_m_s", 1, "m/s"),
        ("down", "down_m_s", 2, "m/s"),
    ):
        sp = [_num(_get(h, "setpoint", key)) for h in run.health]
        actual = [b[idx] for b in body]
        vals = [v for v in sp + actual if v is not None]
        lo, hi = (min(vals + [0.0]), max(vals + [0.0])) if vals else (-1.0, 1.0)
        pad = max(0.1, 0.1 * (hi - lo))
        p = Plot(_WIDTH, 170, (t[0], t[-1]), (lo - pad, hi + pad), title=f"{title}, body frame", x_label="time, s", y_label=unit)
        p.line(t, sp, "#d93025", label="setpoint")
        if have_velocity:
            p.line(t, actual, "#1f5fd1", label="vehicle")
        out.append(p.svg())
    # Yaw rate: the setpoint against the rate of the reported heading.
    sp = [_num(_get(h, "setpoint", "yaw_rate_deg_s")) for h in run.health]
    yaw = [_num((_get(h, "vehicle", "attitude_rad") or [None] * 3)[2]) if isinstance(_get(h, "vehicle", "attitude_rad"), list) else None for h in run.health]
    rate: list[float | None] = [None]
    for i in range(1, len(t)):
        if yaw[i] is None or yaw[i - 1] is None or t[i] - t[i - 1] <= 1e-3:
            rate.append(None)
        else:
            d = (yaw[i] - yaw[i - 1] + math.pi) % (2 * math.pi) - math.pi  # type: ignore[operator]
            rate.append(math.degrees(d) / (t[i] - t[i - 1]))
    vals = [v for v in sp + rate if v is not None]
    lim = max([10.0] + [abs(v) for v in vals])
    p = Plot(_WIDTH, 170, (t[0], t[-1]), (-lim, lim), title="yaw rate", x_label="time, s", y_label="deg/s")
    p.line(t, sp, "#d93025", label="setpoint")
    if any(r is not None for r in rate):
        p.line(t, rate, "#1f5fd1", label="vehicle (from its heading)")
    out.append(p.svg())
    note = "" if have_velocity else "<p class=note>The vehicle's velocity or attitude is not in these health messages; setpoints only.</p>"
    return note + "".join(out)


def _timing_plots(run: Run, t: list[float]) -> str:
    age = [_num(h.get("frame_age_ms")) for h in run.health]
    lat = [_num(_get(h, "frame_to_setpoint_ms", "last")) for h in run.health]
    p99 = [_num(_get(h, "frame_to_setpoint_ms", "p99")) for h in run.health]
    vals = [v for v in age + lat + p99 if v is not None]
    hi = min(max(vals + [50.0]) * 1.1, 6000.0)
    p = Plot(_WIDTH, 200, (t[0], t[-1]), (0.0, hi), title="Frame age and frame → setpoint latency", x_label="time, s", y_label="ms")
    p.line(t, age, "#1f5fd1", label="frame age")
    p.line(t, lat, "#d93025", label="frame → setpoint (last)")
    p.line(t, p99, "#8a5a00", dash="4 3", label="p99 (last 500)")
    p.hline(500.0, "#d93025", "stale: zero velocity (0.5 s)")
    fps = [_num(h.get("fps")) for h in run.health]
    d0 = _num(run.health[0].get("dropped_frames")) or 0.0
    dropped = [(_num(h.get("dropped_frames")) or 0.0) - d0 if h.get("dropped_frames") is not None else None for h in run.health]
    vals = [v for v in fps + dropped if v is not None]
    q = Plot(_WIDTH, 170, (t[0], t[-1]), (0.0, max(vals + [10.0]) * 1.1), title="fps and dropped frames", x_label="time, s", y_label="")
    q.line(t, fps, "#2e9e44", label="frames processed / s")
    q.line(t, dropped, "#d93025", label="dropped since the start")
    return p.svg() + q.svg()


def _path_plot(run: Run, t: list[float]) -> str | None:
    pts = []
    for h in run.health:
        pos = _get(h, "vehicle", "position_ned_m")
        if isinstance(pos, list) and len(pos) == 3 and _num(pos[0]) is not None and _num(pos[1]) is not None:
            pts.append((float(pos[1]), float(pos[0]), _kind(h)))
        else:
            pts.append(None)
    known = [p for p in pts if p is not None]
    if len(known) < 2:
        return None
    es, ns = [p[0] for p in known], [p[1] for p in known]
    pad = 1.0
    plot = Plot(_WIDTH, 460, (min(es) - pad, max(es) + pad), (min(ns) - pad, max(ns) + pad), equal_aspect=True,
                title="Path from above, coloured by decision (grey: no decision)", x_label="east, m", y_label="north, m")
    for i in range(1, len(pts)):
        a, b = pts[i - 1], pts[i]
        if a is None or b is None:
            continue
        colour = KIND_COLOUR.get(b[2] or "", "#9aa3ad")
        plot.line([a[0], b[0]], [a[1], b[1]], colour, width=3.0, clip=False)
    first, last = known[0], known[-1]
    plot.marker(first[0], first[1], "#15181d", "start", r=5, shape="square")
    plot.text(first[0], first[1], "start")
    plot.marker(last[0], last[1], "#15181d", "end", r=5)
    plot.text(last[0], last[1], "end")
    for i in moments(run.health):
        if pts[i] is not None:
            e, n, kind = pts[i]  # type: ignore[misc]
            plot.marker(e, n, KIND_COLOUR[kind], f"{kind} at {t[i] - t[0]:.1f} s", r=4.5)
    return plot.svg()


def _regions_svg(h: dict[str, Any], near_m: float, far_m: float) -> str:
    """The 9 region depths as a 3 x 3 grid with the decision's arrow: Fig. 10 drawn from a health message."""
    cells = []
    w, hh = 240, 135
    for i, name in enumerate(REGION_NAMES):
        r, c = divmod(i, 3)
        d = _num(_get(h, "regions_m", name))
        if d is None or d <= near_m:
            colour = "#d93025"
        elif d >= far_m:
            colour = "#2e9e44"
        else:
            colour = "#e89a00"
        label = "?" if d is None else f"{d:.2f} m"
        x, y = c * w / 3, r * hh / 3
        cells.append(f'<rect x="{x:.1f}" y="{y:.1f}" width="{w / 3:.1f}" height="{hh / 3:.1f}" fill="{colour}" opacity="0.8" stroke="#fff"/>')
        cells.append(f'<text x="{x + w / 6:.1f}" y="{y + hh / 6 + 5:.1f}" text-anchor="middle" class="cell">{label}</text>')
    yaw, pitch = _num(h.get("yaw")) or 0.0, _num(h.get("pitch")) or 0.0
    cx, cy = w / 2, hh / 2
    tx, ty = cx + yaw * 0.4 * hh, cy - pitch * 0.4 * hh
    cells.append(f'<line x1="{cx}" y1="{cy}" x2="{tx:.1f}" y2="{ty:.1f}" stroke="#111" stroke-width="4"/>')
    cells.append(f'<circle cx="{tx:.1f}" cy="{ty:.1f}" r="5" fill="#111"/>')
    return f'<svg viewBox="0 0 {w} {hh}" width="100%" xmlns="http://www.w3.org/2000/svg">{"".join(cells)}</svg>'


def _contact_sheet(run: Run, t: list[float], max_moments: int) -> str:
    idx = moments(run.health)
    if not idx:
        return "<p class=note>No brake or avoid moment in this flight.</p>"
    shown = idx[:max_moments]
    parts = []
    for i in shown:
        h = run.health[i]
        ts = float(h["time_s"])
        picture = None
        if run.previews:
            best = min(run.previews, key=lambda p: abs(p[0] - ts))
            if abs(best[0] - ts) <= 1.0:
                try:
                    data = base64.b64encode(best[1].read_bytes()).decode("ascii")
                    picture = f'<img alt="preview at {best[0] - float(run.health[0]["time_s"]):.1f} s" src="data:image/jpeg;base64,{data}">'
                except OSError:
                    picture = None
        if picture is None:
            picture = _regions_svg(h, run.near_m, run.far_m)
        kind = _kind(h) or "?"
        reason = escape(str(_get(h, "decision", "reason") or ""))
        parts.append(
            f'<figure class="moment"><div class="kind" style="background:{KIND_COLOUR.get(kind, "#999")}">{escape(kind)} at {t[i] - t[0]:.1f} s</div>'
            f"{picture}<figcaption>yaw {(_num(h.get('yaw')) or 0):+.2f}, pitch {(_num(h.get('pitch')) or 0):+.2f}, "
            f"centre {('?' if _num(_get(h, 'regions_m', 'center')) is None else format(_num(_get(h, 'regions_m', 'center')), '.2f') + ' m')}"
            f"<br>{reason}</figcaption></figure>"
        )
    more = f"<p class=note>{len(idx) - len(shown)} more moments not shown (--max-moments).</p>" if len(idx) > len(shown) else ""
    source = "the recorded preview frame nearest to each moment" if run.previews else "the region depths of the health message (no preview frames recorded)"
    return f'<p class=note>Each moment is the first message of a brake or avoid episode, shown with {source}.</p><div class="sheet">{"".join(parts)}</div>{more}'


_CSS = """
body{font:14px/1.4 system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;color:#15181d;background:#eef1f4;margin:0}
main{max-width:1000px;margin:0 auto;padding:16px}
h1{font-size:22px;margin:8px 0}h2{font-size:18px;margin:28px 0 8px;border-bottom:2px solid #1c2430}
h3{font-size:15px;margin:18px 0 6px;color:#3a4350}h4{margin:10px 0 4px}
section.run{background:#fff;border:1px solid #d5d9df;border-radius:8px;padding:12px 16px;margin-bottom:18px}
table.summary{border-collapse:collapse}table.summary th{text-align:left;padding:2px 14px 2px 0;color:#5c6470;font-weight:500}
ul.changes{columns:2;font-size:13px}.note{color:#5c6470;font-size:13px}
svg{display:block;margin:4px 0 10px}svg text.tick{font-size:11px;fill:#5c6470}svg text.label{font-size:12px;fill:#3a4350}
svg text.ptitle{font-size:13px;font-weight:600;fill:#15181d}svg text.cell{font-size:15px;font-weight:700;fill:#fff}
.sheet{display:grid;grid-template-columns:repeat(auto-fill,minmax(220px,1fr));gap:10px}
figure.moment{margin:0;border:1px solid #d5d9df;border-radius:6px;overflow:hidden;background:#fafbfc}
figure.moment img{width:100%;display:block}figure.moment .kind{color:#fff;font-weight:700;padding:3px 8px;text-transform:uppercase;font-size:12px}
figcaption{font-size:12px;padding:4px 8px;color:#3a4350}nav a{margin-right:10px}
"""


def render_run(run: Run, max_moments: int = 24) -> str:
    """One flight's section of the report (HTML)."""
    t = [float(h["time_s"]) for h in run.health]
    t0 = t[0]
    rel = [x - t0 for x in t]
    path = _path_plot(run, rel)
    parts = [
        f'<section class="run" id="{escape(run.name)}"><h2>{escape(run.name)}</h2>',
        f'<p class=note>{escape(str(run.folder))}</p>',
        _summary(run, rel),
        "<h3>Decisions and regions over time</h3>",
        _decisions_plot(run, rel),
        "<h3>Setpoints against the vehicle's velocity</h3>",
        _setpoint_plots(run, rel),
        "<h3>Frame age, latency and dropped frames</h3>",
        _timing_plots(run, rel),
        "<h3>Path from above</h3>",
        path if path is not None else "<p class=note>The vehicle's position is not in these health messages.</p>",
        "<h3>Contact sheet: brake and avoid moments</h3>",
        _contact_sheet(run, rel, max_moments),
        "</section>",
    ]
    return "".join(parts)


def write_review(path: Path, out: Path | None, max_moments: int = 24) -> Path:
    """Write the report of the flights under ``path`` to ``out`` (default: ``review.html`` in the
    run's folder, or beside a given ``health.jsonl``); returns where it went.

    Raises:
        InputError: nothing to review, or the report cannot be written.
    """
    runs = load_runs(path)
    if out is None:
        base = path.expanduser()
        out = (base.parent if base.is_file() else base) / "review.html"
    nav = ""
    if len(runs) > 1:
        nav = "<nav>" + "".join(f'<a href="#{escape(r.name)}">{escape(r.name)}</a>' for r in runs) + "</nav>"
    body = "".join(render_run(r, max_moments) for r in runs)
    html = (
        '<!doctype html><html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>companion review: {escape(path.name)}</title><style>{_CSS}</style></head><body><main>"
        f"<h1>companion review: {escape(path.name)}</h1><p class=note>{len(runs)} flight(s); times are seconds from the "
        f"first health message of each.</p>{nav}{body}</main></body></html>"
    )
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(html, encoding="utf-8")
    except OSError as err:
        raise InputError(f"{out}: cannot write the report: {err.strerror or err}") from None
    return out
