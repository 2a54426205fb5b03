"""See what the drone sees: the browser view and the post-flight review.

The preview image and its message on the wire are the service's (:mod:`companion.service.preview_frame`);
this package only reads them.

* :mod:`companion.view.server`: ``companion view``, the web page (aiohttp) that follows a service's
  health and preview over ZeroMQ (:mod:`~companion.view.feed`) and speaks its control protocol, for
  whom :mod:`~companion.view.access` lets in (:mod:`~companion.view.options`: what it connects to).
* :mod:`companion.view.simbridge`: publishes a simulated flight as the service would, for
  ``companion demo --view`` and ``companion sim --view``.
* :mod:`companion.view.review`: ``companion review``, an HTML report from a recorded health stream.

Nothing here is imported by the service.
"""
