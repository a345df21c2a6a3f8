"""omni_sfm.forked: a computation in a forked child, its result (or error) taken later."""

from __future__ import annotations

import os
import signal
import time
from functools import partial

import numpy as np
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.forked import Deferred, can_fork, run_all

needs_fork = pytest.mark.skipif(not can_fork(), reason="the platform does not fork")


def _fail() -> None:
    raise OmniSfmError("no stretch of frames starts a solution")


@needs_fork
def test_the_child_computes_and_the_caller_gets_the_value():
    parent = os.getpid()
    job = Deferred(lambda: (os.getpid(), np.arange(5.0) ** 2), fork=True)
    assert job.forked
    pid, value = job.result()
    assert pid != parent and np.array_equal(value, np.arange(5.0) ** 2)
    assert job.result()[0] == pid  # asked again: the same value, no new child


def test_without_fork_it_runs_here_when_asked():
    calls: list[int] = []
    job = Deferred(lambda: calls.append(os.getpid()) or 7)
    assert not job.forked and calls == []  # nothing run yet
    assert job.result() == 7 and calls == [os.getpid()]
    assert job.result() == 7 and len(calls) == 1


@needs_fork
@pytest.mark.parametrize("fork", [True, False])
def test_an_error_in_the_job_is_raised_in_the_caller(fork: bool):
    job = Deferred(_fail, fork=fork)
    with pytest.raises(OmniSfmError, match="no stretch of frames starts a solution"):
        job.result()


@needs_fork
def test_a_result_that_cannot_be_sent_back_is_a_clear_error():
    job = Deferred(lambda: (lambda: 1), fork=True)  # a lambda does not pickle
    with pytest.raises(RuntimeError, match="could not be sent back .*function"):
        job.result()


@needs_fork
def test_start_later_and_cancel():
    job = Deferred(lambda: time.sleep(60))
    job.start()
    assert job.forked
    proc = job._proc
    job.cancel()  # stops the child now: terminated, not ended by itself after its minute
    assert not job.forked and proc.exitcode == -signal.SIGTERM
    done = Deferred(lambda: 3)
    assert done.result() == 3
    done.start()  # already computed here: nothing is started
    assert not done.forked and done.result() == 3


@pytest.mark.parametrize("workers", [1, 2, 3, 7])
def test_run_all_gives_every_result_in_order_whatever_the_workers(workers: int):
    # calls dealt to the workers in turn, all but the first group in children: the values
    # come back in the calls' order, the same as one after the other here
    fns = [partial(_square_pid, k) for k in range(5)]
    got = run_all(fns, workers)
    assert [v for v, _ in got] == [k * k for k in range(5)]
    here = os.getpid()
    ran_here = [pid == here for _, pid in got]
    assert ran_here == [k % min(workers, 5) == 0 for k in range(5)] or not can_fork()


def test_run_all_raises_the_error_of_a_call_in_a_child():
    with pytest.raises(ValueError, match="bad call"):
        run_all([partial(_square_pid, 1), partial(_bad_call)], 2)


def _square_pid(k: int) -> tuple[int, int]:
    return k * k, os.getpid()


def _bad_call() -> None:
    raise ValueError("bad call")
