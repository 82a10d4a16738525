"""Ctrl-C held back while a block runs that must not be cut in two (:func:`sigint_deferred`): an optimiser step and
its bookkeeping, a set of files written together, VTK rendering (an interruption between two of pyvista's calls
into VTK leaves its objects half made, and VTK then crashes on them); and after Ctrl-C, no partial output left as if
it were whole (:func:`folder_listing` before, :func:`undo_partial` after)."""
import contextlib
import os
import shutil
import signal
import threading

__all__ = ["sigint_deferred", "folder_listing", "undo_partial"]


@contextlib.contextmanager
def sigint_deferred():
    """Hold Ctrl-C back while the block runs and raise the ``KeyboardInterrupt`` when it ends. Only in the main
    thread (elsewhere Python delivers no signals) and where Python handles SIGINT (an ignored or default SIGINT, or
    one set outside Python, is left alone).

    Example:
        >>> with sigint_deferred():
        ...     pass
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or not callable(previous):
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


def folder_listing(folder):
    """``{name: (inode, size, mtime_ns)}`` of the files in ``folder``; None when it does not exist (what a command
    that writes a folder notes before it starts, for :func:`undo_partial`)."""
    if not os.path.isdir(folder):
        return None
    entries = {}
    for entry in os.scandir(folder):
        if entry.is_file(follow_symlinks=False):
            stat = entry.stat(follow_symlinks=False)
            entries[entry.name] = (stat.st_ino, stat.st_size, stat.st_mtime_ns)
    return entries


def undo_partial(folder, before, what):
    """After Ctrl-C: no partial ``what`` (e.g. "fit") is left as if it were one. A folder the command created
    (``before`` None, :func:`folder_listing`) is removed; in an existing one the files it added are removed, and when
    it had already replaced files of an earlier ``what``, that one's ``summary.json`` goes too (a folder holds a
    whole ``what`` exactly when it holds summary.json, written last). Returns what was kept, for
    :func:`interrupted`'s line."""
    if before is None:
        shutil.rmtree(folder, ignore_errors=True)
        return "nothing was written (start it again)"
    after = folder_listing(folder) or {}
    for name in set(after) - set(before):
        with contextlib.suppress(OSError):
            os.remove(os.path.join(folder, name))
    replaced = sorted(name for name in set(after) & set(before) if after[name] != before[name])
    if not replaced:
        return f"{folder!r} is as it was (start it again)"
    dropped = ""
    if "summary.json" in before and "summary.json" not in replaced:
        with contextlib.suppress(OSError):
            os.remove(os.path.join(folder, "summary.json"))
        dropped = ": its summary.json is removed"
    return (f"the earlier {what} in {folder!r} was partly replaced ({', '.join(replaced[:3])}"
            f"{', ...' if len(replaced) > 3 else ''}) and is incomplete{dropped}; start it again to redo it")
