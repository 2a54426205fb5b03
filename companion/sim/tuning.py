"""The tuner's settings, scores and results, without Ray (``companion tune``; Ray's side: :mod:`companion.sim.cluster`).

A *setting* is a number in the config named by a dotted path, and the range to search it in:
``planner.cruise_speed_m_s=2:3.5``, ``controller.input_terms.near.params_m.1=1.8:2.6`` (a membership
function's breakpoint: its term, then the parameter's index), ``controller.main_rules.R7.weight=0.2:1``
(a rule by its name). The range is clipped to the field's own bounds and to the safety envelope
(:func:`resolve_settings`), and every candidate is validated whole by the config models before it flies
(:func:`with_settings`): what the service would refuse is never flown.

A candidate's *score* (:func:`score_flights`): with any collision, minus the collisions (below every
candidate without one: collisions are a hard constraint); without, the success percentage (goal reached,
or held where holding is right) less ``time_weight_per_s`` points per second of mean time to goal.
"""

from __future__ import annotations

import csv
import json
import math
import re
import shlex
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from companion.config import CompanionConfig, as_written, parse_config
from companion.config.edit import toml_value
from companion.config.envelope import envelope_violations
from companion.core.rig_check import check_rig_config
from companion.errors import InputError
from companion.sim.scoring import Outcome

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

#: The score of a candidate the config models refuse (never flown): below any flown candidate's.
INVALID_SCORE = -1000.0

_SETTING = re.compile(r"^\s*([A-Za-z0-9_.\-]+)\s*=\s*([^:]+):([^:]+)\s*$")
_BARE_KEY = re.compile(r"^[A-Za-z0-9_\-]+$")


@dataclass(frozen=True)
class Setting:
    """One setting searched.

    Attributes:
        path: the dotted path in the config (model fields, table keys, list indices or rule names).
        low, high: the range searched, inclusive, in the field's unit, inside the field's bounds and the
            envelope.
        integer: the field is an integer (searched over integers).
        start: the base config's value, clipped into the range (the first candidate flies it).
    """

    path: str
    low: float
    high: float
    integer: bool
    start: float

    @property
    def key(self) -> str:
        """The parameter's name in the search (the path)."""
        return self.path

    def cast(self, value: Any) -> int | float:
        """``value`` as the field's type."""
        return int(round(float(value))) if self.integer else float(value)

    def distribution(self, optuna: Any) -> Any:
        """This setting's Optuna distribution (``optuna`` is the imported module)."""
        if self.integer:
            return optuna.distributions.IntDistribution(int(self.low), int(self.high))
        return optuna.distributions.FloatDistribution(self.low, self.high)


def parse_setting(text: str) -> tuple[str, float, float]:
    """``PATH=LOW:HIGH`` -> (path, low, high).

    Raises:
        InputError: not of that form, bounds not finite numbers, or low above high.
    """
    m = _SETTING.match(text)
    if m is None:
        raise InputError(f"setting {text!r}: expected PATH=LOW:HIGH, e.g. planner.cruise_speed_m_s=2:3.5")
    return _range(m.group(1), m.group(2), m.group(3))


def _range(path: str, low: Any, high: Any) -> tuple[str, float, float]:
    try:
        lo, hi = float(low), float(high)
    except (TypeError, ValueError):
        raise InputError(f"setting {path}: the range needs two numbers, got {low!r} and {high!r}") from None
    if isinstance(low, bool) or isinstance(high, bool) or not (math.isfinite(lo) and math.isfinite(hi)):
        raise InputError(f"setting {path}: the range needs two finite numbers, got {low!r} and {high!r}")
    if lo > hi:
        raise InputError(f"setting {path}: low {lo:g} is above high {hi:g}")
    return path, lo, hi


def load_space_file(path: Path) -> list[tuple[str, float, float]]:
    """The settings of a space file (TOML, or YAML by its suffix .yaml/.yml): each a dotted path (quoted,
    or as nested tables) to ``[low, high]`` or ``{low = .., high = ..}``.

    Raises:
        InputError: unreadable, not TOML/YAML, or an entry that is not a range.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise InputError(f"{path}: cannot read the space file ({err.strerror or err})") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise InputError(f"{path}: a YAML space file needs PyYAML: pip install 'companion[cluster]'") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise InputError(f"{path}: not valid YAML: {str(err).splitlines()[0]}") from None
    else:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise InputError(f"{path}: not valid TOML: {err}") from None
    if not isinstance(data, Mapping) or not data:
        raise InputError(f"{path}: expected a table of settings (PATH = [LOW, HIGH])")
    out: list[tuple[str, float, float]] = []
    _flatten_space(data, "", out, path)
    return out


def _flatten_space(data: Mapping[str, Any], prefix: str, out: list[tuple[str, float, float]], source: Path) -> None:
    for key, value in data.items():
        where = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping) and set(value) == {"low", "high"}:
            out.append(_range(where, value["low"], value["high"]))
        elif isinstance(value, Mapping):
            _flatten_space(value, where, out, source)
        elif isinstance(value, (list, tuple)) and len(value) == 2:
            out.append(_range(where, value[0], value[1]))
        else:
            raise InputError(f"{source}: {where}: expected [LOW, HIGH] or {{low, high}}, got {value!r}")


def _step(node: Any, part: str, path: str) -> tuple[Any, FieldInfo | None, int | str]:
    """One step of a dotted path: (child, its model field or None, the key or index taken)."""
    if isinstance(node, BaseModel):
        fields = type(node).model_fields
        if part not in fields:
            raise InputError(f"setting {path}: {part!r} is not a setting here; settings are {', '.join(fields)}")
        return getattr(node, part), fields[part], part
    if isinstance(node, Mapping):
        if part not in node:
            raise InputError(f"setting {path}: no {part!r} here; there are {', '.join(map(str, node))}")
        return node[part], None, part
    if isinstance(node, (list, tuple)):
        if part.isdigit() and int(part) < len(node):
            return node[int(part)], None, int(part)
        names = [getattr(x, "name", None) for x in node]
        if part in names:
            return node[names.index(part)], None, names.index(part)
        raise InputError(
            f"setting {path}: no {part!r} here; give an index below {len(node)}"
            + (f" or a name ({', '.join(str(n) for n in names)})" if any(names) else "")
        )
    raise InputError(f"setting {path}: {part!r} is below a value, not a table")


def _locate(cfg: CompanionConfig, path: str) -> tuple[Any, FieldInfo | None, list[int | str], bool]:
    """(value at ``path``, the model field it is (None inside a table or list), the keys and indices taken,
    whether every step was a model field)."""
    node: Any = cfg
    info: FieldInfo | None = None
    keys: list[int | str] = []
    fields_only = True
    for part in path.split("."):
        node, info, key = _step(node, part, path)
        fields_only = fields_only and info is not None
        keys.append(key)
    return node, info, keys, fields_only


def _field_bounds(info: FieldInfo | None) -> tuple[float, float, bool, bool]:
    """(low, high, low open, high open) of a field's own bounds; infinite where it has none."""
    lo, hi, lo_open, hi_open = -math.inf, math.inf, False, False
    if info is None:
        return lo, hi, lo_open, hi_open
    # A union such as ``Annotated[int, Field(ge=0)] | Literal["auto"]`` keeps its bounds on its member.
    members = [m for arg in get_args(info.annotation) for m in getattr(arg, "__metadata__", ())]
    members = [x for m in members for x in (m.metadata if isinstance(m, FieldInfo) else [m])]
    for m in [*info.metadata, *members]:
        for attr, is_low, is_open in (("ge", True, False), ("gt", True, True), ("le", False, False), ("lt", False, True)):
            v = getattr(m, attr, None)
            if v is None:
                continue
            if is_low and float(v) >= lo:
                lo, lo_open = float(v), is_open
            elif not is_low and float(v) <= hi:
                hi, hi_open = float(v), is_open
    return lo, hi, lo_open, hi_open


def _set_unvalidated(model: BaseModel, keys: Sequence[int | str], value: Any) -> BaseModel:
    """``model`` with the model field at ``keys`` set, without validation (for probing the envelope)."""
    head = str(keys[0])
    if len(keys) == 1:
        return model.model_copy(update={head: value})
    return model.model_copy(update={head: _set_unvalidated(getattr(model, head), keys[1:], value)})


def _envelope_range(cfg: CompanionConfig, path: str, keys: Sequence[int | str], lo: float, hi: float,
                    integer: bool) -> tuple[float, float]:
    """The part of [lo, hi] where ``path`` keeps ``cfg`` inside its envelope.

    The envelope is a list of checks (:func:`~companion.config.envelope.envelope_violations`), each an
    upper or a lower limit on one field, not a table of bounds; the limit is found by bisection on those
    checks, so that a check added there bounds the search too.
    """

    def inside(v: float) -> bool:
        probe = _set_unvalidated(cfg, keys, int(v) if integer else v)
        return not any(line.startswith(path + " ") for line in envelope_violations(probe))  # type: ignore[arg-type]

    lo_ok, hi_ok = inside(lo), inside(hi)
    if lo_ok and hi_ok:
        return lo, hi
    if not lo_ok and not hi_ok:
        raise InputError(f"setting {path}: no value in {lo:g}..{hi:g} is inside the safety envelope ([envelope])")
    good, bad = (lo, hi) if lo_ok else (hi, lo)
    for _ in range(64):  # to the float's resolution
        mid = (good + bad) / 2.0
        if integer:
            mid = math.floor(mid) if lo_ok else math.ceil(mid)
            if mid in (good, bad):
                break
        if mid in (good, bad):
            break
        if inside(mid):
            good = mid
        else:
            bad = mid
    return (lo, good) if lo_ok else (good, hi)


def resolve_settings(cfg: CompanionConfig, requested: Sequence[tuple[str, float, float]]) -> tuple[Setting, ...]:
    """The settings searched: each path found in ``cfg``, its range clipped to the field's bounds and the
    safety envelope of ``cfg``.

    Raises:
        InputError: a path that names no number in the config, names the envelope, is given twice, or whose
            clipped range is empty.
    """
    out: list[Setting] = []
    seen: set[str] = set()
    for path, lo, hi in requested:
        if path in seen:
            raise InputError(f"setting {path}: given twice")
        seen.add(path)
        if path.split(".")[0] == "envelope":
            raise InputError(f"setting {path}: the safety envelope bounds the search; it is not searched")
        value, info, keys, fields_only = _locate(cfg, path)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"setting {path}: not a number (it is {value!r}); only numbers are searched")
        integer = isinstance(value, int)
        f_lo, f_hi, lo_open, hi_open = _field_bounds(info)
        if lo_open:
            f_lo = f_lo + 1 if integer else math.nextafter(f_lo, math.inf)
        if hi_open:
            f_hi = f_hi - 1 if integer else math.nextafter(f_hi, -math.inf)
        c_lo, c_hi = max(lo, f_lo), min(hi, f_hi)
        if integer:
            c_lo, c_hi = float(math.ceil(c_lo)), float(math.floor(c_hi))
        if c_lo > c_hi:
            raise InputError(f"setting {path}: {lo:g}..{hi:g} is outside the field's bounds {f_lo:g}..{f_hi:g}")
        if fields_only:
            c_lo, c_hi = _envelope_range(cfg, path, keys, c_lo, c_hi, integer)
        start = min(max(float(value), c_lo), c_hi)
        out.append(Setting(path=path, low=c_lo, high=c_hi, integer=integer, start=start))
    if not out:
        raise InputError("name at least one setting to search (PATH=LOW:HIGH or --space FILE)")
    return tuple(out)


def _keys_in_data(data: Any, path: str) -> list[int | str]:
    """The keys and indices of ``path`` in a config's JSON form (rule names found by their ``name``)."""
    keys: list[int | str] = []
    node = data
    for part in path.split("."):
        if isinstance(node, list):
            names = [x.get("name") if isinstance(x, dict) else None for x in node]
            k: int | str = int(part) if part.isdigit() else names.index(part)
        else:
            k = part
        keys.append(k)
        node = node[k]
    return keys


def with_settings(base: CompanionConfig, values: Mapping[str, float]) -> CompanionConfig:
    """``base`` with each path of ``values`` set, validated whole by the config models (fields, rules,
    the rig and the safety envelope), as a reload would be.

    Raises:
        ConfigError: the candidate is not a valid config (naming the field and why).
        InputError: a path that names nothing in ``base``.
    """
    data = as_written(base)  # settings written "auto" stay "auto", resolved again for the candidate
    for path, value in values.items():
        try:
            keys = _keys_in_data(data, path)
        except (KeyError, IndexError, ValueError, TypeError):
            raise InputError(f"setting {path}: names nothing in the config") from None
        node = data
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value
    candidate = parse_config(data, source="candidate")
    check_rig_config(candidate, "candidate")  # as the service checks a reload
    return candidate


def best_patch(base: CompanionConfig, values: Mapping[str, float]) -> dict[str, Any]:
    """The patch that turns ``base`` into the candidate of ``values``, as ``ctl set`` and a TOML file take
    it: ``{dotted path: value}`` where a value inside a list (a rule, a membership function's parameters)
    carries the whole list, since a config's lists are replaced, not merged.

    Raises:
        ConfigError: the candidate is not a valid config.
    """
    data = with_settings(base, values).model_dump(mode="json")
    patch: dict[str, Any] = {}
    for path in values:
        keys = _keys_in_data(data, path)
        node: Any = data
        unit: list[str] = []
        for k in keys:
            if isinstance(node, list):
                break
            unit.append(str(k))
            node = node[k]
        patch[".".join(unit)] = node
    return patch


def _toml_key(parts: Sequence[str]) -> str:
    return ".".join(p if _BARE_KEY.match(p) else json.dumps(p) for p in parts)


def fragment_toml(patch: Mapping[str, Any], header: Sequence[str] = ()) -> str:
    """``patch`` (:func:`best_patch`) as a TOML fragment: a table per config section, dotted keys under
    it; merged into a config file and reloaded (SIGHUP, ``ctl reload``) it applies the patch."""
    lines = [f"# {h}" for h in header]
    sections: dict[str, list[str]] = {}
    for path, value in patch.items():
        head, *rest = path.split(".")
        sections.setdefault(head, []).append(f"{_toml_key(rest)} = {toml_value(value)}")
    for head, body in sections.items():
        lines += ["", f"[{head}]", *body]
    return "\n".join(lines).lstrip("\n") + "\n"


def ctl_set_command(patch: Mapping[str, Any]) -> str:
    """The ``companion ctl set`` command line that applies ``patch`` to a running service."""
    return "companion ctl set " + " ".join(
        shlex.quote(f"{path}={json.dumps(value, separators=(',', ':'))}") for path, value in patch.items()
    )


@dataclass(frozen=True)
class TrialScore:
    """How one candidate flew its courses (what a trial reports).

    Attributes:
        score: the search's objective, higher is better (see the module).
        success_pct: flights that reached the goal or held where holding is right, percent.
        goal_pct: flights that reached the goal, percent.
        collisions: flights that ended in a collision.
        mean_goal_time_s: mean simulated time of the flights that reached the goal, seconds (0: none did).
        flights: flights flown (0: the candidate was refused).
        failed: the courses that were no success, each ``name: outcome``, comma-separated.
        problem: why the candidate was refused, one line; "" when it flew.
    """

    score: float
    success_pct: float
    goal_pct: float
    collisions: int
    mean_goal_time_s: float
    flights: int
    failed: str = ""
    problem: str = ""

    @classmethod
    def invalid(cls, problem: str) -> TrialScore:
        """A candidate the config models refuse: :data:`INVALID_SCORE`, nothing flown."""
        return cls(INVALID_SCORE, 0.0, 0.0, 0, 0.0, 0, "", problem)


def score_flights(results: Sequence[Any], time_weight_per_s: float = 0.1) -> TrialScore:
    """Score a candidate's flights (:class:`~companion.sim.loop.FlightResult`).

    With any collision the score is minus the collisions; without, the success percentage less
    ``time_weight_per_s`` per second of mean time to goal (0.1: one flight in ten more at the goal of a
    10-flight suite is worth 100 s of mean time).
    """
    n = len(results)
    if n == 0:
        return TrialScore.invalid("no flights")
    collisions = sum(r.outcome is Outcome.COLLISION for r in results)
    goals = [r.time_s for r in results if r.outcome is Outcome.GOAL]
    success_pct = 100.0 * sum(bool(r.success) for r in results) / n
    mean_goal_time_s = float(sum(goals) / len(goals)) if goals else 0.0
    score = -float(collisions) if collisions else success_pct - time_weight_per_s * mean_goal_time_s
    return TrialScore(
        score=score,
        success_pct=success_pct,
        goal_pct=100.0 * len(goals) / n,
        collisions=collisions,
        mean_goal_time_s=mean_goal_time_s,
        flights=n,
        failed=", ".join(f"{r.course.name}: {r.outcome.value}" for r in results if not r.success),
    )


_COLUMNS = ("score", "success_pct", "goal_pct", "collisions", "mean_goal_time_s", "flights", "failed")


def best_row(rows: Sequence[Mapping[str, Any]]) -> Mapping[str, Any] | None:
    """The trial with the highest score among those that flew (the first made wins a tie); None if none flew."""
    flown = [r for r in rows if r.get("flights", 0) > 0]
    return max(flown, key=lambda r: r["score"]) if flown else None


def write_report(rows: Sequence[Mapping[str, Any]], settings: Sequence[Setting], out: Path,
                 title: str) -> list[Path]:
    """What each setting did: ``trials.csv`` (every trial), ``report.md`` (the trials best first, the first
    trial being the base config's own values) and, with matplotlib, ``settings.png`` (each setting's value
    against the score, collisions marked) and ``progress.png`` (score by trial, and the best so far).

    Returns:
        The files written.
    """
    out.mkdir(parents=True, exist_ok=True)
    paths = [s.path for s in settings]
    written = [out / "trials.csv", out / "report.md"]
    with written[0].open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["trial", *paths, *_COLUMNS, "problem"])
        for r in rows:
            w.writerow([r.get("trial", ""), *(r.get(p, "") for p in paths), *(r.get(c, "") for c in _COLUMNS),
                        r.get("problem", "")])
    header = ["trial", *paths, "score", "success %", "goal %", "collisions", "mean time to goal s", "flights",
              "not a success"]
    lines = [f"# {title}", "", f"{len(rows)} trials, best first; trial 1 flies the base config's values.", ""]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in sorted(rows, key=lambda r: -r.get("score", INVALID_SCORE)):
        tag = " (base)" if r.get("trial") == 1 else ""
        cells = [f"{r.get('trial', '')}{tag}", *(_fmt(r.get(p)) for p in paths), _fmt(r.get("score")),
                 _fmt(r.get("success_pct")), _fmt(r.get("goal_pct")), str(r.get("collisions", "")),
                 _fmt(r.get("mean_goal_time_s")), str(r.get("flights", "")), str(r.get("failed", ""))]
        lines.append("| " + " | ".join(cells) + " |")
    refused = [r for r in rows if r.get("problem")]
    if refused:
        lines += ["", "Not scored (refused by the config models, or failed):", ""]
        lines += [f"* {r.get('trial', '')}: {r['problem']}" for r in refused]
    written[1].write_text("\n".join(lines) + "\n", encoding="utf-8")
    written += _plots(rows, settings, out)
    return written


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def _plots(rows: Sequence[Mapping[str, Any]], settings: Sequence[Setting], out: Path) -> list[Path]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    flown = [r for r in rows if r.get("flights", 0) > 0]
    if not flown:
        return []
    n = len(settings)
    fig, axes = plt.subplots(1, n, figsize=(4.0 * n, 3.5), squeeze=False)
    for ax, s in zip(axes[0], settings):
        clean = [r for r in flown if r["collisions"] == 0]
        hit = [r for r in flown if r["collisions"] > 0]
        ax.scatter([r[s.path] for r in clean], [r["score"] for r in clean], c="tab:blue", label="no collision")
        ax.scatter([r[s.path] for r in hit], [r["score"] for r in hit], c="tab:red", marker="x", label="collision")
        ax.axvline(s.start, color="grey", linestyle=":", label="base")
        ax.set_xlabel(s.path, fontsize=8)
        ax.set_ylabel("score")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    settings_png = out / "settings.png"
    fig.savefig(settings_png, dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6.0, 3.5))
    numbers = [r["trial"] for r in flown]
    scores = [r["score"] for r in flown]
    best = [max(scores[: i + 1]) for i in range(len(scores))]
    ax.plot(numbers, scores, "o", label="trial (refused ones not shown)")
    ax.plot(numbers, best, "-", label="best so far")
    ax.set_xlabel("trial")
    ax.set_ylabel("score")
    ax.legend(fontsize=7)
    fig.tight_layout()
    progress_png = out / "progress.png"
    fig.savefig(progress_png, dpi=100)
    plt.close(fig)
    return [settings_png, progress_png]
