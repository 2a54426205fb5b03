"""The commands in README.md and docs/*.md do what the docs say: the runnable ones run, the others parse.

The convention, for every fenced ``bash`` block of README.md and docs/*.md:

* ``bash run``: needs no hardware; this test runs the block (``bash -euo pipefail``) in a scratch folder
  holding a copy of the repository's ``samples/`` and ``config/`` (so ``samples/frame.jpg`` is there),
  with ``companion`` being this checkout. docs/first-flight.md's run blocks depend on each other and
  run in order in ``tests/test_first_flight_doc.py``.
* any other ``bash`` block (untagged, ``hardware``, ``sitl``, ``ci``): needs a camera, a vehicle, a
  running service, PX4 or root; every ``companion`` command line in it must parse.

The samples are small files the repository ships (each under 200 kB; ``tools/gen-samples.py`` renders
them with the project's own renderer); a test here keeps them small and readable.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from companion.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
#: Pages with commands (history.md is a record, not instructions).
DOCS = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").glob("*.md") if p.name != "history.md")]
SAMPLES = ROOT / "samples"
MAX_SAMPLE_BYTES = 200_000


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


def _run_blocks() -> list[tuple[str, str]]:
    return [
        (f"{path.relative_to(ROOT)}#{i}", body)
        for path in DOCS
        if path.name != "first-flight.md"
        for i, (lang, tag, body) in enumerate(blocks(path))
        if lang == "bash" and tag == "run"
    ]


def test_every_companion_command_in_the_docs_parses() -> None:
    parser = build_parser()
    parsed, bad = 0, []
    for path in DOCS:
        for lang, _tag, body in blocks(path):
            if lang != "bash":
                continue
            for command in commands(body):
                argv = companion_argv(command)
                if argv is None:
                    continue
                try:
                    parser.parse_args(argv)
                    parsed += 1
                except SystemExit:
                    bad.append(f"{path.relative_to(ROOT)}: `{command}`")
    assert not bad, "commands that do not parse:\n" + "\n".join(bad)
    assert parsed >= 40


def test_the_readme_s_try_it_runs_on_the_samples_and_says_which_blocks_need_hardware() -> None:
    tags = [(lang, tag) for lang, tag, _ in blocks(ROOT / "README.md")]
    assert ("bash", "run") in tags and ("bash", "hardware") in tags
    runnable = " ".join(body for _, tag, body in blocks(ROOT / "README.md") if tag == "run")
    assert "samples/frame.jpg" in runnable and "companion demo" in runnable


def test_the_samples_are_small_and_complete() -> None:
    files = [p for p in SAMPLES.rglob("*") if p.is_file()]
    assert {"frame.jpg", "frame-calib.yaml", "distances.csv"} <= {p.name for p in files}
    assert len(list((SAMPLES / "calib_views").iterdir())) >= 10 and len(list((SAMPLES / "lut_captures").iterdir())) >= 5
    heavy = [(p.name, p.stat().st_size) for p in files if p.stat().st_size > MAX_SAMPLE_BYTES]
    assert not heavy, heavy


def _shim(folder: Path) -> dict[str, str]:
    """An environment whose ``companion`` is this interpreter on this checkout."""
    bin_dir = folder / ".bin"
    bin_dir.mkdir()
    shim = bin_dir / "companion"
    shim.write_text(f"#!/bin/sh\nexec {shlex.quote(sys.executable)} -m companion \"$@\"\n")
    shim.chmod(shim.stat().st_mode | stat.S_IXUSR)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


@pytest.mark.parametrize("where, body", _run_blocks(), ids=[w for w, _ in _run_blocks()])
def test_a_run_block_runs(where: str, body: str, tmp_path: Path) -> None:
    shutil.copytree(SAMPLES, tmp_path / "samples")
    shutil.copytree(ROOT / "config", tmp_path / "config")
    proc = subprocess.run(["bash", "-euo", "pipefail", "-c", body], cwd=tmp_path, env=_shim(tmp_path),
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"{where}\n```bash run\n{body}```\nexit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
