"""See what the drone sees: the live preview image, the browser view and the post-flight review (issue 19).

* :mod:`companion.view.frame`: the preview image (the paper's Fig. 10 overlay with the disparity inset
  and its legend) and the preview message on the wire. Pure: arrays in, bytes out.
* :mod:`companion.view.server`: ``companion view``, the web page (aiohttp) that follows a service's
  health and preview over ZeroMQ and speaks its control protocol.
* :mod:`companion.view.simbridge`: publishes a simulated flight as the service would, for
  ``companion demo --view`` and ``companion sim --view``.
* :mod:`companion.view.review`: ``companion review``, an HTML report from a recorded health stream.

Nothing here is imported by the flight path except :mod:`companion.view.frame`, and that only by the
preview thread (:mod:`companion.service.preview`).
"""
