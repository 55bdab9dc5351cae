"""All-or-nothing output folders.

A command writes every file into a hidden staging folder beside ``DIR``; only
when the whole command succeeds are the files moved into ``DIR``. On any
failure (and on SIGINT/SIGTERM, which the CLI turns into exceptions) the
staging folder is removed, so no partial output is ever left. A process
killed outright (SIGKILL) cannot clean up: its staging folder carries its
process id, and the next run into the same ``DIR`` removes it. The removal itself
cannot be cut short by a signal (``interrupts_deferred``).
"""
from __future__ import annotations

import glob
import os
import shutil
import signal
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from collections.abc import Iterator


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: the signals the CLI turns into exceptions (Ctrl-C, SIGTERM)
_INTERRUPTS = {signal.SIGINT, signal.SIGTERM}


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """A block that SIGINT and SIGTERM cannot interrupt halfway: a signal that arrives inside it is noted and
    raised again, to the handler it would have met, when the block ends. For short bookkeeping whose half-done
    state would leave something behind: a child forked but not yet owned, children half stopped, a staging
    folder half removed. (Held by Python handlers, not by the thread's signal mask: the kernel hands a
    process's signal to any thread that does not block it, BLAS's among them.) Outside the main thread, which
    alone runs Python's signal handlers, it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: arrived.append(signum)) for s in _INTERRUPTS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for signum in arrived:
            signal.raise_signal(signum)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _remove_orphans(parent: Path, name: str) -> None:
    """Remove staging folders of ``name`` left by processes that no longer run (killed outright)."""
    prefix = f".{name}.staging-"
    for folder in parent.glob(f"{glob.escape(prefix)}*"):
        pid = folder.name[len(prefix):].split("-", 1)[0]
        if folder.is_dir() and pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)


@contextmanager
def staged_output(out_dir: str | Path) -> Iterator[Path]:
    """Yield a staging folder; on success move its files into ``out_dir`` (created if needed)."""
    out_dir = Path(out_dir)
    parent = out_dir.resolve().parent
    parent.mkdir(parents=True, exist_ok=True)
    _remove_orphans(parent, out_dir.name)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.staging-{os.getpid()}-", dir=parent))
    try:
        yield staging
        out_dir.mkdir(parents=True, exist_ok=True)
        for item in sorted(staging.iterdir()):
            target = out_dir / item.name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            os.replace(item, target)
    finally:
        with interrupts_deferred():
            shutil.rmtree(staging, ignore_errors=True)


@contextmanager
def staged_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success."""
    path = Path(path)
    path.resolve().parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.resolve().parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
