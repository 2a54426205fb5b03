"""``companion demo``: the main job on the embedded default (placeholder until the simulator lands)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``demo``."""
