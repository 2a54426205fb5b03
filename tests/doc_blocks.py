"""Fenced blocks of the docs and the commands in them, for the tests that run or parse them."""

from __future__ import annotations

import re
import shlex
from pathlib import Path


def blocks(path: Path) -> list[tuple[str, str, str]]:
    """(language, tag, body) of every fenced block of ``path``, in order."""
    text = path.read_text(encoding="utf-8")
    return [
        (m.group(1), m.group(2), m.group(3))
        for m in re.finditer(r"^```(\w*)[ \t]*(\w*)[ \t]*\n(.*?)^```[ \t]*$", text, re.M | re.S)
    ]


def commands(body: str) -> list[str]:
    """The shell commands of a block: continuation lines joined, here-documents and comments dropped,
    ``&&`` chains split."""
    lines, skip_until = [], None
    for line in body.replace("\\\n", " ").splitlines():
        if skip_until is not None:
            if line.strip() == skip_until:
                skip_until = None
            continue
        here = re.search(r"<<\s*'?(\w+)'?", line)
        if here:
            skip_until = here.group(1)
        line = line.split(" #")[0].strip()
        if line and not line.startswith("#"):
            lines.append(line)
    return [part.strip() for line in lines for part in line.split("&&") if part.strip()]


def companion_argv(command: str) -> list[str] | None:
    """The arguments of a ``companion`` command line (after ``sudo``, a venv path), else None."""
    try:
        argv = shlex.split(command)
    except ValueError:
        return None
    if argv and argv[0] == "sudo":
        argv = argv[1:]
    if not argv or Path(argv[0]).name != "companion":
        return None
    for i, word in enumerate(argv):  # the shell's redirections and pipes are not the command's
        if word in (">", ">>", "<", "|", "2>&1") or word.startswith((">", "2>")):
            return argv[1:i]
    return argv[1:]


def companion_commands(body: str) -> list[tuple[str, list[str]]]:
    """``(command, arguments)`` of every ``companion`` command in a block's body (:func:`commands`)."""
    found = []
    for command in commands(body):
        argv = companion_argv(command)
        if argv is not None:
            found.append((command, argv))
    return found
