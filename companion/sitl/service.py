"""The service as a user runs it: ``python -m companion run --config FILE`` in its own process.

The harness writes the config (the user's, with the camera switched to the telemetry-driven sim
source and private ZeroMQ endpoints), starts the process, follows its health messages over ZeroMQ
and sends requests through the control socket, exactly as ``companion watch`` and ``companion ctl``
do. Killing the process (SIGKILL) takes MAVSDK down with it, which is how the offboard-loss test
makes PX4's own failsafe act.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig
from companion.config.document import render_config_toml
from companion.service.aio import cancel_and_wait
from companion.service.client import ClientError, ControlClient
from companion.service.install import START_TIMEOUT_S
from companion.sitl.px4 import SitlError, log_tail

log = logging.getLogger(__name__)


class ServiceProcess:
    """``companion run`` in a child process, its health followed over ZeroMQ.

    Args:
        cfg: the service's whole config (its ``bus`` endpoints are used to talk to it).
        workdir: where the config file and the service's log go.
        log_level: the service's ``--log-level``.
    """

    def __init__(self, cfg: CompanionConfig, workdir: Path, log_level: str = "INFO") -> None:
        self.cfg = cfg
        self.workdir = workdir
        self.log_level = log_level
        self.config_path = workdir / "companion.toml"
        self.log_path = workdir / "service.log"
        self.health_log_path = workdir / "health.jsonl"
        self.health: dict[str, Any] | None = None
        self.health_at_s: float | None = None
        self.health_history: list[tuple[float, dict[str, Any]]] = []
        self._proc: subprocess.Popen[bytes] | None = None
        self._ctx: Any = None
        self._sub: Any = None
        self._task: asyncio.Task | None = None

    async def start(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Write the config, start the process, wait until its health says the camera streams and the
        vehicle link is connected with the flight mode known (what ``engage`` needs): at most as long
        as systemd lets the service start (a first start compiles the kernels). Whatever ends
        the wait early (not ready, an error, a cancelled task) stops the process first (:meth:`stop`):
        a start that fails leaves nothing running.

        Raises:
            SitlError: it exited (its exit code and log tail are in the message) or was not ready in time.
        """
        try:
            await self._start(timeout_s)
        except BaseException:
            await self.stop()
            raise

    async def _start(self, timeout_s: float) -> None:
        import zmq
        import zmq.asyncio

        self.workdir.mkdir(parents=True, exist_ok=True)
        self.config_path.write_text(render_config_toml(self.cfg, ["# written by companion sitl"]))
        self._ctx = zmq.asyncio.Context()
        self._sub = self._ctx.socket(zmq.SUB)
        self._sub.setsockopt(zmq.LINGER, 0)
        self._sub.setsockopt(zmq.SUBSCRIBE, b"")
        self._sub.connect(self.cfg.bus.health_endpoint)
        self._task = asyncio.get_running_loop().create_task(self._follow())
        cmd = [sys.executable, "-m", "companion", "--log-level", self.log_level, "run", "--config", str(self.config_path)]
        log.info("starting the service: %s", " ".join(cmd))
        # Its temporary files (MAVSDK's component metadata) go in its workdir, as systemd's PrivateTmp
        # keeps them in the unit's own /tmp: a killed service leaves nothing in the machine's /tmp.
        tmp = self.workdir / "tmp"
        tmp.mkdir(exist_ok=True)
        env = {**os.environ, "TMPDIR": str(tmp)}
        with self.log_path.open("wb") as out:
            self._proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env)

        def ready() -> bool:
            h = self.health or {}
            vehicle = h.get("vehicle") or {}
            return (
                (h.get("camera") or {}).get("status") == "streaming"
                and vehicle.get("link") == "connected"
                and vehicle.get("flight_mode") not in (None, "UNKNOWN")
            )

        deadline = time.monotonic() + timeout_s
        while not ready():
            if self._proc.poll() is not None:
                raise SitlError(f"the service exited with {self._proc.returncode} while starting:\n{self.log_tail()}")
            if time.monotonic() > deadline:
                raise SitlError(f"the service was not ready within {timeout_s:g} s:\n{self.log_tail()}")
            await asyncio.sleep(0.05)

    async def _follow(self) -> None:
        while True:
            raw = await self._sub.recv()
            try:
                message = json.loads(raw)
            except ValueError:
                log.warning("service health: not JSON: %r", raw[:80])
                continue
            self.health, self.health_at_s = message, time.monotonic()
            self.health_history.append((self.health_at_s, message))

    @property
    def state(self) -> str | None:
        """The supervisor state of the newest health message."""
        return None if self.health is None else self.health.get("state")

    def call(self, request: dict[str, Any], timeout_s: float = 3.0) -> dict[str, Any]:
        """One request on the control socket (what ``companion ctl`` sends); returns the reply.

        Raises:
            SitlError: no reply, or the service refused (the reply's error in the message).
        """
        try:
            with ControlClient(self.cfg.bus.control_endpoint, timeout_s=timeout_s) as client:
                reply = client.call(request)
        except ClientError as err:
            raise SitlError(str(err)) from None
        if not reply.get("ok"):
            raise SitlError(f"the service refused {request.get('cmd')!r}: {(reply.get('error') or {}).get('message')}")
        return reply

    async def request(self, request: dict[str, Any], timeout_s: float = 3.0) -> dict[str, Any]:
        """:meth:`call` off the event loop."""
        return await asyncio.to_thread(self.call, request, timeout_s)

    async def wait_state(self, states: tuple[str, ...], timeout_s: float) -> float:
        """Wait until health reports one of ``states``; returns when.

        Raises:
            SitlError: not within ``timeout_s`` (the last state and reason in the message).
        """
        deadline = time.monotonic() + timeout_s
        while self.state not in states:
            if time.monotonic() > deadline:
                h = self.health or {}
                raise SitlError(f"service: not {'/'.join(states)} within {timeout_s:g} s (state {h.get('state')}: {h.get('reason')})")
            await asyncio.sleep(0.02)
        return time.monotonic()

    def log_tail(self, lines: int = 15) -> str:
        return log_tail(self.log_path, lines)

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def kill(self) -> float:
        """SIGKILL the service (no shutdown at all: MAVSDK dies with it); returns when."""
        assert self._proc is not None
        os.kill(self._proc.pid, signal.SIGKILL)
        self._proc.wait()
        return time.monotonic()

    async def stop(self, timeout_s: float = 10.0) -> int | None:
        """SIGTERM (the service sends zero, leaves offboard if it owns it, exits) and wait; SIGKILL
        after ``timeout_s``. Returns the exit code (None if it was never started). Safe to call twice."""
        proc = self._proc
        code = None
        try:
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    await asyncio.to_thread(proc.wait, timeout_s)
                except subprocess.TimeoutExpired:
                    log.warning("the service did not stop within %g s; killing it", timeout_s)
        finally:
            # Whatever happened above (the wait cancelled included), nothing is left behind.
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
            task, self._task = self._task, None
            try:
                if task is not None:
                    await cancel_and_wait([task])
            finally:
                if self._sub is not None:
                    self._sub.close(0)
                    self._sub = None
                if self._ctx is not None:
                    self._ctx.destroy(linger=0)
                    self._ctx = None
        if proc is not None:
            code = proc.returncode
        if self.health_history:
            await asyncio.to_thread(self._write_health_log)
        return code

    def _write_health_log(self) -> None:
        with self.health_log_path.open("w", encoding="utf-8") as f:
            for _, message in self.health_history:
                f.write(json.dumps(message) + "\n")
