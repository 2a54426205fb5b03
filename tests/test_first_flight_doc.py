"""docs/first-flight.md: every command in it is run here or by CI, or needs hardware/PX4 and parses.

Fenced blocks are tagged: ``bash run`` blocks run, in order, in one scratch folder that holds a copy of
the repository's ``samples/`` (board views and target captures of a known rig, rendered by
``tools/gen-samples.py``); ``bash sitl`` and ``bash hardware`` blocks need PX4 SITL or the vehicle, and
each ``companion`` command line in them must parse; ``bash ci`` is CI's own line; ``nsh`` is PX4's shell.
"""

from __future__ import annotations

import os
import shlex
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from doc_blocks import blocks, commands, companion_commands

from companion.cli import build_parser
from companion.config import load_config
from companion.core.calibration_files import load_calibration

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "first-flight.md"
TAGS = {("bash", "run"), ("bash", "sitl"), ("bash", "hardware"), ("bash", "ci"), ("nsh", "")}


def test_every_block_is_tagged_and_every_companion_command_parses() -> None:
    found = blocks(DOC)
    assert len(found) >= 12
    untagged = [(lang, tag, body[:40]) for lang, tag, body in found if (lang, tag) not in TAGS]
    assert not untagged, f"blocks without a known tag (bash run|sitl|hardware|ci, nsh): {untagged}"
    parser = build_parser()
    parsed = 0
    for lang, tag, body in found:
        if lang != "bash":
            continue
        for command, argv in companion_commands(body):
            try:
                parser.parse_args(argv)
            except SystemExit:
                pytest.fail(f"docs/first-flight.md ({tag}): `{command}` does not parse")
            parsed += 1
    assert parsed >= 15
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    for _, _, body in (b for b in found if b[1] == "ci"):
        for command in commands(body):
            assert command.split(" install")[0] in ci, command


def test_the_run_blocks_run_in_order(tmp_path: Path) -> None:
    import shutil

    shutil.copytree(ROOT / "samples", tmp_path / "samples")
    # `companion` as this interpreter runs it, however the package was installed.
    bin_dir = tmp_path / ".bin"
    bin_dir.mkdir()
    shim = bin_dir / "companion"
    shim.write_text(f"#!/bin/sh\nexec {shlex.quote(sys.executable)} -m companion \"$@\"\n")
    shim.chmod(shim.stat().st_mode | stat.S_IXUSR)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    ran = 0
    for _lang, tag, body in blocks(DOC):
        if tag != "run":
            continue
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", body], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, f"```bash run\n{body}```\nexit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
        ran += 1
    assert ran >= 5
    assert (tmp_path / "demo" / "flight.png").is_file()
    cfg = load_config(tmp_path / "companion.toml")
    assert cfg.camera.model == "sbs" and cfg.calibration.file == (tmp_path / "calib.yaml").resolve()
    assert load_calibration(cfg.calibration.file, (640, 400)).baseline_m == pytest.approx(0.06, rel=0.005)
    assert len(cfg.lut.points_m) >= 4 and cfg.lut.points_m != [(0.2, 0.2), (40.0, 40.0)]
    for name in ("rectified.png", "check.png", "lut.png"):
        assert (tmp_path / name).stat().st_size > 1000, name
