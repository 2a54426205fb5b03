"""The daemon's lifecycle, in the manner of uvicorn's ``Server``: startup, the main loop, shutdown.

:class:`Lifecycle` holds what decides when the process ends: ``should_exit`` (set by the first
SIGTERM/SIGINT, by a part that died, or by a caller), the forced exit (the second signal: a plain
signal handler ends the process at once with :data:`~companion.exitcodes.FORCED_EXIT`, whatever the
loop is doing), the exit code and the reason. It knows nothing of the vehicle: the daemon runs startup, waits on :meth:`wait`, then
runs its own shutdown (zero, Hold, then each part's ``stop`` within its budget).
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
from collections.abc import Callable
from typing import Any

from companion import exitcodes

log = logging.getLogger(__name__)


def flush_logs() -> None:
    """Flush every root log handler (before an exit that skips the interpreter's own cleanup)."""
    for handler in logging.getLogger().handlers:
        try:
            handler.flush()
        except Exception:  # nothing more can be done about a broken log handler at this point
            pass


def _force_exit(signum: int, frame: Any) -> None:
    """Second SIGTERM/SIGINT: leave now. MAVSDK dies with us, so its re-sending stops and PX4's
    offboard-loss failsafe takes over."""
    log.warning("%s again: forced exit", signal.Signals(signum).name)
    flush_logs()
    os._exit(exitcodes.FORCED_EXIT)


class Lifecycle:
    """When the service ends, and with which exit code.

    Args:
        on_reload: called (on the loop) for SIGHUP.
    """

    def __init__(self, on_reload: Callable[[], None] | None = None) -> None:
        self.exit_code = exitcodes.OK
        self.reason: str | None = None
        self.signals = 0
        self._on_reload = on_reload
        self._should_exit = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def should_exit(self) -> bool:
        return self._should_exit.is_set()

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """The loop the service runs on (for :meth:`request_exit_threadsafe`)."""
        self._loop = loop

    def request_exit(self, reason: str = "requested", exit_code: int | None = None) -> None:
        """Begin a clean shutdown (on the loop). The first non-zero exit code given is kept."""
        if exit_code is not None and self.exit_code == exitcodes.OK:
            self.exit_code = exit_code
        if not self._should_exit.is_set():
            self.reason = reason
            log.info("shutting down: %s", reason)
            self._should_exit.set()

    def request_exit_threadsafe(self, reason: str = "requested", exit_code: int | None = None) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self.request_exit, reason, exit_code)
            except RuntimeError:
                pass  # the loop closed between the check and the call: we are shutting down

    async def wait(self) -> None:
        """The main loop's wait: until a shutdown is requested."""
        await self._should_exit.wait()

    # ------------------------------------------------------------------ signals

    def install_signals(self) -> None:
        """SIGTERM/SIGINT: a clean shutdown, the second forces the exit; SIGHUP: ``on_reload``."""
        loop = self._loop
        assert loop is not None
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.handle_exit, sig)
        if self._on_reload is not None:
            loop.add_signal_handler(signal.SIGHUP, self._on_reload)

    def handle_exit(self, sig: int) -> None:
        name = signal.Signals(sig).name
        self.signals += 1
        log.info("%s: clean shutdown (send it again to force the exit)", name)
        # The second signal must work even if the loop is stuck: a plain handler, run by the
        # interpreter between bytecodes, not by the event loop.
        loop = self._loop
        assert loop is not None
        for s in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(s)
            signal.signal(s, _force_exit)
        self.request_exit(name)
