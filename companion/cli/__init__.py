"""The ``companion`` command line: one sub-command per module, each with a ``register(subparsers)``.

Sub-command modules import their heavy dependencies (OpenCV, CuPy, MAVSDK, ZeroMQ) inside the command
function, so ``companion --help`` and light commands start fast. A :class:`~companion.errors.CompanionError`
becomes one line on stderr and exit code 2, and so does an OSError (a file, socket or device given); any
other exception is a bug: one line and exit code 1, its traceback only with ``--log-level DEBUG``.
Nothing a user typed produces a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from companion import __version__, exitcodes
from companion.errors import CompanionError

#: Modules under ``companion.cli`` that contribute sub-commands, in help order.
_COMMAND_MODULES = ("demo", "process", "calibrate", "eval", "sim", "tune", "sitl", "bench", "service", "view")

log = logging.getLogger("companion")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion",
        description="Stereo-vision obstacle avoidance for PX4 (ZED -> 9 regions -> fuzzy -> MAVSDK).",
    )
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging threshold (default INFO)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in _COMMAND_MODULES:
        importlib.import_module(f"companion.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``companion`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args) or 0)
    except CompanionError as err:
        print(f"companion {args.command}: error: {err}", file=sys.stderr)
        return exitcodes.BAD_INPUT
    except KeyboardInterrupt:
        return exitcodes.FORCED_EXIT
    except OSError as err:  # a file, a socket or a device the command was given: the user's to fix
        where = f"{err.filename}: " if getattr(err, "filename", None) else ""
        print(f"companion {args.command}: error: {where}{err.strerror or err}", file=sys.stderr)
        return exitcodes.BAD_INPUT
    except Exception as err:  # a bug: one line for the user, the traceback in the log at DEBUG
        log.debug("companion %s failed", args.command, exc_info=True)
        print(
            f"companion {args.command}: internal error: {type(err).__name__}: {err} "
            "(--log-level DEBUG shows where; please report it)",
            file=sys.stderr,
        )
        return exitcodes.INTERNAL_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
