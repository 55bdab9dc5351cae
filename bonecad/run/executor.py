"""Independent pipeline stages on the second core: a forked child process per job.

A job (a model's analysis and figures, the curves figure) needs only data that
already exists when it starts, and OpenCascade shapes cannot be pickled, so the
child is forked: it inherits every object as it is, writes its own files and
sends back only its (picklable) result. Results are identical to running the
job in the process itself; where ``fork`` is unavailable (Windows, macOS
defaults) or switched off (``[pipeline] background_jobs = false``), the job
runs at once, in the process itself.

Inside a group of jobs BLAS (OpenBLAS under numpy) runs one thread per
process: the processes already fill the two cores, and a second BLAS thread
per process only spins against the other process (measured on TLEM2: 44 s of
CPU and 27 s wall with two BLAS threads, 30 s and 20.5 s with one). It is one
thread with background jobs off too, so both ways give the same numbers (BLAS
sums in another order with more threads, and a fit to noisy MRI data can
refine differently on a last-digit difference).
"""
from __future__ import annotations

import multiprocessing
import pickle
import time
import traceback
from contextlib import contextmanager
from typing import Any, Callable, Iterator


class Job:
    """A started job; ``result()`` waits for it and returns (value, seconds it took)."""

    def __init__(self, fn: Callable[..., Any], args: tuple, kwargs: dict, background: bool):
        self._name = getattr(fn, "__name__", "job")
        self._process = None
        if not background:
            start = time.perf_counter()
            self._value = fn(*args, **kwargs)
            self._seconds = time.perf_counter() - start
            return
        ctx = multiprocessing.get_context("fork")
        self._receive, send = ctx.Pipe(duplex=False)
        # not a daemon: a job may start jobs of its own (the frame-and-curves job fits the
        # proximal curves beside the distal ones); ``jobs`` stops every child it started
        self._process = ctx.Process(target=_run, args=(send, fn, args, kwargs), daemon=False)
        self._process.start()
        send.close()

    def terminate(self) -> None:
        """Stop the child if it is still running (its result is not wanted any more)."""
        if self._process is not None:
            self._process.terminate()
            self._process.join()
            self._receive.close()
            self._process = None

    def result(self) -> tuple[Any, float]:
        if self._process is None:
            return self._value, self._seconds
        try:
            ok, value, seconds = self._receive.recv()
        except EOFError:
            self._process.join()
            raise RuntimeError(f"background job {self._name} died (exit code {self._process.exitcode})") from None
        finally:
            self._receive.close()
        self._process.join()
        self._process = None
        if not ok:
            raise value
        self._value, self._seconds = value, seconds
        return value, seconds


def _run(send, fn, args, kwargs) -> None:
    start = time.perf_counter()
    try:
        message = (True, fn(*args, **kwargs), time.perf_counter() - start)
    except BaseException as exc:  # sent back and raised in the parent
        message = (False, exc, time.perf_counter() - start)
    try:
        send.send(message)
    except (pickle.PicklingError, TypeError, AttributeError):
        text = "".join(traceback.format_exception(message[1])) if not message[0] else "unpicklable result"
        send.send((False, RuntimeError(f"background job {fn.__name__}: {text}"), message[2]))
    send.close()


def can_fork() -> bool:
    return "fork" in multiprocessing.get_all_start_methods()


class JobGroup:
    """Jobs started together; see ``jobs``."""

    def __init__(self, background: bool):
        self.background = background and can_fork()
        self._jobs: list[Job] = []

    def start(self, fn: Callable[..., Any], *args, **kwargs) -> Job:
        """Start ``fn(*args, **kwargs)`` in a forked child (or, without background jobs, run it now)."""
        job = Job(fn, args, kwargs, self.background)
        self._jobs.append(job)
        return job


@contextmanager
def jobs(background: bool = True) -> Iterator[JobGroup]:
    """A group of jobs whose children are stopped when the block ends before their results are taken
    (an error in the parent: no child goes on writing into an output folder that is being removed).

    BLAS runs single-threaded inside the block (children inherit it)."""
    from threadpoolctl import threadpool_limits

    group = JobGroup(background)
    with threadpool_limits(limits=1, user_api="blas"):
        try:
            yield group
        finally:
            for job in group._jobs:
                job.terminate()
