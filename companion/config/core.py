"""The perception and decision core's config sections, one module per stage (kept as an import path).

calibration → stereo → regions → LUT → fuzzy controller → command: each section's model
lives in its own module (``companion.config.stereo`` and so on). This module re-exports them so that
``from companion.config.core import StereoConfig`` keeps working for users' scripts.

Every field has a type, a default, bounds, its unit in its name and a description. The defaults are
the paper's values where the paper gives one (near 0.75 m, far 2.25 m, a 0.5 m safe window at 1.5 m,
the seven rules, a 45°-rotated corner controller). The knobs the paper leaves open are tuned in the
closed-loop simulator (``companion sim --suite standard``, docs/benchmarks.md): the release filter,
the escape threshold and four side rules. ``config/paper.toml`` restores the paper's controller (no
side rules, constant speed) and lets it dominate the local planner's choice, for comparison.
"""

from __future__ import annotations

from companion.config.calibration import CalibrationConfig
from companion.config.command import CommandConfig
from companion.config.controller import (
    ControllerConfig,
    InputTerm,
    MembershipShape,
    OutputTerm,
    RuleConfig,
)
from companion.config.lut import LutConfig
from companion.config.regions import RegionName, RegionsConfig
from companion.config.stereo import StereoBackend, StereoConfig, StereoMatcher

__all__ = [
    "CalibrationConfig",
    "CommandConfig",
    "ControllerConfig",
    "InputTerm",
    "LutConfig",
    "MembershipShape",
    "OutputTerm",
    "RegionName",
    "RegionsConfig",
    "RuleConfig",
    "StereoBackend",
    "StereoConfig",
    "StereoMatcher",
]
