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
import shlex
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from doc_blocks import blocks, companion_commands

from companion.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
#: Pages with commands.
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SAMPLES = ROOT / "samples"
MAX_SAMPLE_BYTES = 200_000


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
            for command, argv in companion_commands(body):
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
