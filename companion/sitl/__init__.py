"""PX4 SITL in the loop: fly the real service against PX4's own flight stack (SIH quadrotor).

The shell around a flight, nothing the service itself runs:

* :mod:`companion.sitl.px4`: find a PX4 SITL build, start and stop a headless SIH instance, its ports;
* :mod:`companion.sitl.pilot`: the ground station (MAVSDK on PX4's GCS link): arm, take off, land,
  switch modes, set parameters, record PX4's own telemetry;
* :mod:`companion.sitl.service`: the service as a user runs it: ``companion run`` in its own process,
  its health over ZeroMQ, requests through the same control socket ``companion ctl`` uses;
* :mod:`companion.sitl.flight`: one course (place it under the vehicle, take off, ``engage``, judge
  against the true geometry, land) and a suite of them;
* :mod:`companion.sitl.scenarios`: the ground-station scenarios (PX4's Collision Prevention, engaging
  from the sticks, ArduPilot's proximity, the step response).

The service's camera renders each frame from the pose PX4 reports over the service's own vehicle link
(``camera.sim_pose = "telemetry"``), so PX4's dynamics, estimator and control loop are all in the loop.
"""
