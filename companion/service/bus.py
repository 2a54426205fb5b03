"""ZeroMQ sockets of the control plane: health PUB and control ROUTER, optionally CURVE-authenticated.

The health socket publishes one JSON object per message (subscribe to b""). The control socket is a
ROUTER: a REQ client's message arrives as [identity, b"", payload] and a DEALER's as [identity,
payload]; the reply mirrors the envelope exactly. With ``bus.curve_server_secret_key_file`` and
``bus.curve_authorized_keys_dir`` both sockets are CURVE servers and only clients whose public
certificate is in that folder can connect (ZeroMQ's ZAP, via pyzmq's asyncio authenticator).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import zmq
import zmq.asyncio

from companion.config import BusConfig
from companion.errors import ConfigError

log = logging.getLogger(__name__)

#: ZeroMQ drops (without a reply) messages larger than this; bus.max_request_bytes (smaller) gets an
#: error reply instead. A guard for memory only.
_HARD_MAX_BYTES = 32 * 1024 * 1024


def load_server_keys(secret_file: Path) -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys from a zmq.auth secret certificate.

    Raises:
        ConfigError: unreadable, or a public-only certificate.
    """
    import zmq.auth

    try:
        public, secret = zmq.auth.load_certificate(str(secret_file))
    except (OSError, ValueError) as err:
        raise ConfigError(f"bus.curve_server_secret_key_file {secret_file}: cannot read it: {err}") from None
    if not secret:
        raise ConfigError(
            f"bus.curve_server_secret_key_file {secret_file}: has no secret key (use the .key_secret file)"
        )
    return public, secret


class Bus:
    """The two sockets, bound; :meth:`close` releases them (linger 0: nothing is held on exit).

    Raises (from :meth:`open`):
        ConfigError: an endpoint cannot be bound (in use, bad address) or the CURVE files are wrong.
    """

    def __init__(self, cfg: BusConfig) -> None:
        self.cfg = cfg
        self.ctx: zmq.asyncio.Context | None = None
        self.health: zmq.asyncio.Socket | None = None
        self.control: zmq.asyncio.Socket | None = None
        self._auth: Any = None
        self.health_endpoint = cfg.health_endpoint
        self.control_endpoint = cfg.control_endpoint

    def open(self) -> None:
        self.ctx = zmq.asyncio.Context()
        try:
            keys = None
            if self.cfg.curve_enabled:
                assert self.cfg.curve_server_secret_key_file is not None
                assert self.cfg.curve_authorized_keys_dir is not None
                keys = load_server_keys(self.cfg.curve_server_secret_key_file)
                allowed = self.cfg.curve_authorized_keys_dir
                if not allowed.is_dir():
                    raise ConfigError(f"bus.curve_authorized_keys_dir {allowed}: not a folder")
                from zmq.auth.asyncio import AsyncioAuthenticator

                self._auth = AsyncioAuthenticator(self.ctx)
                self._auth.start()
                self._auth.configure_curve(domain="*", location=str(allowed))
            self.health = self._bind(zmq.PUB, self.cfg.health_endpoint, "bus.health_endpoint", keys)
            self.control = self._bind(zmq.ROUTER, self.cfg.control_endpoint, "bus.control_endpoint", keys)
            self.control.setsockopt(zmq.ROUTER_MANDATORY, 1)
            # What the endpoints really are (a tcp port 0 is bound to an ephemeral port).
            self.health_endpoint = self.health.getsockopt_string(zmq.LAST_ENDPOINT)
            self.control_endpoint = self.control.getsockopt_string(zmq.LAST_ENDPOINT)
        except BaseException:
            self.close()
            raise
        log.info(
            "health on %s, control on %s%s",
            self.health_endpoint,
            self.control_endpoint,
            " (CURVE)" if keys else "",
        )

    def _bind(self, kind: int, endpoint: str, field: str, keys: tuple[bytes, bytes] | None) -> zmq.asyncio.Socket:
        assert self.ctx is not None
        sock = self.ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, _HARD_MAX_BYTES)
        if kind == zmq.PUB:
            sock.setsockopt(zmq.SNDHWM, 100)  # a slow subscriber loses old health, never blocks us
        if keys is not None:
            sock.curve_server = True
            sock.curve_publickey, sock.curve_secretkey = keys
        try:
            sock.bind(endpoint)
        except zmq.ZMQError as err:
            sock.close(linger=0)
            raise ConfigError(f"{field} {endpoint!r}: cannot bind: {err}") from None
        return sock

    async def publish(self, payload: bytes) -> None:
        """Publish one health message; never blocks (a full queue drops it)."""
        if self.health is None:
            return
        try:
            await self.health.send(payload, flags=zmq.NOBLOCK)
        except zmq.Again:
            log.debug("health message dropped: subscribers are slow")

    def close(self) -> None:
        for name in ("health", "control"):
            sock = getattr(self, name)
            if sock is not None:
                sock.close(linger=0)
                setattr(self, name, None)
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self.ctx is not None:
            self.ctx.term()
            self.ctx = None
