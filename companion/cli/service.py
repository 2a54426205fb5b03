"""Sub-commands of the service: ``run``, ``ctl``, ``watch``, ``record``, ``install-service``.

Heavy imports (asyncio daemon, MAVSDK, ZeroMQ, OpenCV) happen inside the command functions.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from companion import exitcodes
from companion.errors import InputError



def register(sub: argparse._SubParsersAction) -> None:
    """Add this module's sub-commands to ``sub``."""
    p = sub.add_parser(
        "run",
        help="run the avoidance service (camera -> pipeline -> MAVSDK offboard), as systemd starts it",
        description=(
            "Run the service in the foreground: capture, process, stream setpoints, serve the ZeroMQ "
            "control plane. It starts passive and engages on an 'engage' request. SIGTERM/SIGINT: clean "
            f"shutdown (a second one forces the exit, code {exitcodes.FORCED_EXIT}); SIGHUP: reload the "
            f"config. Exit code {exitcodes.STARTUP_FAILURE}: it could not start (bad config, no camera)."
        ),
    )
    p.add_argument("--config", type=Path, help="TOML config (default: built-in defaults; the unit passes /etc/companion/companion.toml)")
    p.set_defaults(func=_run)

    p = sub.add_parser(
        "ctl",
        help="send one request to a running service (status, get, set, reload, engage, ...)",
        description="Send one request to the service's control socket and print the reply as JSON.",
    )
    _endpoint_options(p, control=True)
    csub = p.add_subparsers(dest="ctl_command", metavar="REQUEST", required=True)
    for name, text in (
        ("status", "the current health message"),
        ("ping", "is it alive?"),
        ("reload", "re-read the config file (as SIGHUP)"),
        ("disengage", "leave offboard to Hold and stop commanding"),
        ("pause", "hover in offboard until resume"),
        ("resume", "back to automatic (ends a pause or an override)"),
    ):
        csub.add_parser(name, help=text)
    for name, text in (
        ("engage", "enter offboard and start avoiding (toward a goal, if given)"),
        ("goto", "while engaged: a new goal from where the vehicle is now"),
    ):
        e = csub.add_parser(name, help=text)
        e.add_argument("--north", type=float, metavar="M", help="goal point: north, local NED metres (with --east)")
        e.add_argument("--east", type=float, metavar="M", help="goal point: east, local NED metres (with --north)")
        e.add_argument("--bearing", type=float, metavar="DEG", help="goal: degrees clockwise from north (with --distance)")
        e.add_argument("--distance", type=float, metavar="M", help="goal: metres along --bearing")
        e.add_argument("--from-heading", action="store_true", help="--bearing is from the vehicle's heading")
        e.add_argument("--course", action="store_true", help="goal: the heading and line at engagement (the default)")
    g = csub.add_parser("get", help="the config in force (or one section)")
    g.add_argument("section", nargs="?", help="e.g. controller, command")
    s = csub.add_parser("set", help="change config fields live: KEY=VALUE ...")
    s.add_argument("assignments", nargs="+", metavar="KEY=VALUE", help="e.g. planner.cruise_speed_m_s=1.5")
    o = csub.add_parser("override", help="fly manual values for a bounded time, then automatic again")
    o.add_argument("--yaw", type=float, default=0.0, help="-1 (hard left) .. 1 (hard right); default 0")
    o.add_argument("--pitch", type=float, default=0.0, help="-1 (down) .. 1 (up); default 0")
    o.add_argument("--speed", type=float, default=0.0, help="forward speed as a share of the cruise speed, 0..1; default 0")
    o.add_argument("--duration", type=float, required=True, help="seconds (at most service.override_max_duration_s)")
    p.set_defaults(func=_ctl)

    p = sub.add_parser(
        "watch",
        help="show the live health of a running service in the terminal",
        description="Subscribe to the health messages and show them (state, fps, latency, regions, setpoint, links).",
    )
    _endpoint_options(p, control=False)
    p.add_argument("--json", action="store_true", help="print each message as one JSON line instead")
    p.add_argument("--verbose", action="store_true", help="also the controller's reason (rules, memberships)")
    p.add_argument("--count", type=int, default=0, help="exit after this many messages (default: run until Ctrl-C)")
    p.add_argument("--timeout-s", type=float, default=5.0, help="give up when no message comes for this long (default 5)")
    p.set_defaults(func=_watch)

    p = sub.add_parser(
        "record",
        help="record what a camera source sees, for `replay`",
        description=(
            "Record frames from the configured camera source (or the one given with --source) to a folder "
            "of PNGs or a lossless .mkv (FFV1), with the capture timestamps beside it; the replay source "
            "plays it back at the recorded rate."
        ),
    )
    p.add_argument("--config", type=Path, help="TOML config: its [camera] section is the source")
    p.add_argument("--source", choices=["sim", "uvc", "replay"], help="override camera.source")
    p.add_argument("--out", type=Path, required=True, help="a new folder, or a .mkv/.avi file")
    lim = p.add_mutually_exclusive_group(required=True)
    lim.add_argument("--frames", type=int, help="stop after this many frames")
    lim.add_argument("--duration-s", type=float, help="stop after this many seconds")
    p.set_defaults(func=_record)

    p = sub.add_parser(
        "install-service",
        help="install the systemd unit, the default config and the 'companion' user",
        description=(
            "Write /etc/systemd/system/companion.service (ExecStart: this Python with -m companion), "
            "/etc/companion/companion.toml (the documented defaults, kept if present) and create the "
            "'companion' system user in the groups video and dialout. Needs root, unless --root. "
            "Without --yes it only prints the plan and changes nothing."
        ),
    )
    p.add_argument("--root", type=Path, default=Path("/"), help="install under this folder instead of / (tests, images)")
    p.add_argument("--dry-run", action="store_true", help="only print what would be done (the default without --yes)")
    p.add_argument("--yes", action="store_true", help="do it: write the files and create the user (without it: the plan only)")
    p.add_argument("--exec-start", help="the unit's ExecStart command line (default: this interpreter -m companion run ...)")
    p.add_argument("--no-user", action="store_true", help="do not create the system user")
    p.add_argument("--force-config", action="store_true", help="replace an existing /etc/companion/companion.toml")
    p.set_defaults(func=_install)


def _endpoint_options(p: argparse.ArgumentParser, control: bool) -> None:
    p.add_argument(
        "--config",
        type=Path,
        help="read the endpoint from this config's [bus] table (the rest of the file may be invalid)",
    )
    p.add_argument(
        "--endpoint",
        help=(
            "ZeroMQ endpoint (default: from --config, else the running service's socket in /run/companion, "
            "$XDG_RUNTIME_DIR/companion or /tmp/companion-<uid>)"
        ),
    )
    if control:
        p.add_argument("--timeout-s", type=float, default=3.0, help="reply timeout, seconds (default 3)")
    p.add_argument("--server-key", type=Path, help="CURVE: the server's public certificate (.key)")
    p.add_argument("--client-key", type=Path, help="CURVE: your secret certificate (.key_secret)")


def _endpoint(args: argparse.Namespace, control: bool) -> str:
    from companion.config.service import AUTO_ENDPOINT
    from companion.service.runtime import find_socket, validate_endpoint, validate_timeout

    which = "control" if control else "health"
    validate_timeout(args.timeout_s)
    if args.endpoint:
        return validate_endpoint(args.endpoint, "--endpoint")
    if args.config is not None:
        from companion.config import load_bus_config

        bus = load_bus_config(args.config)
        endpoint = bus.control_endpoint if control else bus.health_endpoint
        if endpoint == AUTO_ENDPOINT:
            return find_socket(which)
        if endpoint.startswith("tcp://") and ("://*:" in endpoint or "0.0.0.0" in endpoint):
            endpoint = endpoint.replace("*", "127.0.0.1").replace("0.0.0.0", "127.0.0.1")
        return endpoint
    return find_socket(which)


def _run(args: argparse.Namespace) -> int:
    from companion.service.daemon import run_service

    return run_service(args.config)


def _ctl(args: argparse.Namespace) -> int:
    from companion.service.client import ControlClient, curve_client_options, parse_assignments

    request: dict[str, Any]
    c = args.ctl_command
    if c == "get":
        request = {"cmd": "get_config", "section": args.section}
    elif c == "set":
        request = {"cmd": "set_config", "patch": parse_assignments(args.assignments)}
    elif c == "override":
        request = {"cmd": "override", "yaw": args.yaw, "pitch": args.pitch, "speed": args.speed, "duration_s": args.duration}
    elif c in ("engage", "goto"):
        request = {"cmd": c}
        goal = _goal_of(args)
        if isinstance(goal, str):
            print(f"companion ctl {c}: {goal}", file=sys.stderr)
            return exitcodes.BAD_INPUT
        if goal is not None:
            request["goal"] = goal
    else:
        request = {"cmd": c}
    curve = curve_client_options(args.server_key, args.client_key)
    with ControlClient(_endpoint(args, control=True), timeout_s=args.timeout_s, curve=curve) as client:
        reply = client.call(request)
    if reply.get("ok"):
        print(json.dumps(reply.get("result"), indent=2))
        return exitcodes.OK
    from companion.core.words import error_words

    err = reply.get("error") or {}
    message = str(err.get("message", reply))
    # the pilot's words; the error's type (ConfigError, ProtocolError...) only with --log-level DEBUG
    kind = f"{err.get('type', 'error')}: " if args.log_level == "DEBUG" else ""
    print(f"companion ctl {c}: {kind}{error_words(message)}", file=sys.stderr)
    return exitcodes.INTERNAL_ERROR if err.get("type") == "InternalError" else exitcodes.BAD_INPUT


def _goal_of(args: argparse.Namespace) -> dict[str, Any] | str | None:
    """The ``goal`` of ``ctl engage``/``goto`` from its options (None: none given; a str: what is wrong)."""
    point = args.north is not None or args.east is not None
    bearing = args.bearing is not None or args.distance is not None
    if sum((point, bearing, args.course)) > 1:
        return "give one goal: --north/--east, --bearing/--distance, or --course"
    if point:
        if args.north is None or args.east is None:
            return "a goal point needs both --north and --east"
        return {"kind": "point", "north_m": args.north, "east_m": args.east}
    if bearing:
        if args.bearing is None or args.distance is None:
            return "a goal bearing needs both --bearing and --distance"
        return {"kind": "bearing", "bearing_deg": args.bearing, "distance_m": args.distance, "from_heading": args.from_heading}
    if args.course:
        return {"kind": "course"}
    if args.ctl_command == "goto":
        return "goto needs a goal: --north/--east, --bearing/--distance, or --course"
    return None


def _watch(args: argparse.Namespace) -> int:
    import zmq

    from companion.service.client import ClientError, check_ipc_access, curve_client_options, render_health

    curve = curve_client_options(args.server_key, args.client_key)
    endpoint = _endpoint(args, control=False)
    check_ipc_access(endpoint)
    ctx = zmq.Context()
    seen = 0
    interactive = sys.stdout.isatty() and not args.json
    try:
        sock = ctx.socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        for name, value in (curve or {}).items():
            setattr(sock, name, value)
        sock.setsockopt(zmq.SUBSCRIBE, b"")
        try:
            sock.connect(endpoint)
        except zmq.ZMQError as err:
            raise ClientError(f"cannot connect to {endpoint}: {err}") from None
        while args.count <= 0 or seen < args.count:
            if not sock.poll(int(args.timeout_s * 1000)):
                raise ClientError(f"no health message from {endpoint} within {args.timeout_s:g} s: no running service there?")
            message = json.loads(sock.recv())
            seen += 1
            if args.json:
                print(json.dumps(message), flush=True)
            else:
                screen = render_health(message, verbose=args.verbose)
                # Clear the screen on a terminal; separate the screens with a blank line otherwise.
                print(("\x1b[H\x1b[2J" if interactive else "\n") + screen, flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        ctx.destroy(linger=0)
    return exitcodes.OK


def _record(args: argparse.Namespace) -> int:
    from companion.config import load_config
    from companion.core.stereo import to_bgr
    from companion.service.camera import make_camera
    from companion.service.recording import RecordingWriter

    cfg = load_config(args.config)
    if args.source:
        cfg = cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"source": args.source})})
        from companion.config import parse_config

        cfg = parse_config(cfg.model_dump(mode="python"), source="--source")  # re-validate the camera section
    if args.config is not None and cfg.camera.replay_path is not None and not cfg.camera.replay_path.is_absolute():
        cfg = cfg.model_copy(
            update={"camera": cfg.camera.model_copy(update={"replay_path": args.config.parent / cfg.camera.replay_path})}
        )
    if (args.frames is not None and args.frames < 1) or (args.duration_s is not None and args.duration_s <= 0):
        raise InputError("--frames must be >= 1 and --duration-s > 0")
    # Recording comes before calibrating: a camera without a calibration file records all the same.
    camera = make_camera(cfg, require_calibration=False)
    camera.open()
    t_end = None if args.duration_s is None else time.monotonic() + args.duration_s
    try:
        with RecordingWriter(args.out, cfg.camera.fps_hz) as writer:
            while True:
                if args.frames is not None and writer.frames >= args.frames:
                    break
                if t_end is not None and time.monotonic() >= t_end:
                    break
                frame = camera.read()
                # a recording is for people and for replay: BGR (a YUYV camera's frame decoded)
                writer.write(to_bgr(frame.image), frame.timestamp_s, frame.seq)
            n = writer.frames
    finally:
        camera.close()
    print(f"recorded {n} frames from {camera.name} to {args.out}")
    return exitcodes.OK


def _install(args: argparse.Namespace) -> int:
    from companion.service.install import install_service

    dry_run = args.dry_run or not args.yes
    steps = install_service(
        args.root,
        exec_start=args.exec_start,
        dry_run=dry_run,
        create_user=not args.no_user,
        force_config=args.force_config,
    )
    if dry_run and not args.dry_run:
        print(f"companion install-service: the plan (under {args.root}):")
    for step in steps:
        would = dry_run and step.what.startswith(("write ", "run "))
        print(("would " if would else "") + step.what)
    if dry_run and not args.dry_run:
        # Writing /etc and creating a user deserve a deliberate "yes": a user ran it as root by accident.
        print("nothing was changed: run it again with --yes to do this", file=sys.stderr)
        return exitcodes.BAD_INPUT
    return exitcodes.OK
