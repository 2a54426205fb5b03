"""``companion view`` (the live web page of a running service) and ``companion review`` (a report from a
recorded flight). Heavy imports (aiohttp, ZeroMQ, OpenCV) happen inside the command functions."""

from __future__ import annotations

import argparse
import os
import secrets
import sys
from pathlib import Path

from companion import exitcodes
from companion.errors import InputError

TOKEN_ENV = "COMPANION_VIEW_TOKEN"


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``view`` and ``review``."""
    p = sub.add_parser(
        "view",
        help="serve a live web page of the running service (preview, regions, decisions, engage/disengage)",
        description=(
            "A web page that shows what the drone sees: the live preview (the 9 regions, their depths, the "
            "command arrow and the disparity map), the state and its reason, the region depths against the "
            "near/far thresholds, yaw/pitch and the setpoint, the last 60 s of decisions, fps, latency and "
            "dropped frames, and engage/pause/resume/disengage buttons that speak the control protocol "
            "(with the permissions `companion ctl` has). A process of its own: it crashing or hanging "
            "never affects the service. Bound to 127.0.0.1 unless --host says otherwise. Commanding needs "
            f"the view's token (--token-file, a file of mode 600 or 640, or ${TOKEN_ENV}; made up when "
            "neither is given), shown only in the printed address; on any other address than loopback, "
            "watching needs it too."
        ),
    )
    p.add_argument("--config", type=Path, help="read the endpoints (and nothing else) from this config")
    p.add_argument("--health-endpoint", help="the service's health socket (default: from --config, else the running service's socket in /run/companion or $XDG_RUNTIME_DIR/companion)")
    p.add_argument("--preview-endpoint", help="the service's preview socket (default: from --config, else the running service's socket in /run/companion or $XDG_RUNTIME_DIR/companion)")
    p.add_argument("--control-endpoint", help="the service's control socket (default: from --config, else the running service's socket in /run/companion or $XDG_RUNTIME_DIR/companion)")
    p.add_argument("--no-control", action="store_true", help="read-only: no buttons, no control socket")
    p.add_argument("--server-key", type=Path, help="CURVE: the server's public certificate (.key)")
    p.add_argument("--client-key", type=Path, help="CURVE: your secret certificate (.key_secret)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1; 0.0.0.0 = every interface, e.g. the companion's Wi-Fi)")
    p.add_argument("--port", type=int, default=8080, help="TCP port (default 8080; 0 = any free one)")
    p.add_argument("--token-file", type=Path, help=f"a file (mode 600 or 640) holding the access token (else ${TOKEN_ENV}, else one is made up)")
    p.add_argument("--title", default="companion", help="the page's title (e.g. the vehicle's name)")
    p.add_argument(
        "--until-input-closes", action="store_true",
        help="stop when standard input closes: a parent that holds it open (companion sim --view) takes the page "
        "down with it however it ends",
    )
    p.set_defaults(func=_view)

    p = sub.add_parser(
        "review",
        help="write an HTML report of a recorded flight (health.jsonl, plus preview frames when recorded)",
        description=(
            "Read a recorded health stream (a `companion sitl --workdir` folder, one of its flights, or a "
            "run folder the service recorded with view.record_dir) and write one self-contained HTML file: "
            "what happened (states, decisions, errors), plots of the decisions and region depths over "
            "time, the setpoints against the vehicle's velocity, frame age and latency, the path from "
            "above when the position is known, and a contact sheet of the brake and avoid moments (the "
            "recorded preview frames, or the region depths drawn from the health messages)."
        ),
    )
    p.add_argument("run", type=Path, metavar="RUN", help="a folder with health.jsonl (or folders of them), or a health.jsonl file")
    p.add_argument("--out", type=Path, help="the HTML file to write (default RUN/review.html)")
    p.add_argument("--max-moments", type=int, default=24, help="most brake/avoid moments in the contact sheet (default 24)")
    p.set_defaults(func=_review)


def _endpoints(args: argparse.Namespace) -> tuple[str, str | None, str | None]:
    """(health, preview, control) endpoints: the flags, else the --config file's ([bus] and [view] only;
    the rest may be invalid), else the running service's sockets (:func:`~companion.service.runtime.find_socket`)."""
    from companion.service.runtime import expected_socket, validate_endpoint

    health = preview = control = "auto"
    if args.config is not None:
        from companion.config import load_bus_config, load_view_config

        bus, view = load_bus_config(args.config), load_view_config(args.config)
        health, control = bus.health_endpoint, bus.control_endpoint
        preview = view.preview_endpoint if view.preview_enabled else None

    def local(endpoint: str | None, which: str, given: str | None, wanted: bool = True) -> str | None:
        if given:
            return validate_endpoint(given, f"--{which}-endpoint")
        if endpoint is None or not wanted:
            return None
        if endpoint == "auto":
            return expected_socket(which)  # the view may start before the service
        if endpoint.startswith("tcp://") and ("://*:" in endpoint or "0.0.0.0" in endpoint):
            return endpoint.replace("*", "127.0.0.1").replace("0.0.0.0", "127.0.0.1")
        return endpoint

    return (
        local(health, "health", args.health_endpoint),
        local(preview, "preview", args.preview_endpoint),
        local(control, "control", args.control_endpoint, wanted=not args.no_control),
    )


def _service_there(endpoint: str) -> bool:
    """False when ``endpoint`` is a socket file that does not exist or that no service listens on
    (other endpoints: True; ZeroMQ cannot tell before a message arrives)."""
    from companion.errors import ConfigError
    from companion.service.runtime import check_listening, socket_path

    path = socket_path(endpoint)
    if path is None:
        return True
    if not path.exists():
        return False
    try:
        check_listening(endpoint)
    except ConfigError:
        return False
    return True


def read_token(token_file: Path | None) -> str | None:
    """The token from ``token_file`` (first line), else ``$COMPANION_VIEW_TOKEN``, else None.

    Raises:
        InputError: the file cannot be read or is empty.
    """
    if token_file is not None:
        try:
            mode = token_file.stat().st_mode
            token = token_file.read_text(encoding="utf-8").strip().splitlines()
        except OSError as err:
            raise InputError(f"--token-file {token_file}: cannot read it: {err.strerror or err}") from None
        except UnicodeDecodeError as err:
            raise InputError(f"--token-file {token_file}: not UTF-8 text (byte {err.start})") from None
        if mode & 0o007:
            raise InputError(
                f"--token-file {token_file}: every local user may read it (mode {mode & 0o777:o}): "
                f"chmod 600 {token_file} (or 640 with the service's group)"
            )
        if not token or not token[0].strip():
            raise InputError(f"--token-file {token_file}: is empty")
        return token[0].strip()
    return os.environ.get(TOKEN_ENV) or None


def _view(args: argparse.Namespace) -> int:
    import asyncio
    import signal

    from companion.service.client import curve_client_options
    from companion.view.options import ViewOptions, is_loopback_host
    from companion.view.server import serve

    token = read_token(args.token_file)
    health, preview, control = _endpoints(args)
    made_up = False
    if token is None and (control is not None or not is_loopback_host(args.host)):
        # Commanding needs it on loopback too: another local user can reach the port, not this terminal.
        token, made_up = secrets.token_urlsafe(24), True
    options = ViewOptions(
        health_endpoint=health,
        preview_endpoint=preview,
        control_endpoint=control,
        curve=curve_client_options(args.server_key, args.client_key),
        host=args.host,
        port=args.port,
        token=token,
        title=args.title,
        say=lambda line: print(f"companion view: {line}", flush=True),
    )

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        if args.until_input_closes:
            if sys.stdin is None:
                raise InputError("--until-input-closes: this process has no standard input")
            fd = sys.stdin.fileno()

            def readable() -> None:
                if not os.read(fd, 4096):  # end of input: the parent is gone (killed too)
                    loop.remove_reader(fd)
                    stop.set()

            loop.add_reader(fd, readable)

        def ready(server: object) -> None:
            urls = getattr(server, "urls")
            print(f"companion view: following {health}" + (f" and {preview}" if preview else "")
                  + ("" if control else " (read-only)"), flush=True)
            # Before the URL, so a reader that stops at the URL has seen what the token in it is.
            if made_up:
                print(f"companion view: the token was made up for this run (set ${TOKEN_ENV} or --token-file to keep one)", flush=True)
            for url in urls:
                print(f"companion view: open {url}", flush=True)
            if not _service_there(health):
                print(f"companion view: no running service at {health} yet: the page says so, and follows it once it starts",
                      flush=True)

        await serve(options, ready=ready, stop=stop)

    asyncio.run(main())
    return exitcodes.OK


def _review(args: argparse.Namespace) -> int:
    from companion.view.review import write_review

    if args.max_moments < 0:
        raise InputError("--max-moments must be >= 0")
    out = write_review(args.run, args.out, max_moments=args.max_moments)
    print(f"companion review: wrote {out}")
    sys.stdout.flush()
    return exitcodes.OK
