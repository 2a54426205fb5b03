"""sd_notify: tell systemd READY=1, STATUS=..., WATCHDOG=1, STOPPING=1, RELOADING=1.

Why our own ~20 lines instead of a library: the protocol is one datagram to the AF_UNIX socket named in
``$NOTIFY_SOCKET`` (a leading '@' means the abstract namespace). ``systemd-python`` needs libsystemd
headers to build (awkward on JetPack), ``cysystemd`` likewise; ``sdnotify`` is unmaintained since 2017
and swallows every error with a bare ``except``. Here a failed send is logged, never hidden, and never
raised into the control loop (a broken notify socket must not stop the setpoint stream; systemd's
watchdog then does its job). The socket never blocks: a receiver that does not read (its queue holds
only ``net.unix.max_dgram_qlen`` datagrams, 10 by default) would otherwise stop the control loop,
which sends WATCHDOG=1 from each step, inside ``sendto``; a notification it cannot take is dropped.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class Notifier:
    """Sends sd_notify datagrams to ``address`` (from ``$NOTIFY_SOCKET``)."""

    def __init__(self, address: str) -> None:
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
        self._failed = False

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] | None = None) -> Notifier | None:
        """A notifier when started by systemd with Type=notify, else None."""
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        return cls(address) if address else None

    def notify(self, *fields: str) -> bool:
        """Send ``fields`` (e.g. "READY=1", "STATUS=engaged") as one message; True if it went out."""
        message = "\n".join(f.replace("\n", " ") for f in fields).encode("utf-8", "replace")
        try:
            self._sock.sendto(message, self.address)
        except BlockingIOError:
            # The receiver's queue is full: drop this one rather than stall the caller (the control
            # loop). systemd reads at once; a notification lost now and then changes nothing.
            log.debug("sd_notify to %r dropped: the receiver's queue is full", self.address)
            return False
        except OSError as err:
            if not self._failed:  # log once per outage, not 20 times a second
                log.error("sd_notify to %r failed: %s", self.address, err)
            self._failed = True
            return False
        if self._failed:
            log.info("sd_notify works again")
        self._failed = False
        return True

    def close(self) -> None:
        self._sock.close()


def watchdog_interval_s(environ: Mapping[str, str] | None = None) -> float | None:
    """systemd's watchdog period for this process (``$WATCHDOG_USEC``), seconds; None when off.

    ``$WATCHDOG_PID``, when set, must be this process (else the watchdog is someone else's).
    """
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC", "")
    pid = env.get("WATCHDOG_PID", "")
    if not usec:
        return None
    if pid and pid != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        log.error("WATCHDOG_USEC=%r is not an integer; watchdog notifications off", usec)
        return None
    return value / 1e6 if value > 0 else None
