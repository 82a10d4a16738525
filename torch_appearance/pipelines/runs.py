"""What every long run needs from its machine and its run folder: an exclusive lock on the folder while the run
writes to it (:func:`lock_run_folder`), the memory it may use (:func:`available_memory_bytes`, :func:`check_memory`),
Ctrl-C held back while a step's state is written (:func:`sigint_deferred`), and the interruption that says how to
resume (:class:`RunInterrupted`)."""
import contextlib
import os
import signal
import threading

__all__ = ["RunInterrupted", "lock_run_folder", "available_memory_bytes", "check_memory", "sigint_deferred"]

GiB = float(1 << 30)


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) during a run, after its checkpoint was written: the message says where and how to resume.

    Attributes:
        folder: the run folder. iteration: iterations done and saved in its checkpoint.
    """

    def __init__(self, message, folder, iteration):
        super().__init__(message)
        self.folder, self.iteration = folder, iteration


@contextlib.contextmanager
def lock_run_folder(folder, name="out"):
    """Create ``folder`` if needed and hold an exclusive lock on it while the ``with`` block runs: a second run on
    the same folder (another process, or another thread) is refused at once instead of mixing its files with the
    first's. The lock is ``flock`` on the folder itself (no lock file is left behind) and goes with the process,
    so a killed run never leaves the folder locked. Without ``fcntl`` (Windows) the folder is not locked.

    Raises:
        ValueError: naming ``name``, when another run holds the folder.
    """
    os.makedirs(folder, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"{name}: {folder!r} is in use by another run (it holds the folder's lock); wait for "
                             f"it to end or choose another folder") from None
        yield
    finally:
        os.close(fd)  # releases the lock


def available_memory_bytes():
    """Memory a new allocation can get without swapping: ``MemAvailable`` of /proc/meminfo (Linux), else the
    physical memory; None when neither is known."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # pragma: no cover - no sysconf
        return None


def check_memory(name, need_bytes, what, fix, available=None):
    """Refuse work that would not fit in memory, before anything is written.

    Args:
        name: the argument to blame. need_bytes: the estimate. what: what needs it ("a 1644×1644×12 slab").
        fix: what to change. available: bytes available (default :func:`available_memory_bytes`).

    Raises:
        ValueError: ``"{name}: {what} needs about X GiB of memory, this machine has Y GiB available; {fix}"``.
    """
    available = available_memory_bytes() if available is None else available
    if available is not None and need_bytes > available:
        raise ValueError(f"{name}: {what} needs about {need_bytes / GiB:.1f} GiB of memory, this machine has "
                         f"{available / GiB:.1f} GiB available; {fix}")


@contextlib.contextmanager
def sigint_deferred():
    """Hold Ctrl-C back while the block runs (an optimiser step and its bookkeeping: a checkpoint written after an
    interruption must not see half of them) and raise the ``KeyboardInterrupt`` when it ends. Only in the main thread
    (elsewhere Python delivers no signals)."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is None:  # None: not set from Python
        yield
        return
    pending = []
    signal.signal(signal.SIGINT, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if pending:
        raise KeyboardInterrupt
