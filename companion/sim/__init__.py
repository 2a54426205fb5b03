"""Closed-loop simulator: fly the product's pipeline through procedural obstacle courses and score it.

* :mod:`companion.sim.vehicle`: a multicopter following body-frame velocity/yaw-rate setpoints
  (a :class:`~companion.interfaces.VehicleLink`);
* :mod:`companion.sim.camera`: the rendered ZED (a :class:`~companion.interfaces.CameraSource`);
* :mod:`companion.sim.courses`: seeded courses (corridor, doorway, forest, pitch, side, deadend);
* :mod:`companion.sim.loop`: the loop in simulated time and the per-step log;
* :mod:`companion.sim.scoring`: clearance and outcomes; :mod:`companion.sim.suite`: many courses;
* :mod:`companion.sim.plot`: top-down and side-view plots drawn with OpenCV.
"""

from __future__ import annotations

#: Mixed into a realization's draws so that they cannot coincide with a seed's own keys.
_REALIZATION_TAG = 0x5EED


def realization_key(seed: int, realization: int) -> tuple[int, ...]:
    """The key of a flight's random draws (sensor noise, exposure, the eyes' mismatch, drift) for
    course seed ``seed`` and ``sim.realization`` ``realization``: ``(seed,)`` for 0, the draws every
    flight had before realizations existed; else ``(seed, tag, realization)``. Each draw appends its
    own constants to it."""
    if realization == 0:
        return (int(seed),)
    return (int(seed), _REALIZATION_TAG, int(realization))
