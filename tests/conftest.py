"""What every test gets: a runtime directory of its own, and a loud failure for a ZeroMQ context left open.

* ``XDG_RUNTIME_DIR`` points at a fresh folder for each test (removed afterwards), and
  ``RUNTIME_DIRECTORY`` is unset: a test's service binds its ``auto`` sockets there, and a client
  looks only there (never in the user's own runtime directory, nor in the /tmp fallback), so no
  test sees another run's sockets or leaves one behind.
* The kernels compiled for the CPU (``companion.gpu.hostemu``) are built in this run's own folder,
  Numba's in pytest's cache folder, and the processes the tests start (MAVSDK's server) keep their
  temporary files in another.
* Every ``zmq.Context`` created during a test must be closed by the end of it (a few seconds of
  grace for threads that close their own): an open one fails the test, naming it, and is destroyed
  with linger 0 so that the interpreter's exit never waits in ``zmq_ctx_term``.
* A test must not leave a service running behind it: a thread of the service's (its event loop, the
  capture, pipeline, control, relay, preview and recorder threads) or any non-daemon thread still
  alive a few seconds after the test fails it, naming the threads. A service left running in this
  process would compete with every later test's service for the interpreter lock and the cores.
* The heap the test process starts with (pytest, the collected tests, every imported module) is frozen
  out of the garbage collector once collection is done (:func:`gc.freeze`), as the service freezes its
  own after start-up. A full collection holds the interpreter lock for the whole heap: in this process
  that is every thread of a service a test runs in-process, and on a loaded machine a collection of
  the test process's heap took 0.5 to 0.9 s, longer than the stale-frame timeout (the service then
  degrades, as it must). The context check collects only when a context still looks open.
"""

from __future__ import annotations

import gc
import shutil
import tempfile
import threading
import time
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zmq

#: How long a test's contexts may take to close after the test (threads that stop on their own).
CONTEXT_GRACE_S = 5.0

_contexts: weakref.WeakSet[zmq.Context] = weakref.WeakSet()
_original_init = zmq.Context.__init__


def _tracking_init(self: zmq.Context, *args: Any, **kwargs: Any) -> None:
    _original_init(self, *args, **kwargs)
    if not getattr(self, "_shadow", False):  # a shadow shares another's context: that one is tracked
        _contexts.add(self)


def pytest_configure(config: pytest.Config) -> None:
    zmq.Context.__init__ = _tracking_init  # type: ignore[method-assign]


def pytest_collection_finish(session: pytest.Session) -> None:
    gc.collect()
    gc.freeze()


def pytest_unconfigure(config: pytest.Config) -> None:
    zmq.Context.__init__ = _original_init  # type: ignore[method-assign]


#: How long a test's threads may take to end after the test, seconds.
THREAD_GRACE_S = 5.0
#: The threads a service running in this process owns (their names): one left alive is a leaked service.
SERVICE_THREADS = frozenset({"service", "capture", "pipeline", "control server", "control relay", "preview", "recorder"})


def _leaked_threads(before: set[int]) -> list[threading.Thread]:
    return [
        t for t in threading.enumerate()
        if t.ident not in before and t.is_alive() and (not t.daemon or t.name in SERVICE_THREADS)
    ]


@pytest.fixture(autouse=True)
def no_threads_left(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail the test when a thread it started (a service's, or any non-daemon one) outlives it."""
    before = {t.ident for t in threading.enumerate()}
    yield
    deadline = time.monotonic() + THREAD_GRACE_S
    left = _leaked_threads(before)
    while left and time.monotonic() <= deadline:
        time.sleep(0.05)
        left = _leaked_threads(before)
    if left:
        pytest.fail(
            f"{request.node.nodeid}: thread(s) left running: {', '.join(sorted(t.name for t in left))} (stop the "
            "service and join its threads before the test ends)",
            pytrace=False,
        )


def _open_contexts(besides: weakref.WeakSet[zmq.Context] | None = None) -> list[zmq.Context]:
    return [c for c in list(_contexts) if not c.closed and (besides is None or c not in besides)]


@pytest.fixture(autouse=True, scope="session")
def hostemu_build_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The kernels compiled for the CPU (companion.gpu.hostemu) are built in this run's own folder,
    not in the shared cache in /tmp: nothing is left behind, and runs side by side do not share it."""
    from companion.gpu.hostemu import BUILD_DIR_ENV

    path = tmp_path_factory.mktemp("hostemu")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(BUILD_DIR_ENV, str(path))
        yield path


@pytest.fixture(autouse=True, scope="session")
def numba_cache_dir(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The compiled kernels (the planner's, the CPU matcher's) are cached in pytest's own cache folder
    (a temporary one without it), for this process and the services it starts, never in the user's:
    each kernel compiles once per checkout, not once per process started."""
    import sys

    cache = getattr(request.config, "cache", None)
    path = cache.mkdir("companion-numba") if cache is not None else tmp_path_factory.mktemp("numba-cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NUMBA_CACHE_DIR", str(path))
        if "numba" in sys.modules:  # imported while collecting: its config has read the environment already
            mp.setattr(sys.modules["numba"].config, "CACHE_DIR", str(path))
        yield path


@pytest.fixture(autouse=True, scope="session")
def private_tmpdir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The processes the tests start write their temporary files in this run's own folder, not in
    /tmp: MAVSDK's server leaves a component-metadata folder in its temporary directory on every start
    (under systemd the service's server writes it in a /tmp of the service's own: PrivateTmp)."""
    path = tmp_path_factory.mktemp("tmp")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TMPDIR", str(path))
        yield path


@pytest.fixture(autouse=True)
def private_runtime_dir(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A runtime directory of this test's own (short: a socket path has at most 107 bytes)."""
    path = tempfile.mkdtemp(prefix="companion-test-")
    monkeypatch.setenv("XDG_RUNTIME_DIR", path)
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(autouse=True)
def zmq_contexts_closed(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail the test when a ZeroMQ context it created is still open at its end."""
    before = weakref.WeakSet(_contexts)
    yield
    deadline = time.monotonic() + CONTEXT_GRACE_S
    left = _open_contexts(besides=before)
    while left and time.monotonic() <= deadline:
        # One that is unreachable is closed by its finaliser once collected; a thread may close its own.
        gc.collect()
        left = _open_contexts(besides=before)
        if left:
            time.sleep(0.05)
    if left:
        for ctx in left:
            ctx.destroy(linger=0)
        pytest.fail(
            f"{request.node.nodeid}: {len(left)} ZeroMQ context(s) left open (close every socket and the "
            "context with linger 0: ctx.destroy(linger=0))",
            pytrace=False,
        )


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """A context still open at the end (a module's fixture's) is destroyed, loudly, so the exit never hangs."""
    gc.collect()
    left = _open_contexts()
    for ctx in left:
        ctx.destroy(linger=0)
    if left:
        session.config.get_terminal_writer().line(
            f"ERROR: {len(left)} ZeroMQ context(s) still open at the end of the session (destroyed now)", red=True
        )
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
