#!/usr/bin/env python3
"""Regenerate config/companion.toml from the config models (run after changing a default or a description)."""

from pathlib import Path

from companion.config.document import render_default_toml

target = Path(__file__).resolve().parent.parent / "config" / "companion.toml"
target.write_text(render_default_toml(), encoding="utf-8")
print(f"wrote {target}")
