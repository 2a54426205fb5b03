"""A service run as a real process (``python -m companion run``): its config, its sd_notify messages,
its start and end. Shared by the process-level tests."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path


def write_config(
    path: Path, port: int, extra: str = "", cruise: float = 1.0, bus: str = "", vehicle: str = "", service: str = ""
) -> None:
    """A config for a service on the sim camera that engages at once (autostart) with the peer on UDP
    ``port``; ``bus``, ``vehicle``, ``service``: more lines of those tables; ``extra``: more lines after [planner]
    (more tables too)."""
    tmp = path.parent
    path.write_text(
        f"""
[bus]
health_endpoint = "ipc://{tmp}/h.sock"
control_endpoint = "ipc://{tmp}/c.sock"
{bus}
[view]
preview_endpoint = "ipc://{tmp}/p.sock"
[camera]
fps_hz = 10.0
[stereo]
backend = "opencv-bm"
[vehicle]
connection = "udpin://127.0.0.1:{port}"
{vehicle}
[service]
autostart = true
{service}
[planner]
cruise_speed_m_s = {cruise}
{extra}
""",
        encoding="utf-8",
    )


class Notifications:
    """A NOTIFY_SOCKET for the child, read at once by a thread of its own (as systemd reads it): its
    sd_notify datagrams with the time each arrived (monotonic seconds)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.05)
        self._lock = threading.Lock()
        self._messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="notify socket", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            t = time.monotonic()
            with self._lock:
                self._messages += [(t, line) for line in data.decode().splitlines()]

    @property
    def messages(self) -> list[tuple[float, str]]:
        """Every line received so far: (arrival time, line)."""
        with self._lock:
            return list(self._messages)

    def poll(self) -> None:
        """Nothing to do: the thread reads (kept for the callers that poll)."""

    def wait_for(self, prefix: str, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(m.startswith(prefix) for _, m in self.messages):
                return True
            time.sleep(0.01)
        return any(m.startswith(prefix) for _, m in self.messages)

    def lines(self, prefix: str) -> list[str]:
        return [m for _, m in self.messages if m.startswith(prefix)]

    def close(self) -> None:
        """Stop reading; what arrived until now stays in :attr:`messages`."""
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


def spawn(config: Path, notify: Notifications | None, watchdog_usec: int | None = None) -> subprocess.Popen:
    env = dict(os.environ)
    env.pop("NOTIFY_SOCKET", None)
    env.pop("WATCHDOG_USEC", None)
    if notify is not None:
        env["NOTIFY_SOCKET"] = str(notify.path)
    if watchdog_usec is not None:
        env["WATCHDOG_USEC"] = str(watchdog_usec)
    return subprocess.Popen(
        [sys.executable, "-m", "companion", "--log-level", "INFO", "run", "--config", str(config)],
        cwd=str(config.parent),  # nothing may depend on the working directory
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc: subprocess.Popen, timeout_s: float = 120.0) -> tuple[int, str]:
    """The exit status and stderr of ``proc``; ``timeout_s`` only tells a hung process from a slow start
    on a loaded machine (a first start compiles the planner's kernels, 10 s on 2 quiet cores)."""
    try:
        _, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"process did not exit; stderr:\n{err[-3000:]}") from None
    return proc.returncode, err
