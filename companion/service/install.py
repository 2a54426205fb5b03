"""The systemd unit and ``companion install-service``.

The unit is rendered from :data:`UNIT_TEMPLATE` (``systemd/companion.service`` in the repository is
:func:`render_unit` with the default ExecStart; a test keeps them equal, and ``tools/gen-systemd-unit.py``
rewrites it). The default config installed to ``/etc/companion/companion.toml`` is
:func:`companion.config.document.render_default_toml`, which a test keeps equal to the repository's
``config/companion.toml``; so nothing here reads a file relative to the working directory or needs
package data.
"""

from __future__ import annotations

import grp
import logging
import os
import pwd
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from companion import exitcodes
from companion.errors import InputError

log = logging.getLogger(__name__)

SERVICE_USER = "companion"
SERVICE_GROUPS = ("video", "dialout")
CONFIG_PATH = Path("/etc/companion/companion.toml")
UNIT_PATH = Path("/etc/systemd/system/companion.service")
DEFAULT_EXEC_START = f"/opt/companion/venv/bin/companion run --config {CONFIG_PATH}"
#: How long a start may take, seconds: a first start compiles the kernels (cpu-sgm: 1.5 min on 2 cores).
START_TIMEOUT_S = 300

UNIT_TEMPLATE = """\
# companion: stereo-vision obstacle avoidance for PX4 (ZED -> 9 regions -> fuzzy -> MAVSDK offboard).
# Installed by `companion install-service`; generated from companion/service/install.py.
[Unit]
Description=companion stereo-vision obstacle avoidance (PX4 offboard)
After=network-online.target
Wants=network-online.target
# A unit that keeps failing stops being restarted after 5 tries in 2 minutes.
StartLimitIntervalSec=120
StartLimitBurst=5

[Service]
Type=notify
NotifyAccess=main
ExecStart={exec_start}
ExecReload=/bin/kill -HUP $MAINPID
# READY=1 once the camera delivers and the pipeline is built. The first start compiles the kernels
# (GPU: seconds; planner: 10 s and cpu-sgm: 1.5 min on 2 cores; then cached under NUMBA_CACHE_DIR).
TimeoutStartSec={start_timeout_s}
# SIGTERM: zero setpoint, Hold if we own offboard, then exit; a second signal forces the exit.
TimeoutStopSec=15
# WATCHDOG=1 comes only from the control loop: a stalled loop gets the process killed (and MAVSDK's
# setpoint re-sending with it), so PX4's offboard-loss failsafe takes over.
WatchdogSec=2
Restart=on-failure
RestartSec=2
# 78 = startup failure (bad config, no camera after the timeout): restarting would only loop.
RestartPreventExitStatus={startup_failure}

User={user}
Group={user}
SupplementaryGroups={groups}
# The control and health sockets live here (bus endpoints "auto"): mode 0750 and sockets 0660, so only
# the service and the members of its group (operators: usermod -aG companion <user>) can command it.
RuntimeDirectory=companion
RuntimeDirectoryMode=0750
StateDirectory=companion
CacheDirectory=companion
ConfigurationDirectory=companion
Environment=PYTHONUNBUFFERED=1
Environment=CUPY_CACHE_DIR=/var/cache/companion/cupy
Environment=NUMBA_CACHE_DIR=/var/cache/companion/numba

# Hardening. Devices: the ZED (V4L2), the flight controller's serial port, the GPU; nothing else.
NoNewPrivileges=yes
ProtectSystem=strict
ProtectHome=yes
PrivateTmp=yes
ProtectKernelTunables=yes
ProtectKernelModules=yes
ProtectKernelLogs=yes
ProtectControlGroups=yes
ProtectClock=yes
ProtectHostname=yes
RestrictSUIDSGID=yes
RestrictNamespaces=yes
LockPersonality=yes
SystemCallArchitectures=native
RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK
UMask=0027
# A flood of connections to a TCP control endpoint must not exhaust the descriptors (the service also
# raises its soft limit itself).
LimitNOFILE=65536
DevicePolicy=closed
# /dev/video* (the ZED over UVC)
DeviceAllow=char-video4linux rw
# /dev/ttyTHS* (Jetson UART), /dev/ttyACM*, /dev/ttyUSB* (USB flight controllers and adapters)
DeviceAllow=char-ttyTHS rw
DeviceAllow=char-ttyACM rw
DeviceAllow=char-ttyUSB rw
# /dev/nvidia* (discrete GPUs: nvidia, nvidiactl, nvidia-uvm, nvidia-caps)
DeviceAllow=char-nvidia* rw
# /dev/nvhost-*, /dev/nvmap, /dev/nvgpu/* (Jetson's integrated GPU)
DeviceAllow=char-nvhost* rw
DeviceAllow=char-nvmap rw
DeviceAllow=char-nvgpu* rw

[Install]
WantedBy=multi-user.target
"""


def render_unit(exec_start: str = DEFAULT_EXEC_START, user: str = SERVICE_USER) -> str:
    """The unit file's text with ``exec_start`` as its ExecStart (an absolute command line)."""
    if not exec_start.startswith("/"):
        raise InputError(f"ExecStart must start with an absolute path, got {exec_start!r}")
    return UNIT_TEMPLATE.format(
        exec_start=exec_start,
        startup_failure=exitcodes.STARTUP_FAILURE,
        user=user,
        groups=" ".join(SERVICE_GROUPS),
        start_timeout_s=START_TIMEOUT_S,
    )


def default_exec_start() -> str:
    """ExecStart for this installation: this interpreter running ``-m companion`` (a venv's python)."""
    return f"{shlex.quote(str(Path(sys.executable).absolute()))} -m companion run --config {CONFIG_PATH}"


@dataclass(frozen=True)
class Step:
    """One thing install does (or, with --dry-run, would do)."""

    what: str
    done: bool


def _user_exists(name: str) -> bool:
    try:
        pwd.getpwnam(name)
        return True
    except KeyError:
        return False


def _existing_groups(names: tuple[str, ...]) -> list[str]:
    out = []
    for name in names:
        try:
            grp.getgrnam(name)
            out.append(name)
        except KeyError:
            log.warning("group %s does not exist here; not adding the service user to it", name)
    return out


def install_service(
    root: Path = Path("/"),
    *,
    exec_start: str | None = None,
    dry_run: bool = False,
    create_user: bool = True,
    force_config: bool = False,
) -> list[Step]:
    """Install the unit and the default config under ``root``; create the service user.

    Args:
        root: the file-system root to install under (tests use a temporary folder).
        exec_start: the unit's ExecStart; default: this interpreter with ``-m companion``.
        dry_run: only say what would be done.
        create_user: create the ``companion`` system user (only when ``root`` is ``/``).
        force_config: overwrite an existing /etc/companion/companion.toml.

    Raises:
        InputError: a file cannot be written (e.g. not root), or useradd failed.
    """
    from companion.config.document import render_default_toml

    steps: list[Step] = []
    unit_path = root / UNIT_PATH.relative_to("/")
    config_path = root / CONFIG_PATH.relative_to("/")
    unit = render_unit(exec_start or default_exec_start())

    def write(path: Path, text: str, mode: int) -> None:
        if dry_run:
            steps.append(Step(f"write {path} ({len(text)} bytes, mode {mode:o})", False))
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(text, encoding="utf-8")
            os.chmod(tmp, mode)
            tmp.replace(path)
        except OSError as err:
            raise InputError(f"{path}: cannot write: {err.strerror or err} (run as root, or use --root)") from None
        steps.append(Step(f"wrote {path}", True))

    write(unit_path, unit, 0o644)
    if config_path.exists() and not force_config:
        steps.append(Step(f"kept the existing {config_path} (--force-config replaces it)", False))
    else:
        write(config_path, render_default_toml(), 0o644)

    if create_user and root == Path("/"):
        if _user_exists(SERVICE_USER):
            steps.append(Step(f"user {SERVICE_USER} exists", False))
        else:
            groups = _existing_groups(SERVICE_GROUPS)
            cmd = [
                "useradd", "--system", "--user-group", "--no-create-home",
                "--home-dir", "/var/lib/companion", "--shell", "/usr/sbin/nologin",
            ]
            if groups:
                cmd += ["--groups", ",".join(groups)]
            cmd.append(SERVICE_USER)
            if dry_run:
                steps.append(Step("run " + shlex.join(cmd), False))
            else:
                try:
                    subprocess.run(cmd, check=True, capture_output=True, text=True)
                except FileNotFoundError:
                    raise InputError("useradd not found: create the 'companion' user by hand") from None
                except subprocess.CalledProcessError as err:
                    raise InputError(f"useradd failed: {err.stderr.strip() or err}") from None
                steps.append(Step("created the system user " + SERVICE_USER, True))
    elif create_user:
        steps.append(Step(f"skipped creating the user {SERVICE_USER} (root is {root}, not /)", False))
    steps.append(Step("next: systemctl daemon-reload && systemctl enable --now companion", False))
    return steps
