"""Closed-loop simulator: fly the product's pipeline through procedural obstacle courses and score it.

* :mod:`companion.sim.vehicle`: a multicopter following body-frame velocity/yaw-rate setpoints
  (a :class:`~companion.interfaces.VehicleLink`);
* :mod:`companion.sim.camera`: the rendered ZED (a :class:`~companion.interfaces.CameraSource`);
* :mod:`companion.sim.courses`: seeded courses (corridor, doorway, forest, pitch, side, deadend);
* :mod:`companion.sim.loop`: the loop in simulated time and the per-step log;
* :mod:`companion.sim.scoring`: clearance and outcomes; :mod:`companion.sim.suite`: many courses;
* :mod:`companion.sim.plot`: top-down and side-view plots drawn with OpenCV.
"""
