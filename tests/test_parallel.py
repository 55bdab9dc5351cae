"""Background jobs (bonecad.run.executor): same results as in-process, errors come back, no orphan children."""
import os
import time

import numpy as np
import pytest

from bonecad.run import executor as parallel
from bonecad.errors import InputError


def _stats(values: np.ndarray, scale: float) -> dict:
    return {"sum": float(values.sum() * scale), "pid": os.getpid()}


def _fails(path: str):
    raise InputError("no bone in this volume", path)


def _sleeps_then_writes(path: str) -> None:
    time.sleep(3.0)
    with open(path, "w") as fh:
        fh.write("late")


@pytest.mark.skipif(not parallel.can_fork(), reason="fork is not available on this platform")
def test_a_background_job_returns_what_the_function_returns_in_a_child():
    values = np.arange(1000.0)
    with parallel.jobs(True) as group:
        job = group.start(_stats, values, scale=2.0)
        result, seconds = job.result()
    assert result["sum"] == _stats(values, 2.0)["sum"]
    assert result["pid"] != os.getpid()
    assert seconds >= 0


def test_without_background_jobs_the_function_runs_in_the_process():
    with parallel.jobs(False) as group:
        result, _ = group.start(_stats, np.ones(3), scale=1.0).result()
    assert result == {"sum": 3.0, "pid": os.getpid()}


@pytest.mark.parametrize("background", [True, False])
def test_an_error_in_a_job_is_raised_by_result(background):
    with parallel.jobs(background) as group:
        if background:
            job = group.start(_fails, "ct.nii")
            with pytest.raises(InputError, match="ct.nii: no bone in this volume"):
                job.result()
        else:
            with pytest.raises(InputError, match="no bone"):
                group.start(_fails, "ct.nii")


@pytest.mark.skipif(not parallel.can_fork(), reason="fork is not available on this platform")
def test_a_job_left_running_when_the_block_fails_is_stopped(tmp_path):
    target = tmp_path / "late.txt"
    with pytest.raises(RuntimeError, match="parent failed"):
        with parallel.jobs(True) as group:
            group.start(_sleeps_then_writes, str(target))
            raise RuntimeError("parent failed")
    time.sleep(3.5)
    assert not target.exists()


def _blas_threads() -> list[int]:
    from threadpoolctl import threadpool_info

    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


@pytest.mark.skipif(not parallel.can_fork(), reason="fork is not available on this platform")
@pytest.mark.parametrize("background", [True, False])
def test_blas_is_single_threaded_in_a_group_of_jobs(background):
    before = _blas_threads()
    with parallel.jobs(background) as group:
        assert set(_blas_threads()) == {1}
        assert set(group.start(_blas_threads).result()[0]) == {1}  # a forked child too
    assert _blas_threads() == before


def _nested(values: np.ndarray) -> dict:
    with parallel.jobs(True) as group:
        return group.start(_stats, values, scale=3.0).result()[0]


@pytest.mark.skipif(not parallel.can_fork(), reason="fork is not available on this platform")
def test_a_background_job_may_start_jobs_of_its_own():
    with parallel.jobs(True) as group:
        result, _ = group.start(_nested, np.arange(10.0)).result()
    assert result["sum"] == 135.0 and result["pid"] != os.getpid()
