"""A headless PX4 SITL instance with the SIH quadrotor (simulation-in-hardware: no Gazebo).

PX4 is not part of this project: a user builds it (``make px4_sitl`` in a PX4-Autopilot checkout, see
the README) and points :func:`find_px4_build` at the build folder. Each instance ``N`` uses its own ports
(``ROMFS/px4fmu_common/init.d-posix/px4-rc.mavlink``): the API/offboard link sends to UDP
``14540 + N`` (the service listens there, as on the Jetson) and the GCS link of every instance sends
to UDP 14550, where a ground station (QGroundControl, or the harness's pilot) listens; instance ``N``
is MAVLink system ``N + 1``.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from companion.errors import CompanionError

log = logging.getLogger(__name__)

_S = TypeVar("_S", bound="SitlProcess")

#: Environment variable naming a PX4 SITL build folder (``.../PX4-Autopilot/build/px4_sitl_default``).
PX4_BUILD_ENV = "COMPANION_PX4_BUILD"


class SitlError(CompanionError):
    """PX4 SITL could not be found, started, or did not do what the flight needed."""


@dataclass(frozen=True)
class Px4Ports:
    """The UDP ports of PX4 SITL instance ``instance``."""

    instance: int = 0

    @property
    def api_port(self) -> int:
        """PX4 sends its API/offboard link here (the service's ``udpin``)."""
        return 14540 + self.instance if self.instance <= 9 else 14549

    @property
    def system_id(self) -> int:
        """The instance's MAVLink system id (``MAV_SYS_ID``)."""
        return self.instance + 1

    @property
    def service_url(self) -> str:
        """The service's ``vehicle.connection``."""
        return f"udpin://127.0.0.1:{self.api_port}"

    @property
    def pilot_url(self) -> str:
        """The ground station's MAVSDK connection (shared by every instance: pick by :attr:`system_id`)."""
        return "udpin://127.0.0.1:14550"


def find_px4_build(path: str | os.PathLike[str] | None = None, environ: dict[str, str] | None = None) -> Path | None:
    """The PX4 SITL build folder: ``path`` if given, else ``$COMPANION_PX4_BUILD``; None when neither is set.

    Raises:
        SitlError: the folder is named but has no ``bin/px4`` or ``etc/init.d-posix``.
    """
    env = os.environ if environ is None else environ
    text = os.fspath(path) if path is not None else env.get(PX4_BUILD_ENV)
    if not text:
        return None
    build = Path(text).expanduser().resolve()
    missing = [p for p in ("bin/px4", "etc/init.d-posix/rcS") if not (build / p).exists()]
    if missing:
        raise SitlError(
            f"{build}: not a PX4 SITL build folder (no {', '.join(missing)}); build one with "
            "`make px4_sitl` in PX4-Autopilot and name build/px4_sitl_default"
        )
    return build


def log_tail(path: Path, lines: int = 15) -> str:
    """The last ``lines`` lines of a process's log file, for an error message ("(no log)" if unreadable)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


class SitlProcess:
    """What both autopilots' SITL processes share: the process (started by a subclass's ``start`` in
    its own process group), its console log (``log_path``, a subclass's), and stopping it.
    ``NAME`` names the autopilot in messages."""

    NAME = "SITL"

    def __init__(self) -> None:
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def log_path(self) -> Path:
        raise NotImplementedError

    def log_tail(self, lines: int = 15) -> str:
        return log_tail(self.log_path, lines)

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the process (SIGTERM, then SIGKILL after ``timeout_s``). Safe to call twice."""
        proc, self._proc = self._proc, None
        if proc is None or proc.poll() is not None:
            return
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop within %g s; killing it", self.NAME, timeout_s)
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()

    def __enter__(self: _S) -> _S:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class Px4Sitl(SitlProcess):
    """One PX4 SITL process (``bin/px4 -d -i N -w WORKDIR BUILD/etc``, SIH quadrotor, real time).

    Args:
        build: the build folder (:func:`find_px4_build`).
        workdir: PX4's working folder (parameters, logs, dataman); created; its ``px4.log`` holds the
            console output.
        instance: the instance number (ports, :class:`Px4Ports`).
        model: ``PX4_SIM_MODEL`` (an SIH airframe).
    """

    NAME = "PX4"

    def __init__(self, build: Path, workdir: Path, instance: int = 0, model: str = "sihsim_quadx") -> None:
        self.build = build
        self.workdir = workdir
        self.ports = Px4Ports(instance)
        self.model = model
        super().__init__()

    @property
    def log_path(self) -> Path:
        return self.workdir / "px4.log"

    def start(self, fresh: bool = True, timeout_s: float = 30.0) -> None:
        """Start PX4 and wait until its start-up script has run.

        Args:
            fresh: delete the previous parameters and mission storage first (a clean vehicle).
            timeout_s: seconds to wait for the start-up script.

        Raises:
            SitlError: it exited or did not finish starting in time (the log's tail is in the message).
        """
        self.workdir.mkdir(parents=True, exist_ok=True)
        if fresh:
            for name in ("parameters.bson", "parameters_backup.bson", "dataman"):
                (self.workdir / name).unlink(missing_ok=True)
        env = dict(os.environ, PX4_SIMULATOR="sihsim", PX4_SIM_MODEL=self.model)
        log_file = self.log_path.open("wb")
        cmd = [str(self.build / "bin/px4"), "-d", "-i", str(self.ports.instance), "-w", str(self.workdir), str(self.build / "etc")]
        log.info("starting PX4 SITL instance %d: %s", self.ports.instance, " ".join(cmd))
        self._proc = subprocess.Popen(
            cmd, cwd=self.workdir, env=env, stdin=subprocess.DEVNULL, stdout=log_file, stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log_file.close()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                raise SitlError(f"PX4 exited with {self._proc.returncode} while starting:\n{self.log_tail()}")
            if b"Startup script returned" in self.log_path.read_bytes():
                return
            time.sleep(0.1)
        self.stop()
        raise SitlError(f"PX4 did not finish starting within {timeout_s:g} s:\n{self.log_tail()}")

    def command(self, *args: str, timeout_s: float = 10.0) -> str:
        """Run a PX4 shell command on this instance (``bin/px4-<module> --instance N args``, PX4's own
        client), e.g. ``command("mavlink", "status")``; returns its output.

        Raises:
            SitlError: it failed.
        """
        module, *rest = args
        cmd = [str(self.build / "bin" / f"px4-{module}"), "--instance", str(self.ports.instance), *rest]
        done = subprocess.run(cmd, cwd=self.workdir, capture_output=True, text=True, timeout=timeout_s, check=False)
        if done.returncode != 0:
            raise SitlError(f"PX4 command {' '.join(args)!r} failed ({done.returncode}): {done.stdout}{done.stderr}")
        return done.stdout
