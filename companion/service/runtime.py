"""Where the service's sockets live: the runtime directory, and what an endpoint of ``auto`` means.

The control socket commands the vehicle, so by default it is a Unix-domain socket (``ipc://``) that
only the service's user and group can open: the socket file is mode 0660 inside a directory that
others cannot enter. Under systemd that directory is ``RuntimeDirectory=companion`` (``/run/companion``,
mode 0750, group ``companion``: add operators to that group). Run by hand, it is
``$XDG_RUNTIME_DIR/companion`` (the user's own), or else ``/tmp/companion-<uid>`` (mode 0700, refused
when it belongs to someone else).

``companion ctl``, ``companion watch`` and the view find the service's sockets the same way
(:func:`find_socket`), looking in the system location first. The /tmp fallback is looked at only when
``XDG_RUNTIME_DIR`` is not set, so a user's (or a test's) own runtime directory never finds another
run's sockets. The service removes its socket files when it stops; a socket file with no service
behind it is reported at once (:func:`check_listening`).
"""

from __future__ import annotations

import logging
import math
import os
import grp
import re
import resource
import socket
import stat
from collections.abc import Mapping
from pathlib import Path

from companion.config.service import AUTO_ENDPOINT
from companion.errors import ConfigError, InputError

log = logging.getLogger(__name__)

#: The systemd unit's RuntimeDirectory.
SYSTEM_RUNTIME_DIR = Path("/run/companion")
#: Mode of the socket files: the service's user and group may connect, nobody else.
SOCKET_MODE = 0o660
#: Socket file names of the two endpoints.
SOCKET_NAMES = {"control": "control.sock", "health": "health.sock", "preview": "preview.sock"}


def runtime_dir(environ: Mapping[str, str] | None = None) -> Path:
    """The service's runtime directory (created if missing; see the module doc).

    Raises:
        ConfigError: the directory cannot be created, or the /tmp fallback belongs to another user or
            is open to others.
    """
    env = os.environ if environ is None else environ
    systemd = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if systemd:
        return Path(systemd)  # systemd made it with the unit's RuntimeDirectoryMode and group
    xdg = env.get("XDG_RUNTIME_DIR")
    if xdg:
        path = Path(xdg) / "companion"
        _make_private_dir(path, 0o700)
        return path
    path = Path("/tmp") / f"companion-{os.getuid()}"
    _make_private_dir(path, 0o700)
    info = path.lstat()
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise ConfigError(
            f"{path}: not a private directory of this user (owner uid {info.st_uid}, mode "
            f"{stat.S_IMODE(info.st_mode):o}); remove it, or set the bus endpoints explicitly"
        )
    return path


def _make_private_dir(path: Path, mode: int) -> None:
    try:
        path.mkdir(mode=mode, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{path}: cannot create the runtime directory: {err.strerror or err}") from None


def resolve_endpoint(endpoint: str, which: str, environ: Mapping[str, str] | None = None) -> str:
    """``endpoint`` as the service binds it: ``auto`` becomes ``ipc://<runtime dir>/<which>.sock``
    (``which``: "control", "health" or "preview"); anything else is returned as it is."""
    if endpoint != AUTO_ENDPOINT:
        return endpoint
    return f"ipc://{runtime_dir(environ) / SOCKET_NAMES[which]}"


def candidate_sockets(which: str, environ: Mapping[str, str] | None = None) -> list[Path]:
    """Where a client looks for the service's ``which`` socket, in order: the systemd location, the
    user's runtime directory, the /tmp fallback."""
    env = os.environ if environ is None else environ
    name = SOCKET_NAMES[which]
    out = [SYSTEM_RUNTIME_DIR / name]
    systemd = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if systemd:
        out.insert(0, Path(systemd) / name)
    xdg = env.get("XDG_RUNTIME_DIR")
    if xdg:
        out.append(Path(xdg) / "companion" / name)
    else:  # the service falls back to /tmp only without XDG_RUNTIME_DIR, and so does the client
        out.append(Path("/tmp") / f"companion-{os.getuid()}" / name)
    return out


def permission_denied(path: Path, what: str = "it") -> str:
    """The one-line refusal for a socket (or its folder) this user may not use, naming the group that
    may: the group that owns ``path`` (the service's), by name where it has one."""
    try:
        gid = path.stat().st_gid
    except OSError:
        group = "the service's group"
    else:
        try:
            group = grp.getgrgid(gid).gr_name
        except KeyError:
            group = str(gid)
    how = f"sudo usermod -aG {group} $USER, then log in again" if not group.startswith("the ") else "ask its owner"
    return (
        f"{path}: permission denied: only the service's user and the members of its group ({group}) "
        f"may use {what} ({how})"
    )


def find_socket(which: str, environ: Mapping[str, str] | None = None) -> str:
    """The ``ipc://`` endpoint of a running service's ``which`` socket (the first candidate that exists).

    Raises:
        ConfigError: none exists (is the service running?), or the one found cannot be opened by this
            user (not in the service's group), saying which.
    """
    candidates = candidate_sockets(which, environ)
    for path in candidates:
        try:
            exists = path.exists()
        except PermissionError:
            raise ConfigError(permission_denied(path.parent, "its sockets")) from None
        if not exists:
            continue
        if not os.access(path, os.R_OK | os.W_OK):
            raise ConfigError(permission_denied(path))
        check_listening(f"ipc://{path}")
        return f"ipc://{path}"
    raise ConfigError(
        f"no {which} socket of a running service in {', '.join(str(p.parent) for p in candidates)} "
        "(is the service running? name the endpoint with --endpoint, or --config to read it)"
    )


def expected_socket(which: str, environ: Mapping[str, str] | None = None) -> str:
    """Like :func:`find_socket`, for a client that waits for the service (``companion view``): when no
    socket exists yet, where the service would make it (the first candidate whose folder exists, else
    the last). ZeroMQ connects once it appears.

    Raises:
        ConfigError: the socket or its folder exists but this user may not use it.
    """
    try:
        return find_socket(which, environ)
    except ConfigError as err:
        if "permission denied" in str(err):
            raise
    candidates = candidate_sockets(which, environ)
    for path in candidates:
        if path.parent.is_dir():
            return f"ipc://{path}"
    return f"ipc://{candidates[-1]}"


_ENDPOINT = re.compile(r"^(tcp://(\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+):(\*|\d{1,5})|ipc://\S+|inproc://\S+)$")


def validate_endpoint(endpoint: str, option: str) -> str:
    """``endpoint`` when it is a ZeroMQ endpoint a client can connect to (``tcp://HOST:PORT``,
    ``ipc://PATH``, ``inproc://NAME``); ``option`` names where it came from (``--endpoint``).

    Raises:
        InputError: anything else, in one line.
    """
    if not _ENDPOINT.match(endpoint) or (
        endpoint.startswith("tcp://") and endpoint.rsplit(":", 1)[1] != "*" and int(endpoint.rsplit(":", 1)[1]) > 65535
    ):
        raise InputError(
            f"{option} {endpoint!r}: not a ZeroMQ endpoint (tcp://HOST:PORT or ipc://PATH, e.g. tcp://127.0.0.1:5561)"
        )
    return endpoint


def validate_timeout(timeout_s: float, option: str = "--timeout-s") -> float:
    """``timeout_s`` when it is a finite number of seconds > 0.

    Raises:
        InputError: zero, negative, NaN or infinite.
    """
    if not math.isfinite(timeout_s) or timeout_s <= 0:
        raise InputError(f"{option} {timeout_s:g}: must be a number of seconds > 0")
    return timeout_s


def socket_path(endpoint: str) -> Path | None:
    """The socket file of an ``ipc://`` endpoint (None: another transport, or an abstract socket)."""
    if not endpoint.startswith("ipc://") or endpoint.startswith("ipc://@"):
        return None
    return Path(endpoint.removeprefix("ipc://"))


def check_listening(endpoint: str) -> None:
    """For an ``ipc://`` endpoint whose socket file exists: raise when no process listens on it (a
    service that was killed leaves its file; ZeroMQ would only retry in silence). Other endpoints,
    and a file that does not exist yet: nothing.

    Raises:
        ConfigError: "no running service", naming the file.
    """
    path = socket_path(endpoint)
    if path is None:
        return
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.settimeout(1.0)
        probe.connect(str(path))
    except (FileNotFoundError, PermissionError):
        return  # not there yet (a client that waits), or said elsewhere with what to do
    except ConnectionRefusedError:
        raise ConfigError(
            f"no running service at {path} (the socket file is left from a service that stopped; "
            "start the service, or remove the file)"
        ) from None
    except OSError:
        return  # anything else: ZeroMQ's own error or timeout says it
    finally:
        probe.close()


def remove_socket(endpoint: str) -> None:
    """Remove the socket file of an ``ipc://`` endpoint this process bound (ZeroMQ usually has; a
    file left behind would look like a running service to a client)."""
    path = socket_path(endpoint)
    if path is None:
        return
    try:
        path.unlink(missing_ok=True)
    except OSError as err:
        log.warning("%s: could not remove the socket file: %s", path, err.strerror or err)


def restrict_socket(endpoint: str) -> None:
    """Make a bound ``ipc://`` socket file mode 0660 (others cannot connect); other endpoints: nothing."""
    if not endpoint.startswith("ipc://"):
        return
    path = Path(endpoint.removeprefix("ipc://"))
    if path.name.startswith("@"):
        return  # an abstract socket has no file
    try:
        os.chmod(path, SOCKET_MODE)
    except OSError as err:
        raise ConfigError(f"{path}: cannot set the socket's permissions: {err.strerror or err}") from None


#: The open-file limit the service asks for (within the hard limit): a flood of connections to a
#: TCP control endpoint must not exhaust the process's descriptors (the default soft limit is 1024).
OPEN_FILES_WANTED = 65536


def raise_open_file_limit(wanted: int = OPEN_FILES_WANTED) -> int:
    """Raise this process's soft limit on open files toward ``wanted`` (never above the hard limit);
    returns the soft limit now in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError) as err:
            log.warning("could not raise the open-file limit from %d to %d: %s", soft, target, err)
    return soft
