"""Ctrl-C held back while a block runs that must not be cut in two (:func:`sigint_deferred`): an optimiser step and
its bookkeeping, a set of files written together, VTK rendering (an interruption between two of pyvista's calls
into VTK leaves its objects half made, and VTK then crashes on them)."""
import contextlib
import signal
import threading

__all__ = ["sigint_deferred"]


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
