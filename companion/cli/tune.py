"""``companion tune``: search config settings on a suite with Optuna through Ray Tune, and report what each did."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion import exitcodes
from companion.errors import InputError

if TYPE_CHECKING:
    from companion.sim.cluster import TuneSpec


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``tune``."""
    p = sub.add_parser(
        "tune",
        help="search config settings (speeds, membership functions, rule weights) on a simulated suite",
        description=(
            "Search the settings named (PATH=LOW:HIGH, or a --space file) for the best score on a suite of "
            "simulated courses: the success rate (goal reached, or held where that is right) less a cost per "
            "second of mean time to goal, with any collision ranking a candidate below every one without. "
            "Optuna proposes the candidates through Ray Tune (pip install 'companion[cluster]'), the first "
            "being the config's own values. Each range is clipped to its field's bounds and to the safety "
            "envelope, and each candidate is validated whole before it flies. The experiment lives in --out: "
            "Ctrl-C (or a kill) stops it, --resume goes on. At the end --out holds best.toml (the best "
            "settings, to merge into a config file and reload, or the `companion ctl set` line printed), "
            "report.md, trials.csv and plots."
        ),
    )
    p.add_argument(
        "settings",
        nargs="*",
        metavar="PATH=LOW:HIGH",
        help=(
            "a setting and its range: e.g. planner.cruise_speed_m_s=2:3.5, "
            "controller.input_terms.near.params_m.1=1.8:2.6 (a breakpoint), controller.main_rules.R7.weight=0.2:1"
        ),
    )
    p.add_argument("--space", type=Path, metavar="FILE", help="settings from a TOML or YAML file: PATH = [LOW, HIGH]")
    p.add_argument("--suite", required=True, metavar="NAME", help="the suite every candidate flies: standard or quick")
    p.add_argument("--kinds", metavar="K1,K2", help="fly only these course kinds of the suite")
    p.add_argument("--config", type=Path, help="TOML config the candidates start from (default: built-in defaults)")
    p.add_argument("--trials", type=int, default=20, help="candidates in all, the config's own values first (default 20)")
    p.add_argument("--out", type=Path, required=True, help="folder of the experiment and its results (made if missing)")
    p.add_argument("--resume", action="store_true", help="go on with the experiment in --out (stopped or killed)")
    p.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="an existing Ray cluster: 'auto' or ray://HOST:10001 (default: a Ray started here for the run)",
    )
    p.add_argument("--cpus", type=int, help="CPUs of the Ray started here: trials at once (default: all)")
    p.add_argument("--seed", type=int, default=0, help="the sampler's seed (default 0)")
    p.add_argument(
        "--time-weight-per-s",
        type=float,
        default=0.1,
        help="score points one second of mean time to goal costs (default 0.1; the success rate is in percent)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import math

    from companion.cli.sim import courses_of
    from companion.config import load_config
    from companion.core.rig_check import check_rig_config
    from companion.sim.cluster import TuneSpec, require_ray, run_tune
    from companion.sim.tuning import (
        best_patch,
        best_row,
        ctl_set_command,
        fragment_toml,
        load_space_file,
        parse_setting,
        resolve_settings,
        write_report,
    )

    require_ray()
    if args.trials < 1:
        raise InputError(f"--trials must be >= 1, got {args.trials}")
    if args.cpus is not None and args.cpus < 1:
        raise InputError(f"--cpus must be >= 1, got {args.cpus}")
    if not math.isfinite(args.time_weight_per_s) or args.time_weight_per_s < 0:
        raise InputError(f"--time-weight-per-s must be a number >= 0, got {args.time_weight_per_s}")
    if args.kinds is not None and not args.kinds.strip():
        raise InputError("--kinds needs at least one course kind")
    cfg = load_config(args.config)
    check_rig_config(cfg, str(args.config or "config"))  # the base the candidates are made from
    requested = [parse_setting(t) for t in args.settings]
    if args.space is not None:
        requested += load_space_file(args.space)
    settings = resolve_settings(cfg, requested)
    courses = courses_of(args)
    out = args.out.expanduser().resolve()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{out}: cannot make the folder ({e.strerror or e})") from None
    for s in settings:
        print(f"search {s.path} in {s.low:g}..{s.high:g} (base {s.start:g})")
    print(f"{args.trials} trials x {len(courses)} flights of suite {args.suite}; experiment in {out}", flush=True)
    spec = TuneSpec(base=cfg, settings=settings, courses=courses, trials=args.trials,
                    time_weight_per_s=args.time_weight_per_s, seed=args.seed)
    _check_same_search(out / "search.json", spec, args.resume)
    rows, complete = run_tune(spec, out, resume=args.resume, address=args.ray, num_cpus=args.cpus)
    title = f"companion tune: suite {args.suite}" + (f" ({args.kinds})" if args.kinds else "")
    files = write_report(rows, settings, out, title)
    best = best_row(rows)
    if best is not None:
        values = {s.path: best[s.path] for s in settings}
        patch = best_patch(cfg, values)
        header = [
            f"{title}: the best of {len(rows)} trials (trial {best['trial']}), score {best['score']:.4g}:",
            f"success {best['success_pct']:.0f}%, goal {best['goal_pct']:.0f}%, {best['collisions']} collisions, "
            f"mean time to goal {best['mean_goal_time_s']:.1f} s over {best['flights']} flights.",
            "Merge into the config file and reload (SIGHUP, `companion ctl reload`), or run:",
            ctl_set_command(patch),
        ]
        fragment = out / "best.toml"
        fragment.write_text(fragment_toml(patch, header), encoding="utf-8")
        files.insert(0, fragment)
        print(f"best: trial {best['trial']}: " + ", ".join(f"{p} = {v:g}" for p, v in values.items())
              + f"; score {best['score']:.4g} (success {best['success_pct']:.0f}%, {best['collisions']} collisions, "
              f"mean time to goal {best['mean_goal_time_s']:.1f} s)")
        command = ctl_set_command(patch)
        print(command if len(command) <= 400 else "apply: the `companion ctl set` line in best.toml")
    for f in files:
        print(f"wrote {f}")
    if not complete:
        print(f"stopped after {len(rows)} of {args.trials} trials; go on with the same command and --resume",
              file=sys.stderr)
        return exitcodes.FORCED_EXIT
    return exitcodes.OK


def _check_same_search(path: Path, spec: TuneSpec, resume: bool) -> None:
    """Keep what a tune searches beside its experiment; a resume must search the same (settings,
    ranges, courses, trials, seed, score, base config), else its trials would not compare."""
    import dataclasses

    from companion.sim.cluster import EXPERIMENT_DIR
    data = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec) if f.name != "base"}
    data["settings"] = [dataclasses.asdict(s) for s in spec.settings]
    data["courses"] = [list(c) for c in spec.courses]
    data["base"] = spec.base.model_dump(mode="json")
    text = json.dumps(data, indent=1, sort_keys=True)
    if not resume:
        if (path.parent / EXPERIMENT_DIR).exists():
            raise InputError(f"{path.parent}: a tune is already here; --resume to go on with it, or another --out")
        path.write_text(text, encoding="utf-8")
        return
    try:
        kept = path.read_text(encoding="utf-8")
    except OSError:
        raise InputError(f"{path.parent}: no tune to resume here") from None
    try:
        differs = _differences(json.loads(kept), json.loads(text))
    except ValueError as err:
        differs = [f"{path.name} is not JSON ({err})"]
    if differs:
        raise InputError(
            f"{path.parent}: --resume must search what the tune there searched (the same settings, ranges, "
            "suite, --kinds, --trials, --seed, --time-weight-per-s and --config, on a machine whose "
            f"'auto' settings resolve alike); differs: {'; '.join(differs)}"
        )


def _differences(there: Any, here: Any, key: str = "", limit: int = 3) -> list[str]:
    """The first ``limit`` dotted keys whose values differ between two JSON values (the kept search's,
    this one's), each as ``key: <there> there, <here> here`` with long values cut short."""
    if isinstance(there, dict) and isinstance(here, dict):
        out: list[str] = []
        for k in sorted(set(there) | set(here)):
            sub = f"{key}.{k}" if key else str(k)
            if k not in there or k not in here:
                out.append(f"{sub}: {'missing there' if k not in there else 'missing here'}")
            else:
                out += _differences(there[k], here[k], sub, limit - len(out))
            if len(out) >= limit:
                break
        return out[:limit]
    if there != here:
        return [f"{key}: {_short(there)} there, {_short(here)} here"]
    return []


def _short(value: Any, chars: int = 60) -> str:
    text = json.dumps(value)
    return text if len(text) <= chars else text[: chars - 3] + "..."
