"""Executors: where the runner's jobs run. The only module that starts processes.

``InProcess`` runs a job at once, in this process. ``Fork`` runs each job in a
forked child on the second core: the child inherits every object as it is
(meshes, OpenCascade shapes, imported modules), so only its result crosses
back, pickled. Results are identical either way.

A ``Fork`` executor owns its children for its whole ``with`` block:

- a job that fails sends its error back and interrupts this process at once
  (SIGUSR1, repeated until this process stops it), whatever it is doing, so
  one failing job ends the run within seconds instead of when its result is
  asked for;
- leaving the block (normally, by an error, or by SIGINT/SIGTERM turned into
  exceptions by the CLI) stops every child still running (SIGTERM, then
  SIGKILL after a grace period) and waits for it;
- a child dies with this process even when this process is killed (SIGKILL):
  Linux's parent-death signal.

Inside the block BLAS (OpenBLAS under numpy) runs one thread per process: the
processes already fill the two cores, and a second BLAS thread per process
only spins against the other (measured on TLEM2: 44 s of CPU and 27 s wall
with two BLAS threads, 30 s and 20.5 s with one). It is one thread in process
too, so both ways give the same numbers (BLAS sums in another order with more
threads, and a fit to noisy MRI data can refine differently on a last-digit
difference).

No stage starts threads inside a call either (scipy's ``workers=-1``): the
processes fill the cores already, and a KeyboardInterrupt, SIGTERM or
child-failure exception raised in the main thread while it joins such threads
frees the arrays they still write (a segmentation fault, seen when Ctrl-C
landed in the T-spline fit's first closest-point search; it left the staging
folder behind). The one Python thread is ``helper_thread``'s, for the intake's
cleanup: a job there holds its own references to its arrays, so an exception
in the main thread frees none of them, and leaving the block waits for the job
it is running (a few seconds at most) and drops the ones not started.
"""
from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import pickle
import signal
import threading
import time
import traceback
from contextlib import AbstractContextManager, ExitStack, contextmanager, nullcontext
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor

from bonecad.staging import interrupts_deferred

log = logging.getLogger(__name__)

#: seconds a child is given to end after SIGTERM before it is killed
_GRACE_S = 2.0
_PR_SET_PDEATHSIG = 1
_PR_SET_THP_DISABLE, _PR_GET_THP_DISABLE = 41, 42
#: seconds between a failed child's signals to its parent
_NUDGE_S = 0.2


class Job(Protocol):
    """A submitted job."""

    name: str

    def result(self) -> Any:
        """The job's return value (waiting for it), or its exception raised here."""


class Executor(Protocol):
    """Runs jobs; a context manager that owns them until it is left."""

    def __enter__(self) -> Executor: ...

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None: ...

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Job: ...

    def shielded(self) -> AbstractContextManager[None]:
        """A block that a failing job must not interrupt (e.g. imports of C extensions, which an
        exception raised inside leaves broken); its failure is raised after the block."""
        ...


class _Done:
    """A job run in process: its value or its exception."""

    def __init__(self, fn: Callable[..., Any], args: tuple, kwargs: dict):
        self.name = getattr(fn, "__name__", "job")
        self._value: Any = None
        self._error: BaseException | None = None
        try:
            self._value = fn(*args, **kwargs)
        except Exception as exc:  # raised when the result is asked for, as from a child
            self._error = exc

    def result(self) -> Any:
        if self._error is not None:
            raise self._error
        return self._value


class InProcess:
    """Runs every job at once, in this process (no children; under Dask, in a thread, without fork)."""

    def __enter__(self) -> InProcess:
        from threadpoolctl import threadpool_limits

        self._limits = threadpool_limits(limits=1, user_api="blas")
        return self

    def __exit__(self, *exc: object) -> None:
        self._limits.unregister()

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> _Done:
        return _Done(fn, args, kwargs)

    def shielded(self) -> AbstractContextManager[None]:
        return nullcontext()


class ChildFailed(Exception):
    """Raised in the parent (by SIGUSR1) when a child job has failed; the executor replaces it by
    the child's own error when it is left."""

    def __init__(self) -> None:
        super().__init__("a background job failed")


class _Child:
    """A job in a forked child; ``result()`` waits for it."""

    def __init__(self, owner: Fork, ctx: Any, fn: Callable[..., Any], args: tuple, kwargs: dict):
        self.name = getattr(fn, "__name__", "job")
        self._owner = owner
        self._receive, send = ctx.Pipe(duplex=False)
        self._send = send
        self._process = ctx.Process(target=_child_main, args=(send, os.getpid(), fn, args, kwargs), daemon=True)
        self._message: tuple[bool, Any] | None = None

    def start(self) -> None:
        self._process.start()
        self._send.close()

    def _take(self, wait: bool) -> tuple[bool, Any] | None:
        """The child's message (None when ``wait`` is False and it has sent none yet)."""
        if self._message is None:
            if not wait and not self._receive.poll():
                return None
            try:
                self._message = self._receive.recv()
            except EOFError:
                self._process.join()
                self._message = (False, RuntimeError(
                    f"background job {self.name} died (exit code {self._process.exitcode})"))
            if self._message[0]:  # done; a failed child signals its parent until it is stopped
                self._process.join()
        return self._message

    def result(self) -> Any:
        return self._owner.wait_for(self)

    def failure(self) -> BaseException | None:
        """The child's error if it has reported one (without waiting)."""
        message = self._take(wait=False) if self._process.exitcode is not None or self._receive.poll() else None
        return None if message is None or message[0] else message[1]

    def stop(self) -> None:
        """End the child if it still runs: SIGTERM, then SIGKILL after the grace period."""
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(_GRACE_S)
            if self._process.is_alive():
                self._process.kill()
                self._process.join()
        self._receive.close()


def _child_main(send: Connection, parent: int, fn: Callable[..., Any], args: tuple, kwargs: dict) -> None:
    """A child's life: die with the parent, run the job, send (ok, value), and on failure interrupt the parent."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: the parent's exit handling still stops it
        pass
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # Ctrl-C reaches the parent, which stops its children
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    try:
        message: tuple[bool, Any] = (True, fn(*args, **kwargs))
    except Exception as exc:
        message = (False, exc)
    try:
        send.send(message)
    except (pickle.PicklingError, TypeError, AttributeError) as exc:
        text = "".join(traceback.format_exception(message[1])) if not message[0] else f"unpicklable result ({exc})"
        message = (False, RuntimeError(f"background job {getattr(fn, '__name__', 'job')}: {text}"))
        send.send(message)
    send.close()
    while not message[0]:  # nudge the parent until it stops this child (a nudge can land where Python
        os.kill(parent, signal.SIGUSR1)  # ignores exceptions, e.g. in fork's after-fork hooks)
        time.sleep(_NUDGE_S)


class Fork:
    """Runs each job in a forked child (see the module docstring). Needs ``fork`` and the main thread."""

    def __init__(self) -> None:
        self._ctx = multiprocessing.get_context("fork")
        self._children: list[_Child] = []
        self._stack = ExitStack()
        self._open = False
        self._waiting = False
        self._forking = False
        self._shielded = 0

    @staticmethod
    def available() -> bool:
        return ("fork" in multiprocessing.get_all_start_methods()
                and threading.current_thread() is threading.main_thread()
                and not multiprocessing.current_process().daemon)

    def __enter__(self) -> Fork:
        from threadpoolctl import threadpool_limits

        self._stack.enter_context(threadpool_limits(limits=1, user_api="blas"))
        previous = signal.signal(signal.SIGUSR1, self._on_child_failure)
        self._stack.callback(signal.signal, signal.SIGUSR1, previous)
        self._open = True
        return self

    def _on_child_failure(self, signum: int, frame: object) -> None:
        # while waiting the failure is read from its pipe; while forking it would land in fork's
        # own hooks, which ignore exceptions (the child signals again until it is stopped)
        if self._open and not self._waiting and not self._forking and not self._shielded:
            raise ChildFailed

    @contextmanager
    def shielded(self) -> Iterator[None]:
        """No failure is raised inside this block (a failed child signals again until it is stopped)."""
        self._shielded += 1
        try:
            yield
        finally:
            self._shielded -= 1

    def wait_for(self, child: _Child) -> Any:
        """``child``'s result; if another child reports a failure first, that failure is raised."""
        self._waiting = True
        try:
            while child._message is None:
                pending = [c for c in self._children if c._message is None]
                ready = set(wait([c._receive for c in pending]))
                for c in pending:
                    if c._receive in ready:
                        ok, value = c._take(wait=True)  # type: ignore[misc]
                        if not ok and c is not child:
                            raise value
        finally:
            self._waiting = False
        ok, value = child._message
        if not ok:
            raise value
        return value

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> _Child:
        child = _Child(self, self._ctx, fn, args, kwargs)
        self._children.append(child)  # owned before it exists: whatever happens next, it is stopped
        self._forking = True
        try:
            release_free_heap()  # what the child inherits is what this process uses
            # an interrupt raised between the fork and the child's record would leave it running unowned (and
            # writing into a staging folder already removed): held until the child is recorded
            with interrupts_deferred():
                child.start()
        finally:
            self._forking = False
        log.debug("job %s started in process %d", child.name, child._process.pid)
        return child

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        self._open = False
        failed = None
        if exc_type is ChildFailed:
            failed = next((e for e in (c.failure() for c in self._children) if e is not None), None)
        started = time.perf_counter()
        with interrupts_deferred():  # every child stopped (at most the grace period each), a second Ctrl-C or not
            for child in self._children:
                child.stop()
            self._children.clear()
            # a failure signal still in flight is ignored from here on (the handler sees _open False)
            self._stack.close()
        log.debug("children stopped in %.2f s", time.perf_counter() - started)
        if exc_type is ChildFailed:
            raise failed or RuntimeError("a background job failed without saying why") from None


def release_free_heap() -> bool:
    """Give the heap memory this process has freed back to the system (glibc's ``malloc_trim``); False where
    the C library has none. glibc keeps freed blocks below its mmap threshold for reuse: after the intake of
    TLEM2 split 16-fold (1.4 M triangles) 135 MB of 713 MB resident were such blocks."""
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except AttributeError:
        return False
    trim(ctypes.c_size_t(0))
    return True


#: glibc's ``mallopt`` parameters, and the values its dynamic thresholds settle at once large blocks were freed:
#: the mmap threshold at its 64-bit maximum (32 MB), the trim threshold twice it, mmaps at once the default
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
_GLIBC_SETTLED = ((_M_MMAP_MAX, 65536), (_M_MMAP_THRESHOLD, 32 * 2**20), (_M_TRIM_THRESHOLD, 64 * 2**20))


@contextmanager
def freed_memory_reused() -> Iterator[None]:
    """A block in which this process (and the children it forks) reuses the memory its freed arrays held
    instead of the system zeroing fresh pages for each new one (glibc's ``mallopt``: no block from ``mmap``,
    no trim of the heap's top on ``free``; ``release_free_heap`` before each fork still gives it back). When
    it ends, glibc gets the thresholds its own dynamic ones reach on a dense mesh, and the heap's free memory
    is given back. Nothing happens where the C library has no ``mallopt``.

    For the intake of a dense mesh, whose arrays are hundreds of MB each, each ``mmap``-ed and faulted in
    page by page by default: TLEM2 split 64-fold (7.7 M triangles), reading to the working copy 32.5 / 33.4
    -> 27.8 / 26.2 s wall, 14.8 / 14.6 -> 8.9 / 7.7 s of system CPU, the same peak (3.19 GB resident). Not
    for the whole run: the stages after the intake fork a job every second or so, and reused pages then cost
    copies (split 16-fold, a whole reconstruct with it: 1.4 % more wall time, 0.27 s more system CPU,
    paired)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except AttributeError:
        yield
        return
    mallopt(_M_MMAP_MAX, 0)
    mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
    try:
        yield
    finally:
        for param, value in _GLIBC_SETTLED:
            mallopt(param, value)
        release_free_heap()  # (what the block freed and kept, given back)


@contextmanager
def huge_pages(allowed: bool) -> Iterator[None]:
    """A block in which this process, and the children it forks, get transparent huge pages (2 MB) or not
    (Linux ``prctl`` PR_SET_THP_DISABLE; numpy asks for them on every array of 4 MB and more). Where the
    first touch of a page costs a hypervisor fault, a huge page faults in 2 MB of fresh memory at once
    while small ones reuse pages freed moments ago (``[pipeline] huge_pages`` has the figures). When it
    ends, the process's previous choice is back. Nothing happens where there is no such ``prctl``."""
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except AttributeError:
        yield
        return
    before = prctl(_PR_GET_THP_DISABLE, 0, 0, 0, 0)
    if before < 0 or prctl(_PR_SET_THP_DISABLE, int(not allowed), 0, 0, 0) != 0:
        yield  # (not Linux, or a kernel without the option)
        return
    try:
        yield
    finally:
        prctl(_PR_SET_THP_DISABLE, before, 0, 0, 0)


@contextmanager
def helper_thread(wanted: bool) -> Iterator[Callable[..., Future] | None]:
    """A block with a ``submit`` that runs jobs in one more thread of this process, in turn (None when not
    ``wanted``: the jobs' callers then do the work themselves).

    For work that releases the GIL on arrays this process holds (numpy's sorts, gathers and comparisons:
    the intake's cleanup, ``mesh.intake._clean``): a thread shares this process's pages, where a forked
    job's writes cost fresh or copied pages, each a hypervisor fault on a VM. TLEM2's leg split 16-fold
    (1.9 M triangles), the intake to the working copy, six alternating runs each: 5.6-8.7 s (median 6.1)
    with the cleanup's jobs forked, 4.7-5.9 s (median 5.1) in the thread, system CPU 1.9-6.6 -> 0.8-1.8 s;
    the same bits; the whole ``reconstruct``, six pairs: 19.9 -> 18.8 s wall (median; each pair 2-15 % less),
    system CPU 4.8 -> 3.3 s. Not for the working copy: ``fast_simplification`` keeps its mesh in global variables.
    The caller asks each job's result before it forks (a forked child has only the forking thread)."""
    if not wanted:
        yield None
        return
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="bonecad-helper")
    try:
        yield pool.submit
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def executor_for(background: bool) -> Executor:
    """``Fork`` when background jobs are wanted and possible, else ``InProcess``."""
    return Fork() if background and Fork.available() else InProcess()
