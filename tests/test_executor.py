"""Executors (bonecad.run.executor): same results in a child as in process, a failing job ends the
block at once (whatever the parent is doing), and no child outlives its block or its parent."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from bonecad.errors import InputError
from bonecad.run.executor import Fork, InProcess, executor_for, helper_thread, release_free_heap

needs_fork = pytest.mark.skipif(not Fork.available(), reason="fork is not available on this platform")


def _stats(values: np.ndarray, scale: float) -> dict:
    return {"sum": float(values.sum() * scale), "pid": os.getpid()}


def _fails(path: str):
    raise InputError("no bone in this volume", path)


def _sleeps(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as fh:  # a zombie is dead
        return fh.read().split()[2] != "Z"


@needs_fork
def test_a_job_returns_what_the_function_returns_in_a_child():
    values = np.arange(1000.0)
    with Fork() as ex:
        job = ex.submit(_stats, values, scale=2.0)
        result = job.result()
    assert result["sum"] == float(values.sum() * 2.0)
    assert result["pid"] != os.getpid()


@pytest.mark.parametrize("make", [Fork, InProcess], ids=["fork", "in-process"])
def test_same_result_and_same_error_either_way(make):
    if make is Fork and not Fork.available():
        pytest.skip("fork is not available on this platform")
    with make() as ex:
        assert ex.submit(_stats, np.ones(10), scale=3.0).result()["sum"] == 30.0
    with pytest.raises(InputError, match="no bone") as info:
        with make() as ex:
            ex.submit(_fails, "/data/ct.nii").result()
    assert info.value.path == "/data/ct.nii"


@needs_fork
def test_a_failing_job_interrupts_the_parent_while_its_siblings_run():
    """The parent is busy (a long computation of its own) and a sibling job sleeps; the failing job
    ends the block within a second, with its own error, and the sibling is stopped."""
    started = time.perf_counter()
    with pytest.raises(InputError, match="no bone"):
        with Fork() as ex:
            sibling = ex.submit(_sleeps, 30.0)
            ex.submit(_fails, "/data/ct.nii")
            deadline = time.perf_counter() + 30.0
            while time.perf_counter() < deadline:  # the parent's own long work
                np.linalg.svd(np.ones((50, 50)))
    assert time.perf_counter() - started < 5.0
    assert not _alive(sibling._process.pid)


@needs_fork
def test_children_are_stopped_when_the_block_fails():
    with pytest.raises(RuntimeError, match="parent failed"):
        with Fork() as ex:
            jobs = [ex.submit(_sleeps, 30.0) for _ in range(2)]
            raise RuntimeError("parent failed")
    assert not any(_alive(job._process.pid) for job in jobs)


@needs_fork
def test_a_child_that_dies_is_an_error_not_a_hang():
    with pytest.raises(RuntimeError, match="died"):
        with Fork() as ex:
            job = ex.submit(os._exit, 3)
            job.result()


@needs_fork
def test_children_die_with_a_killed_parent(tmp_path):
    """SIGKILL of the parent cannot run any cleanup; the parent-death signal still ends the children."""
    pids = tmp_path / "pids"
    script = textwrap.dedent(f"""
        import os, time
        from bonecad.run.executor import Fork
        def sleeps():
            time.sleep(60)
        with Fork() as ex:
            jobs = [ex.submit(sleeps) for _ in range(2)]
            open({str(pids)!r}, "w").write(" ".join(str(j._process.pid) for j in jobs))
            time.sleep(60)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.time() + 30
        while not (pids.exists() and pids.read_text()) and time.time() < deadline:
            time.sleep(0.05)
        children = [int(p) for p in pids.read_text().split()]
        assert all(_alive(p) for p in children)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.time() + 5
        while any(_alive(p) for p in children) and time.time() < deadline:
            time.sleep(0.05)
        assert not any(_alive(p) for p in children)
    finally:
        parent.kill()
        for p in [int(p) for p in pids.read_text().split()] if pids.exists() and pids.read_text() else []:
            try:
                os.kill(p, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_helper_thread_runs_jobs_in_turn_and_an_error_drops_the_ones_not_started():
    """``helper_thread``: a job's result as the function's, in this process; leaving the block on an error
    waits for the running job and cancels the queued one; no thread is left; none when not wanted."""
    with helper_thread(False) as submit:
        assert submit is None
    ran = []
    with pytest.raises(KeyboardInterrupt):
        with helper_thread(True) as submit:
            assert submit(_stats, np.arange(4.0), 2.0).result() == {"sum": 12.0, "pid": os.getpid()}
            started = threading.Event()
            running = submit(lambda: started.set() or _sleeps(0.3))
            queued = submit(ran.append, 1)
            started.wait(10.0)
            raise KeyboardInterrupt
    assert running.done() and running.result() == os.getpid()
    assert queued.cancelled() and not ran
    assert not [t.name for t in threading.enumerate() if t.name.startswith("bonecad-helper")]


def test_in_process_when_fork_is_not_wanted():
    assert isinstance(executor_for(False), InProcess)


@needs_fork
def test_a_shielded_block_is_not_interrupted_and_the_failure_follows_it():
    """Imports of C extensions must not be interrupted (an exception inside leaves them broken)."""
    finished = False
    started = time.perf_counter()
    with pytest.raises(InputError, match="no bone"):
        with Fork() as ex:
            ex.submit(_fails, "/data/ct.nii")
            with ex.shielded():
                time.sleep(1.0)  # the child fails and signals meanwhile
                finished = True
            time.sleep(30.0)
    assert finished and time.perf_counter() - started < 3.0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="malloc_trim is glibc's (Linux)")
def test_freed_heap_goes_back_to_the_system_before_a_fork():
    """Memory freed on the heap (blocks below glibc's mmap threshold) leaves the resident set when released,
    as ``Fork.submit`` does before each child."""
    import psutil

    process = psutil.Process()
    blocks = [np.ones(8000) for _ in range(3000)]  # 64 kB each, 192 MB: on the heap
    del blocks[:-1]  # the last one keeps the heap's top in use
    before = process.memory_info().rss
    assert release_free_heap()
    assert before - process.memory_info().rss > 100e6


def test_large_arrays_come_from_the_heap_only_inside_freed_memory_reused():
    """Inside the block a 256 MB array lies on the heap (below the program break: reused when freed, no
    fresh pages from mmap); after it a 256 MB array is mapped apart again (above the break). In a new
    process: a long-lived one may keep free heap blocks that large from earlier work."""
    script = textwrap.dedent("""
        import ctypes
        import numpy as np
        from bonecad.run.executor import freed_memory_reused

        libc = ctypes.CDLL(None)
        libc.sbrk.restype = ctypes.c_void_p

        def on_heap() -> bool:
            array = np.ones(2**25)  # 256 MB
            return array.ctypes.data < libc.sbrk(0)

        with freed_memory_reused():
            inside = on_heap()
        print(inside, on_heap())
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "False"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="transparent huge pages are Linux's")
def test_no_huge_pages_inside_the_block_nor_in_its_children():
    """Inside ``huge_pages(False)`` the process and a child it forks are barred from transparent huge pages, and
    a 64 MB array (numpy asks for huge pages) has none; after the block the process's earlier choice is back.
    In a new process, whose flag starts cleared."""
    script = textwrap.dedent("""
        import ctypes, re
        import numpy as np
        from bonecad.run.executor import Fork, huge_pages

        prctl = ctypes.CDLL(None).prctl
        def barred() -> int:
            return prctl(42, 0, 0, 0, 0)  # PR_GET_THP_DISABLE

        def huge_kb(array) -> int:  # over the mappings the array spans (numpy's madvise splits them)
            start, end = array.ctypes.data, array.ctypes.data + array.nbytes
            with open("/proc/self/smaps") as smaps:
                lines = smaps.read().splitlines()
            kb, inside = 0, False
            for line in lines:
                span = re.match(r"([0-9a-f]+)-([0-9a-f]+) ", line)
                if span:
                    inside = int(span[1], 16) < end and start < int(span[2], 16)
                elif inside and line.startswith("AnonHugePages:"):
                    kb += int(line.split()[1])
            return kb

        with huge_pages(False):
            array = np.ones(2**23)
            with Fork() as ex:
                child = ex.submit(barred).result()
            inside = (barred(), child, huge_kb(array))
            with huge_pages(True):
                allowed = barred()
            again = barred()
        print(*inside, allowed, again, barred())
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["1", "1", "0", "0", "1", "0"]


def test_an_interrupt_inside_a_deferred_block_lands_after_it():
    """Ctrl-C during a fork, the stopping of the children or the removal of a staging folder is held until
    that bookkeeping is done, then raised."""
    from bonecad.staging import interrupts_deferred

    done = []
    # Python's own Ctrl-C handler: a test run started in the background by a non-interactive shell (CI) inherits
    # SIGINT ignored
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with interrupts_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
                done.append("the whole block")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert done == ["the whole block"]

