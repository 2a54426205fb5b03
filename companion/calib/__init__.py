"""The calibration tools' shell (``companion calibrate stereo`` and ``companion calibrate lut``):
reading view folders, capturing views from a camera, measuring a flat target's depth, plotting.

The arithmetic lives in the pure core (:mod:`companion.core.calibrate`, :func:`companion.core.lut.fit_lut`);
this package reads files and cameras for it.
"""
