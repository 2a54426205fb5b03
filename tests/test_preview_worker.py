"""The preview worker: the service's preview drawn and encoded in a child process, the same bytes as in
the service's own process; a worker that crashes, hangs or fails to draw is reported and replaced, and
never blocks its caller for longer than its timeout."""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
import time
from pathlib import Path

import pytest
from peers.fakes import avoid_scene_preview_inputs, service_config

from companion.service.preview_worker import PreviewWorker, PreviewWorkerError
from companion.service.preview_frame import PreviewInputs, encode_jpeg, render_preview


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> PreviewInputs:
    return avoid_scene_preview_inputs(service_config(tmp_path_factory.mktemp("cfg")))


def test_the_worker_draws_the_same_jpeg_as_the_service_would(inputs: PreviewInputs) -> None:
    worker = PreviewWorker(timeout_s=30.0)  # the first call starts Python and imports OpenCV
    try:
        jpeg, ms, h, w = worker.render(inputs, 320, 70)
        assert jpeg == encode_jpeg(render_preview(inputs, 320), 70)
        assert (h, w) == (179, 320) and ms > 0
        no_inset = dataclasses.replace(inputs, disparity=None)
        assert worker.render(no_inset, 320, 70)[0] == encode_jpeg(render_preview(no_inset, 320), 70)
        assert worker.starts == 1  # one child for every preview
    finally:
        worker.close()
    assert worker.pid is None


def test_a_killed_worker_is_reported_then_replaced(inputs: PreviewInputs) -> None:
    worker = PreviewWorker(timeout_s=30.0, restart_after_s=0.0)
    try:
        worker.render(inputs, 160, 60)
        pid = worker.pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        time.sleep(0.2)
        with pytest.raises(PreviewWorkerError, match="exited"):
            worker.render(inputs, 160, 60)
        assert worker.render(inputs, 160, 60)[0][:2] == b"\xff\xd8"  # a new worker, a JPEG
        assert worker.starts == 2 and worker.pid != pid
    finally:
        worker.close()


def test_a_hung_worker_costs_its_caller_at_most_the_timeout(inputs: PreviewInputs) -> None:
    hung = [sys.executable, "-c", "import time; time.sleep(60)"]  # never reads, never answers
    worker = PreviewWorker(timeout_s=0.5, restart_after_s=60.0, command=hung)
    t0 = time.monotonic()
    with pytest.raises(PreviewWorkerError, match="within 0.5 s"):
        worker.render(inputs, 320, 70)
    assert time.monotonic() - t0 < 2.0
    assert worker.pid is None  # killed
    with pytest.raises(PreviewWorkerError, match="waiting to restart"):  # not restarted at once
        worker.render(inputs, 320, 70)
    worker.close()


def test_a_worker_that_cannot_start_or_cannot_draw_says_why(inputs: PreviewInputs, tmp_path: Path) -> None:
    missing = PreviewWorker(command=[str(tmp_path / "no-such-python")])
    with pytest.raises(PreviewWorkerError, match="could not start"):
        missing.render(inputs, 320, 70)
    worker = PreviewWorker(timeout_s=30.0)
    try:
        with pytest.raises(PreviewWorkerError, match="drawing failed"):
            worker.render(inputs, 0, 70)  # no width: OpenCV refuses in the child
        pid = worker.pid
        assert pid is not None  # a drawing error does not cost the worker
        assert worker.render(inputs, 160, 60)[0][:2] == b"\xff\xd8" and worker.pid == pid
    finally:
        worker.close()


def test_ctrl_c_in_the_terminal_leaves_the_worker_to_the_service(inputs: PreviewInputs) -> None:
    """SIGINT reaches the whole foreground process group; the service decides when its child ends."""
    worker = PreviewWorker(timeout_s=30.0)
    try:
        worker.render(inputs, 160, 60)
        pid = worker.pid
        assert pid is not None
        os.kill(pid, signal.SIGINT)
        time.sleep(0.2)
        assert worker.render(inputs, 160, 60)[0][:2] == b"\xff\xd8" and worker.pid == pid
    finally:
        worker.close()
