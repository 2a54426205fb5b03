"""The service shell around the pure core: camera sources, capture thread, MAVSDK vehicle link, ZeroMQ
control plane, the asyncio daemon (``companion run``), systemd glue, and recording.

Modules (each imported only by what needs it; nothing runs at import time):

* :mod:`~companion.service.camera`: ``uvc`` / ``replay`` / ``sim`` camera sources (:class:`CameraSource`),
  built from the config; the sources in ``camera_v4l2``, ``camera_replay`` and ``camera_sim``.
* :mod:`~companion.service.capture`: the capture thread and its one-slot mailbox.
* :mod:`~companion.service.vehicle`: :class:`MavsdkVehicleLink` (``mavsdk`` >= 4.1, asyncio API).
* :mod:`~companion.service.protocol`: the JSON control protocol (pydantic models).
* :mod:`~companion.service.bus`: ZeroMQ health PUB and control ROUTER (optionally CURVE).
* :mod:`~companion.service.daemon`: :class:`Service`, the asyncio process (``companion run``).
* :mod:`~companion.service.notify`: sd_notify (READY, STATUS, WATCHDOG).
* :mod:`~companion.service.install`: the systemd unit and ``companion install-service``.
* :mod:`~companion.service.client`: ``companion ctl`` and ``companion watch``.
"""
