#!/usr/bin/env python3
"""Regenerate systemd/companion.service from companion/service/install.py (run after changing the unit)."""

from pathlib import Path

from companion.service.install import render_unit

target = Path(__file__).resolve().parent.parent / "systemd" / "companion.service"
target.write_text(render_unit(), encoding="utf-8")
print(f"wrote {target}")
