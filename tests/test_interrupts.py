"""A Ctrl-C during a compile (Numba calls back into Python through ctypes, where a KeyboardInterrupt is
dropped) is delivered once the compile is over."""

from __future__ import annotations

import ctypes
import os
import signal
import threading

from collections.abc import Iterator

import pytest

from companion.interrupts import interrupt_after


@pytest.fixture(autouse=True)
def python_handles_sigint() -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt, as in a command started from a terminal, even where this test
    process was started with SIGINT ignored (a shell's background job); the disposition it had is put
    back after."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def _sort_interrupted_in_a_callback() -> None:
    """libc's qsort with a Python comparator that sends this process SIGINT: the signal arrives while
    C code runs a ctypes callback, as it does while Numba's compiler runs llvmlite's."""
    libc = ctypes.CDLL(None)
    compare_t = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))
    sent = []

    def compare(a, b) -> int:
        if not sent:
            sent.append(True)
            os.kill(os.getpid(), signal.SIGINT)
        return a[0] - b[0]

    values = (ctypes.c_int * 8)(5, 3, 7, 1, 8, 2, 6, 4)
    libc.qsort(values, len(values), ctypes.sizeof(ctypes.c_int), compare_t(compare))
    assert list(values) == [1, 2, 3, 4, 5, 6, 7, 8]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_ctrl_c_in_a_callback_is_otherwise_dropped() -> None:
    # The defect the block exists for: without it the interrupt is lost (printed, not raised), and
    # the command runs on.
    _sort_interrupted_in_a_callback()


def test_a_ctrl_c_in_a_callback_is_delivered_after_the_block() -> None:
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        with interrupt_after():
            _sort_interrupted_in_a_callback()
    assert signal.getsignal(signal.SIGINT) is before


def test_without_a_ctrl_c_nothing_is_raised() -> None:
    before = signal.getsignal(signal.SIGINT)
    with interrupt_after():
        pass
    assert signal.getsignal(signal.SIGINT) is before


def test_an_error_in_the_block_is_raised_and_the_handler_restored() -> None:
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(ValueError):
        with interrupt_after():
            raise ValueError("compile failed")
    assert signal.getsignal(signal.SIGINT) is before


def test_off_the_main_thread_the_block_runs_as_it_is() -> None:
    ran: list[bool] = []

    def work() -> None:
        with interrupt_after():
            ran.append(True)

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert ran == [True]
