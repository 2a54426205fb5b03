"""Rendered calibration data for the tests: see :mod:`companion.sim.render.samples` (the same code
writes the repository's ``samples/``)."""

from companion.sim.render.samples import (  # noqa: F401
    BOARD,
    LUT_GEOMETRY,
    Rig,
    generic_rig,
    write_calibration,
    write_lut_captures,
    write_rig_lut_captures,
    write_samples,
    write_stereo_views,
)
