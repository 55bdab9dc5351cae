"""The Dask executor: jobs on a Dask cluster. With ``executor.py`` the only module that starts processes.

``DaskExecutor`` has the ``Executor`` protocol of ``run/executor.py`` (``submit``
returns a job with ``.result()``; the ``with`` block owns the cluster). It runs
on a local cluster of worker processes with one thread each (the default), or
on an existing scheduler (``scheduler="tcp://host:8786"``) whose workers may be
on other machines. Jobs and their results cross processes pickled (stage
inputs and results pickle; no stage forks).

- A worker process that dies while running a job (killed, out of memory, a
  crash in C) has the job run again on another worker; a job that has taken
  down ``allowed_failures`` + 1 workers ends with ``KilledWorker`` (the local
  cluster's scheduler; an existing scheduler keeps its own setting).
- ``running()`` says how long each job has been running, and on which worker;
  ``stop(job, worker)`` cancels a job and restarts its worker process (a thread
  cannot be stopped), so a job that hangs cannot hold the run.
- Leaving the block (normally, on an error, or on SIGINT/SIGTERM turned into
  exceptions by the CLI) closes the client and the local cluster: no worker
  process is left. Local workers also die with this process when it is killed
  outright (Dask's nanny watches its parent; the worker watches the nanny).
"""
from __future__ import annotations

import logging
import os
import uuid
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, ExitStack, nullcontext
from dataclasses import dataclass
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from bonecad.errors import InputError

log = logging.getLogger(__name__)

#: seconds to connect to an existing scheduler, and given to the client and the local cluster to close
_CONNECT_S = 10.0
_CLOSE_S = 10.0


@dataclass(frozen=True)
class Running:
    """A job running on a worker: the worker's address and the seconds since the job started there."""

    worker: str
    seconds: float


class DaskJob:
    """A job submitted to the cluster (its Dask future); ``result()`` waits for it."""

    def __init__(self, name: str, future: Any):
        self.name = name
        self.future = future

    @property
    def key(self) -> str:
        return str(self.future.key)

    def result(self) -> Any:
        return self.future.result()


def _running_jobs(dask_worker: Any) -> dict[str, float]:
    """On a worker: key -> seconds since the task started, of every task executing there."""
    from distributed.metrics import time

    now = time()
    tasks = dask_worker.state.tasks
    return {str(key): now - tasks[key].start_time for key in list(dask_worker.active_keys)
            if key in tasks and tasks[key].start_time is not None}


class _MainThreadImports(WorkerPlugin):
    """A Dask worker plugin: on each worker (those there and those that join), imports in the worker's main
    thread (its event loop's) the libraries that must not first load in a task's thread. pymeshlab loaded in a
    thread other than the main one, then used there (MeshLab's repairs of a mesh), makes the process abort as
    it exits (glibc: "malloc_consolidate(): unaligned fastbin chunk detected"): measured, 5 of 70 such
    processes, 0 of 80 with pymeshlab imported in the main thread first; on a local cluster making 40 phantom
    tibias, one worker of two aborted at every close (5 runs), none with this plugin."""

    name = "bonecad-main-thread-imports"

    def setup(self, worker: Any) -> None:
        import pymeshlab  # noqa: F401


def local_cpus() -> int:
    """The CPU cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


class DaskExecutor:
    """Runs jobs on a Dask cluster (see the module docstring).

    workers : local worker processes (one thread each; 0: one per CPU core); ignored with ``scheduler``.
    scheduler : address of an existing scheduler, e.g. ``tcp://10.0.0.5:8786``; None for a local cluster.
    retries : times a job that raised is run again (Dask ``retries``).
    allowed_failures : worker deaths a job may cause before it ends with ``KilledWorker`` (local cluster).
    """

    def __init__(self, *, workers: int = 0, scheduler: str | None = None, retries: int = 0,
                 allowed_failures: int = 3):
        self.workers = workers if workers > 0 else local_cpus()
        self.scheduler = scheduler
        self.retries = retries
        self.allowed_failures = allowed_failures
        self._stack = ExitStack()
        self.client: Any = None

    def __enter__(self) -> DaskExecutor:
        import dask
        from distributed import Client, LocalCluster

        try:
            if self.scheduler is not None:
                try:
                    self.client = self._stack.enter_context(Client(self.scheduler, timeout=_CONNECT_S))
                except (OSError, TimeoutError) as exc:
                    raise InputError(f"cannot reach the Dask scheduler ({type(exc).__name__}: {exc})",
                                     self.scheduler) from None
                log.info("Dask scheduler %s: %d workers, %d threads", self.scheduler,
                         len(self.client.scheduler_info()["workers"]), sum(self.client.nthreads().values()))
            else:
                # the workers' statistical profiler samples every thread each 10 ms: measured, a third of a
                # bone's CPU for nothing the run reads. Dask starts its workers with glibc's trim threshold at
                # 64 kB (MALLOC_TRIM_THRESHOLD_), which also fixes glibc's mmap threshold: every freed array
                # goes back to the system and the next one faults in fresh pages (measured in one process on
                # 3 phantom tibias: 2.1 M page faults and 4-6 s of system CPU a bone, against 0.1 M and
                # 0.3-0.6 s with glibc's own thresholds); unset, glibc's dynamic thresholds apply
                with dask.config.set({"distributed.scheduler.allowed-failures": self.allowed_failures,
                                      "distributed.worker.profile.enabled": False,
                                      "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
                    cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                           dashboard_address=":0", silence_logs=logging.ERROR)
                self._stack.callback(cluster.close, timeout=_CLOSE_S)
                self.client = self._stack.enter_context(Client(cluster))
                log.info("local Dask cluster: %d worker processes, one thread each", self.workers)
            self.client.register_plugin(_MainThreadImports())
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        self._stack.close()
        self.client = None

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> DaskJob:
        name = getattr(fn, "__name__", "job")
        future = self.client.submit(fn, *args, key=f"{name}-{uuid.uuid4().hex}", pure=False, retries=self.retries,
                                    **kwargs)
        return DaskJob(name, future)

    def shielded(self) -> AbstractContextManager[None]:
        return nullcontext()  # a failing job never interrupts this process: its error comes with its result

    def done(self, jobs: Sequence[DaskJob], timeout_s: float) -> list[DaskJob]:
        """The jobs of ``jobs`` that have ended (with a result or an error), waiting at most ``timeout_s``
        for the first one."""
        from distributed import wait

        try:
            wait([j.future for j in jobs], timeout=timeout_s, return_when="FIRST_COMPLETED")
        except TimeoutError:
            return []
        return [j for j in jobs if j.future.done()]

    def running(self) -> dict[str, Running]:
        """Job key -> where and for how long it has been running (workers that do not answer are left out)."""
        answers = self.client.run(_running_jobs, on_error="return")
        return {key: Running(worker, seconds) for worker, jobs in answers.items() if isinstance(jobs, dict)
                for key, seconds in jobs.items()}

    def stop(self, job: DaskJob, worker: str) -> None:
        """Cancel ``job`` and restart the worker process running it (only a worker with a nanny restarts;
        another keeps running the job's thread, its result discarded)."""
        self.client.cancel([job.future], force=True)
        status = self.client.restart_workers([worker], raise_for_error=False)
        log.info("worker %s restarted: %s", worker, status.get(worker, status))
