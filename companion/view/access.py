"""Who may reach ``companion view``: every request held against the view's bind and token.

Access: bound to 127.0.0.1 by default. The view has a token (given in a file or
``$COMPANION_VIEW_TOKEN``, else made up), printed only in the URL it shows its operator
(``…/?token=…``); it is never served to anyone who asks.

* Commanding (``POST /api/control``) always needs it, on loopback too (another local user can reach a
  loopback port, but cannot read the operator's terminal, a file of mode 0600, or a process's
  environment): ``Authorization: Bearer TOKEN``, compared in constant time, besides the page's own
  header (``X-Companion-View: 1``) and origin (no cross-site request can send them). The page takes
  the token from its address once, keeps it in the tab's ``sessionStorage`` and drops it from the
  address bar.
* Watching: on a loopback bind open to anyone local, for loopback Host names only (a web page
  elsewhere cannot reach it by DNS rebinding). Any other bind needs the token for everything: as
  ``?token=`` once (the page's later requests carry it in a cookie) or ``Authorization: Bearer``.
"""

from __future__ import annotations

import hmac
from typing import Any

from companion.view.options import ViewOptions, is_loopback_host

_COOKIE = "companion_view_token"


class AccessGuard:
    """The view's access rules for ``options`` (its bind and token): :attr:`middleware` guards every
    request, :meth:`bearer_ok` is what commanding needs besides."""

    def __init__(self, options: ViewOptions) -> None:
        self.options = options

    def _token_ok(self, request: Any) -> bool:
        """Whether ``request`` carries the token (in its query, its cookie or its Authorization)."""
        given = [
            request.query.get("token", ""),
            request.cookies.get(_COOKIE, ""),
            request.headers.get("Authorization", "").removeprefix("Bearer ").strip(),
        ]
        return any(self._is_token(g) for g in given)

    def _is_token(self, given: str) -> bool:
        token = self.options.token
        # Constant time: how much of a guess matched must not show in how long the refusal takes.
        return token is not None and bool(given) and hmac.compare_digest(given.encode(), token.encode())

    def bearer_ok(self, request: Any) -> bool:
        """Whether ``request`` carries the token as ``Authorization: Bearer`` (what commanding needs)."""
        header = request.headers.get("Authorization", "")
        return header.startswith("Bearer ") and self._is_token(header.removeprefix("Bearer ").strip())

    def _same_origin(self, request: Any) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:
            return True
        from yarl import URL

        try:
            o = URL(origin)
        except ValueError:
            return False
        return o.host is not None and f"{o.host}:{o.port}" == f"{request.url.host}:{request.url.port}"

    async def _guard_impl(self, request: Any, handler: Any) -> Any:
        from aiohttp import web

        loopback_bind = is_loopback_host(self.options.host)
        if loopback_bind and not is_loopback_host(request.url.host or ""):
            # Bound to loopback: a Host that is not loopback is a DNS-rebinding page.
            return web.Response(status=403, text="companion view: this view answers only to localhost\n")
        if not loopback_bind and not self._token_ok(request):
            return web.Response(
                status=401,
                text="companion view: this view needs its token: open the address `companion view` printed (…/?token=…)\n",
            )
        if request.method != "GET" or request.path == "/ws":
            if not self._same_origin(request):
                return web.Response(status=403, text="companion view: cross-origin request refused\n")
        response = await handler(request)
        if response.prepared:  # a WebSocket or a stream: its headers are gone already
            return response
        if not loopback_bind and request.query.get("token") and isinstance(response, web.Response):
            # For the page's later reads (its WebSocket, its images); commanding needs the header.
            response.set_cookie(_COOKIE, self.options.token, httponly=True, samesite="Strict", path="/")
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("Referrer-Policy", "no-referrer")
        response.headers.setdefault("Cache-Control", "no-store")
        return response

    @property
    def middleware(self) -> Any:
        """The aiohttp middleware that holds every request to these rules (and sets the responses' safety
        headers)."""
        from aiohttp import web

        @web.middleware
        async def guard(request: Any, handler: Any) -> Any:
            return await self._guard_impl(request, handler)

        return guard
