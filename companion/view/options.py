"""What ``companion view`` connects to and how it serves (:class:`ViewOptions`), and the checks of a
bind: a network bind needs a token (:func:`check_options`); :func:`display_hosts` names the addresses a
wildcard bind serves on.
"""

from __future__ import annotations

import ipaddress
import shutil
import socket
import subprocess
from collections.abc import Callable
from dataclasses import dataclass

from companion.errors import InputError

_LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost")


@dataclass(frozen=True)
class ViewOptions:
    """What ``companion view`` connects to and how it serves.

    Attributes:
        health_endpoint: the service's health PUB endpoint.
        preview_endpoint: the service's preview XPUB endpoint, or None (no picture).
        control_endpoint: the control socket, or None: read-only (no buttons).
        curve: CURVE client options for the ZeroMQ sockets (see
            :func:`~companion.service.client.curve_client_options`), or None.
        host: the address to bind (127.0.0.1 by default).
        port: the TCP port (0 = any free one).
        token: the access token, or None (only on a loopback bind, and then nothing commands).
        title: shown in the page's header.
        control_timeout_s: how long a control request waits for the service's reply, seconds.
        say: called with each line the operator's terminal should show (the rig check's lines from
            health's ``rig``, when they first arrive or change), or None.
    """

    health_endpoint: str
    preview_endpoint: str | None
    control_endpoint: str | None
    curve: dict[str, bytes] | None = None
    host: str = "127.0.0.1"
    port: int = 8080
    token: str | None = None
    title: str = "companion"
    control_timeout_s: float = 3.0
    say: Callable[[str], None] | None = None


def is_loopback_host(host: str) -> bool:
    """True for a loopback address or name (127.0.0.0/8, ::1, localhost)."""
    host = host.strip("[]")
    if host.lower() in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_options(options: ViewOptions) -> None:
    """Refuse a network bind without a token, and a token too short to be one.

    Raises:
        InputError: naming what is wrong.
    """
    if not is_loopback_host(options.host) and not options.token:
        raise InputError(
            f"--host {options.host} serves the network: it needs a token (--token-file FILE, or "
            "$COMPANION_VIEW_TOKEN; `companion view` makes one up and prints it when neither is given)"
        )
    if options.token is not None and len(options.token) < 8:
        raise InputError("the view's token must be at least 8 characters")
    if not 0 <= options.port <= 65535:
        raise InputError(f"--port must be 0..65535, got {options.port}")


def display_hosts(host: str) -> list[str]:
    """The addresses to print for ``host``: itself, or this machine's IPv4 addresses for a wildcard."""
    if host not in ("0.0.0.0", "::", ""):
        return [host]
    found: list[str] = []
    ip = shutil.which("ip")
    if ip is not None:
        try:
            out = subprocess.run([ip, "-4", "-o", "addr", "show"], capture_output=True, text=True, timeout=2.0).stdout
            for line in out.splitlines():
                parts = line.split()
                if "inet" in parts:
                    addr = parts[parts.index("inet") + 1].split("/")[0]
                    if not addr.startswith("127."):
                        found.append(addr)
        except (OSError, subprocess.SubprocessError):
            pass
    if not found:
        try:
            found = sorted({a[4][0] for a in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)} - {"127.0.0.1"})
        except OSError:
            pass
    return found or ["127.0.0.1"]
