"""The engine's helper process (`service.worker`): jobs and results cross the process boundary intact, a failed
job is reported to its caller and no one else, a helper that dies fails its pending jobs and is started again,
and submitting never waits for a busy helper."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from service.worker import Worker, WorkerError


def _scaled(a: np.ndarray, k: float) -> np.ndarray:
    return a * k


def _fails(message: str) -> None:
    raise ValueError(message)


def _dies(status: int) -> None:
    os._exit(status)


def _pid() -> int:
    return os.getpid()


@pytest.fixture
def helper():
    w = Worker()
    yield w
    w.close()


def test_a_job_runs_in_another_process_and_its_result_comes_back(helper):
    a = np.arange(12.0).reshape(4, 3)
    assert np.array_equal(helper.submit(_scaled, a, 2.0).result(timeout=60), 2 * a)
    assert helper.submit(_pid).result(timeout=60) != os.getpid()


def test_results_come_back_in_order_of_submission(helper):
    futures = [helper.submit(_scaled, np.full(3, float(k)), 1.0) for k in range(20)]
    assert [f.result(timeout=60)[0] for f in futures] == list(range(20))


def test_a_failing_job_raises_worker_error_and_the_helper_serves_the_next(helper):
    with pytest.raises(WorkerError, match="ValueError: no pose"):
        helper.submit(_fails, "no pose").result(timeout=60)
    assert helper.submit(_scaled, np.ones(2), 3.0).result(timeout=60).tolist() == [3.0, 3.0]


def test_a_helper_that_dies_fails_its_pending_jobs_and_is_started_again(helper):
    first = helper.submit(_pid).result(timeout=60)
    with pytest.raises(WorkerError, match="exited"):
        helper.submit(_dies, 3).result(timeout=60)
    assert helper.submit(_pid).result(timeout=60) not in (first, os.getpid())


def test_a_job_submitted_as_a_dead_helper_still_looks_alive_goes_to_a_new_one(helper, monkeypatch):
    """A helper's pipes close as it exits, before its exit shows (`poll()` is still None for a moment): a job
    submitted in that moment went to the dead helper and was neither answered nor failed (seen in CI under
    load). Here the moment is made to last: the next job must still be answered, by a new helper."""
    import subprocess

    first = helper.submit(_pid).result(timeout=60)
    monkeypatch.setattr(subprocess.Popen, "poll", lambda self: None)  # every exit unseen
    with pytest.raises(WorkerError, match="exited"):
        helper.submit(_dies, 3).result(timeout=60)
    assert helper.submit(_pid).result(timeout=20) not in (first, os.getpid())


def test_submitting_a_large_job_does_not_wait_for_a_busy_helper(helper):
    busy = helper.submit(time.sleep, 3.0)
    big = np.zeros((2000, 68, 3))  # 3 MB, far more than a pipe holds: writing it blocks until the helper reads
    later = helper.submit(np.sum, big)
    assert not busy.done()  # submit returned while the helper was still asleep
    assert later.result(timeout=60) == 0.0


def test_wait_idle_returns_when_every_submitted_job_is_answered(helper):
    jobs = [helper.submit(time.sleep, 0.3), helper.submit(_pid)]
    assert not jobs[0].done()
    helper.wait_idle(timeout_s=60)
    assert all(j.done() for j in jobs)


def test_cpu_time_of_the_helper_is_reported(helper):
    assert np.isnan(helper.cpu_s())  # none running yet
    helper.submit(_pid).result(timeout=60)
    assert helper.cpu_s() >= 0.0


def test_a_helper_whose_parent_stopped_reading_exits_quietly():
    """A parent that dies mid-job closes the result pipe: the helper's answer meets a broken pipe. It exits
    with status 0 and prints nothing (it used to print a BrokenPipeError traceback)."""
    import pickle
    import struct
    import subprocess
    import sys

    from service import worker

    read, write = os.pipe()
    child = subprocess.Popen(
        [sys.executable, "-m", "service.worker", str(write)],
        stdin=subprocess.PIPE, stderr=subprocess.PIPE, pass_fds=(write,), cwd=worker._REPO,
    )
    os.close(write)
    os.close(read)
    payload = pickle.dumps((time.sleep, (0.2,)))
    child.stdin.write(struct.pack("<QQ", 0, len(payload)) + payload)
    child.stdin.close()
    with child.stderr:
        assert child.wait(timeout=60) == 0
        assert child.stderr.read() == b""
