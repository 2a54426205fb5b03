"""``companion sitl``: fly the service against PX4 SITL (SIH) or ArduPilot SITL (ArduCopter) through the
simulator's courses."""

from __future__ import annotations

import argparse
import asyncio
import time
from pathlib import Path
from typing import Any

from companion.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``sitl``."""
    p = sub.add_parser(
        "sitl",
        help="fly the service against PX4 SITL (SIH quadrotor) or ArduPilot SITL through simulated obstacle courses",
        description=(
            "The autopilot in the loop: PX4's SIH quadrotor (or ArduCopter SITL's built-in quad with "
            "--autopilot ardupilot) flies, the service (`companion run`, in its own process) "
            "commands it over MAVSDK exactly as on the vehicle, and its camera renders each frame from the "
            "pose the autopilot reports, inside a course whose geometry is known. The ground station here arms, takes "
            "off to the course height, sends the same `engage` a user would, judges the autopilot's own position "
            "against the true geometry (goal, collision, held, timeout; minimum clearance), and lands. "
            "The autopilot must be running (`make px4_sitl sihsim_quadx` in PX4-Autopilot; ArduPilot: see "
            "docs/sitl-ardupilot.md), or name its build with --px4-build / $COMPANION_PX4_BUILD "
            "(--ardupilot-build / $COMPANION_ARDUPILOT_BUILD) to have it started fresh for every course."
        ),
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--course", metavar="KIND", help="course kind: corridor, doorway, forest, pitch, side, deadend, office, detour, head-on")
    what.add_argument("--suite", metavar="NAME", help="a suite of courses: quick (16 flights) or standard (72)")
    what.add_argument(
        "--scenario", choices=["collision-prevention", "rc-engage", "proximity", "step-response"],
        help=(
            "PX4 (docs/sitl.md): collision-prevention: the service only feeds OBSTACLE_DISTANCE while a pilot "
            "flies Position mode at a wall (CP_DIST set); then the service stops. rc-engage: the ground station "
            "switches PX4 to Offboard while the service is ready (vehicle.engage_on_offboard_switch), then back to "
            "Position mode. step-response: the ground station steps PX4's velocity and yaw-rate setpoints itself "
            "and fits the simulator's vehicle model to the response (docs/simulator.md). "
            "ArduPilot (--autopilot ardupilot, docs/sitl-ardupilot.md): proximity: the service only "
            "feeds OBSTACLE_DISTANCE to ArduCopter's proximity library (PRX1_TYPE 2) while a pilot flies LOITER at "
            "the wall; then the service stops"
        ),
    )  # fmt: skip
    p.add_argument("--cp-dist", type=float, default=2.0, metavar="M", help="--scenario collision-prevention: CP_DIST, metres (default 2)")
    p.add_argument("--seed", type=int, default=0, help="--course: the course seed (default 0)")
    p.add_argument("--config", type=Path, help="TOML config of the service (default: built-in defaults)")
    p.add_argument("--autopilot", choices=["px4", "ardupilot"], default="px4", help="which SITL flies (default px4)")
    p.add_argument(
        "--instance", type=int, default=0,
        help="SITL instance number (PX4: ports 14540+N, system id N+1; ArduPilot: TCP 5760+10N and 5762+10N; default 0)",
    )  # fmt: skip
    p.add_argument(
        "--connect", metavar="URL",
        help="the service's vehicle link (default PX4's API link udpin://127.0.0.1:14540+N; ArduPilot's SERIAL1 tcpout://127.0.0.1:5762+10N)",
    )  # fmt: skip
    p.add_argument(
        "--pilot", metavar="URL",
        help="the ground station's link (default PX4's GCS link udpin://127.0.0.1:14550; ArduPilot's SERIAL0 tcpout://127.0.0.1:5760+10N)",
    )  # fmt: skip
    p.add_argument("--px4-build", type=Path, metavar="DIR", help="PX4 build folder (build/px4_sitl_default): start PX4 fresh for every course")
    p.add_argument(
        "--ardupilot-build", type=Path, metavar="DIR",
        help="ArduPilot checkout with build/sitl/bin/arducopter: start ArduCopter SITL fresh for every course",
    )  # fmt: skip
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="--course: draw the flight")
    p.add_argument("--plot-dir", type=Path, metavar="DIR", help="--suite: draw every flight into this folder")
    p.add_argument("--workdir", type=Path, metavar="DIR", help="keep PX4's and the service's files and logs here (default: a temporary folder)")
    p.add_argument("--service-log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"], help="the service's log level")
    p.set_defaults(func=run)


def describe_sitl(flight: Any) -> list[str]:
    """The lines printed for one SITL flight."""
    from companion.cli.sim import describe_flight

    r = flight.result
    lines = [line for line in describe_flight(r) if not line.startswith(("time:", "frames:"))]
    d = r.decisions
    total = max(1, sum(d.values()))
    modes = ", ".join(f"{m} at {t:.1f} s" for t, m in flight.px4_modes) or "none"
    lines += [
        f"time:          {r.time_s:.1f} s from offboard (OFFBOARD, GUIDED) to the verdict (real time, the autopilot in the loop)",
        f"frames:        {r.frames} processed; the setpoint came from clear {100 * d.get('clear', 0) / total:.0f} %, "
        f"avoid {100 * d.get('avoid', 0) / total:.0f} %, brake {100 * d.get('brake', 0) / total:.0f} % of the time",
        f"engage:        offboard (OFFBOARD, GUIDED) {flight.engage_s:.2f} s after the request; max speed {flight.max_speed_m_s:.2f} m/s",
        f"modes:         {modes}",
        f"service exit:  {flight.service_exit_code}",
    ]
    return lines


def run(args: argparse.Namespace) -> int:
    from companion.cli.sim import _check_plot_path, write_plot
    from companion.config import load_config
    from companion.core.rig_check import check_rig_config
    from companion.sim.courses import make_course
    from companion.sim.suite import suite_courses, suite_table
    from companion.sitl.ardupilot import ArduPilotPorts, find_ardupilot_build
    from companion.sitl.flight import fly_courses
    from companion.sitl.px4 import Px4Ports, find_px4_build

    if not 0 <= args.instance <= 9:
        raise InputError(f"--instance must be 0..9, got {args.instance}")
    ardupilot = args.autopilot == "ardupilot"
    if (args.px4_build is not None and ardupilot) or (args.ardupilot_build is not None and not ardupilot):
        raise InputError("--px4-build goes with --autopilot px4, --ardupilot-build with --autopilot ardupilot")
    cfg = load_config(args.config)
    check_rig_config(cfg, str(args.config or "config"))  # the service it starts checks it too: say it now
    if args.scenario is not None:
        return _run_scenario(args, cfg)
    if args.course is not None:
        if args.plot_dir is not None:
            raise InputError("--plot-dir goes with --suite; use --plot with --course")
        courses = [make_course(args.course, args.seed)]
    else:
        if args.plot is not None:
            raise InputError("--plot goes with --course; use --plot-dir with --suite")
        courses = [make_course(kind, seed) for kind, seed in suite_courses(args.suite)]
    plot_path = _check_plot_path(args.plot) if args.plot is not None else None
    if args.plot_dir is not None:
        args.plot_dir.mkdir(parents=True, exist_ok=True)
    px4_build = ardupilot_build = None
    if ardupilot:
        ardupilot_build = find_ardupilot_build(args.ardupilot_build)
        ports: Any = ArduPilotPorts(args.instance)
        where = f"started from {ardupilot_build.root}" if ardupilot_build else "already running"
    else:
        px4_build = find_px4_build(args.px4_build)
        ports = Px4Ports(args.instance)
        where = f"started from {px4_build}" if px4_build else "already running"
    pilot_url = args.pilot or ports.pilot_url
    workdir = args.workdir.expanduser().resolve() if args.workdir is not None else None
    print(f"{'ArduPilot' if ardupilot else 'PX4'} SITL: {where}, instance {args.instance}; "
          f"service link {args.connect or ports.service_url}, pilot link {pilot_url}", flush=True)

    def progress(done: int, total: int, flight: Any) -> None:
        if total > 1:
            print(f"[{done:2d}/{total}] {flight.result.summary()}", flush=True)
            if args.plot_dir is not None:
                write_plot(flight.result, args.plot_dir / f"{flight.result.course.name}.png", side_view=True)

    t0 = time.perf_counter()
    flights = asyncio.run(
        fly_courses(
            courses, cfg, ports=ports, pilot_url=pilot_url, workdir=workdir, px4_build=px4_build, ardupilot_build=ardupilot_build,
            progress=progress, service_log_level=args.service_log_level, service_url=args.connect,
        )
    )
    if len(flights) == 1:
        for line in describe_sitl(flights[0]):
            print(line)
        if plot_path is not None:
            write_plot(flights[0].result, plot_path, side_view=True)
            print(f"plot:          {plot_path}")
        return 0 if flights[0].result.success else 1
    results = [f.result for f in flights]
    print()
    print(suite_table(results))
    print(f"\n{len(results)} flights with {'ArduPilot' if ardupilot else 'PX4'} in the loop in {time.perf_counter() - t0:.0f} s")
    return 0 if all(r.success for r in results) else 1


def _run_scenario(args: argparse.Namespace, cfg: Any) -> int:
    """``--scenario``: one of the ground-station scenarios against PX4 or ArduPilot SITL; prints what it measured."""
    import tempfile

    from companion.sitl.ardupilot import ArduPilotPorts, find_ardupilot_build
    from companion.sitl.px4 import Px4Ports, find_px4_build
    from companion.sitl.scenarios import run_scenario

    ardupilot = args.scenario == "proximity"
    if ardupilot != (args.autopilot == "ardupilot"):
        raise InputError(
            "--scenario proximity flies ArduPilot (--autopilot ardupilot); collision-prevention and rc-engage fly PX4"
        )
    kw: dict[str, Any] = {}
    px4_build = None
    if ardupilot:
        ports: Any = ArduPilotPorts(args.instance)
        kw["ardupilot_build"] = find_ardupilot_build(args.ardupilot_build)
        kw["seed"] = args.seed
    else:
        ports = Px4Ports(args.instance)
        px4_build = find_px4_build(args.px4_build)
    if args.scenario == "collision-prevention":
        kw["cp_dist_m"] = args.cp_dist
        kw["seed"] = args.seed
    with tempfile.TemporaryDirectory(prefix="companion-sitl-") as tmp:
        workdir = args.workdir.expanduser().resolve() if args.workdir is not None else Path(tmp)
        result = asyncio.run(
            run_scenario(
                args.scenario, cfg, ports=ports, pilot_url=args.pilot or ports.pilot_url, workdir=workdir,
                px4_build=px4_build, service_log_level=args.service_log_level, **kw,
            )
        )
    for line in result.lines():
        print(line)
    print("passed" if result.passed else "FAILED")
    return 0 if result.passed else 1
