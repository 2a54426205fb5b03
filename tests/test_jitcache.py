"""The compiled kernels' cache folder: a start after the first loads the planner's kernels from it."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_planner_kernels_are_cached_in_the_folder_the_service_points_at(tmp_path: Path) -> None:
    code = ("from companion.jitcache import use_cache_dir; print(use_cache_dir()); "
            "from companion.core.planner import compile_kernels; compile_kernels()")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == str(tmp_path / "numba")
    cached = {p.name.split(".")[0] for p in (tmp_path / "numba").rglob("*.nbi")}
    assert {"_waykernels", "_mapkernels", "_blockkernels"} <= cached, cached


def test_a_cache_folder_that_cannot_be_written_is_one_warning_and_kernels_in_memory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import numba

    from companion.jitcache import use_cache_dir_or_memory

    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocker / "numba"))
    with caplog.at_level(logging.WARNING):
        assert use_cache_dir_or_memory(logging.getLogger("companion.test")) is None
    assert numba.config.CACHE_DIR == ""
    (line,) = [r.getMessage() for r in caplog.records]
    assert str(blocker / "numba") in line and "NUMBA_CACHE_DIR" in line and "in memory" in line


def test_the_cache_folder_is_never_beside_the_source(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from companion.jitcache import cache_dir

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache_dir() == tmp_path / "companion" / "numba"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "companion" / "numba"
