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
    # ready at once, then never reads, never answers
    hung = [sys.executable, "-c", "import sys, time; sys.stdout.buffer.write(b'R'); sys.stdout.flush(); time.sleep(60)"]
    worker = PreviewWorker(timeout_s=0.5, restart_after_s=60.0, command=hung)
    t0 = time.monotonic()
    with pytest.raises(PreviewWorkerError, match="within 0.5 s"):
        worker.render(inputs, 320, 70)
    assert time.monotonic() - t0 < 30.0  # bounded by the timeout, not by the worker (generous: a busy machine)
    assert worker.pid is None  # killed
    with pytest.raises(PreviewWorkerError, match="waiting to restart"):  # not restarted at once
        worker.render(inputs, 320, 70)
    worker.close()


def test_a_slow_start_up_is_outside_the_deadline_of_a_preview(inputs: PreviewInputs) -> None:
    """A busy laptop took 1.2-2.9 s to import the worker's modules; with the start-up inside the 2 s
    deadline of a preview the worker was killed again and again and the page never got a picture."""
    # a start-up longer than a preview's deadline (5 s: one preview, generous on a loaded machine)
    slow = [sys.executable, "-c", "import time; time.sleep(6.0); from companion.service.preview_worker import main; main()"]
    worker = PreviewWorker(timeout_s=5.0, command=slow)
    try:
        assert worker.render(inputs, 160, 60)[0][:2] == b"\xff\xd8"
        assert worker.starts == 1
    finally:
        worker.close()


def test_a_worker_that_never_gets_ready_is_reported(inputs: PreviewInputs) -> None:
    silent = [sys.executable, "-c", "import time; time.sleep(60)"]
    worker = PreviewWorker(startup_timeout_s=0.5, restart_after_s=60.0, command=silent)
    with pytest.raises(PreviewWorkerError, match="not started within 0.5 s"):
        worker.render(inputs, 320, 70)
    assert worker.pid is None
    worker.close()


def test_the_worker_runs_below_the_flight_loop_but_above_idle_work(inputs: PreviewInputs) -> None:
    from companion.service.preview_worker import WORKER_NICE

    worker = PreviewWorker(timeout_s=30.0)
    try:
        worker.render(inputs, 160, 60)
        assert worker.pid is not None
        assert os.getpriority(os.PRIO_PROCESS, worker.pid) == max(WORKER_NICE, os.nice(0))
        assert 0 < WORKER_NICE < 19
    finally:
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


def test_a_worker_whose_service_goes_while_it_starts_ends_without_a_traceback() -> None:
    import subprocess

    proc = subprocess.Popen([sys.executable, "-m", "companion.service.preview_worker"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdin is not None
    proc.stdout.close()  # the service is gone before the worker is ready
    proc.stdin.close()
    assert proc.stderr is not None
    err = proc.stderr.read()
    proc.wait(120)
    proc.stderr.close()
    assert proc.returncode == 0 and b"Traceback" not in err, err.decode()


def test_a_running_service_s_worker_runs_at_the_worker_s_priority(tmp_path: Path) -> None:
    """The worker inherits the niceness of the thread that starts it (Linux), and a process may lower
    its own priority but not raise it again. The service's preview thread used to lower itself to nice
    10 before it started the worker: the worker's imports and previews ran at nice 10, and beside two
    busy processes the page showed its first picture after about 50 s and then fewer than one a second.
    The worker of a running service, watched, runs at :data:`WORKER_NICE` above the service."""
    import zmq
    from peers.fakes import FakeLink, ServiceRunner, avoid_scene_camera, wait_until

    from companion.service.daemon import Service
    from companion.service.preview_worker import WORKER_NICE

    cfg = service_config(tmp_path)
    service = Service(cfg, camera=avoid_scene_camera(15.0), link=FakeLink(), install_signals=False, environ={})
    ctx = zmq.Context()
    try:
        with ServiceRunner(service):
            sub = ctx.socket(zmq.SUB)
            sub.setsockopt(zmq.LINGER, 0)
            sub.setsockopt(zmq.SUBSCRIBE, b"preview")
            sub.connect(cfg.view.preview_endpoint)
            assert sub.poll(120_000), "no preview"  # the worker is up and has drawn one
            worker = service.view.publisher._worker
            assert worker.pid is not None
            assert os.getpriority(os.PRIO_PROCESS, worker.pid) == max(WORKER_NICE, os.nice(0))
            # The service's own threads keep its priority (none that takes the GIL below the others').
            preview_thread = service.view.publisher._thread
            assert os.getpriority(os.PRIO_PROCESS, preview_thread.native_id) == os.nice(0)
            sub.close(0)
            assert wait_until(lambda: not service.view.publisher.subscribed, 30.0)
    finally:
        ctx.destroy(linger=0)
