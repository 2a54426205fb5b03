"""Checks a configuration must pass before it may fly: does it still see a near obstacle as near?

The config's own validation bounds every field; what it cannot see is the controller as a whole. A
look-up table that maps 0.5 m to 5 m, a ``near`` term that starts at 0.2 m, or a rule list without the
brake's rules each pass field by field and still fly a vehicle into a wall. :func:`near_blindness`
runs the configured LUT and controller on two synthetic frames and says what is wrong.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from companion.core.fuzzy.avoidance import AvoidanceController
from companion.core.lut import DepthLUT
from companion.core.types import REGION_INDEX, N_REGIONS, DecisionKind

if TYPE_CHECKING:
    from companion.config import CompanionConfig

#: The depth the other regions read in the "only the centre is near" frame, metres: far by any tuning.
_OPEN_DEPTH_M = 20.0


def near_blindness(cfg: CompanionConfig) -> str | None:
    """None when ``cfg`` sees an obstacle ``cfg.envelope.near_check_depth_m`` away as near; else one line
    saying what it does instead.

    Two frames of computed (pre-LUT) region depths, metres, through the configured LUT and controller:

    * every region at the near depth (a wall filling the view): the decision must be BRAKE;
    * only the centre there, the rest open: the decision must not be CLEAR (it must avoid or brake).
    """
    near_m = cfg.envelope.near_check_depth_m
    lut = DepthLUT(cfg.lut.points_m)
    controller = AvoidanceController(cfg.controller)
    wall = controller.decide(lut.apply(np.full(N_REGIONS, near_m, dtype=np.float64)))
    if wall.kind is not DecisionKind.BRAKE:
        return (
            f"with every region {near_m:g} m away (envelope.near_check_depth_m) this controller and LUT decide "
            f"{wall.kind.value} ({wall.reason}), not brake: it would fly into a wall"
        )
    centre = np.full(N_REGIONS, _OPEN_DEPTH_M, dtype=np.float64)
    centre[REGION_INDEX["center"]] = near_m
    ahead = controller.decide(lut.apply(centre))
    if ahead.kind is DecisionKind.CLEAR:
        return (
            f"with the centre {near_m:g} m away (envelope.near_check_depth_m) and the rest open this "
            f"controller and LUT decide clear ({ahead.reason}): it would fly on into the obstacle"
        )
    return None
