"""Progress bars that suit where they are written: tqdm's bar on a terminal, whole lines anywhere else.

tqdm redraws its bar with a carriage return at every refresh; written into a log file or a pipe that is 157 kB of
returns for one print run (issue 49). :func:`progress_bar` gives such a stream one line each time the count passes
another few percent of the total (:class:`LineProgress`) and a terminal tqdm's own bar. Both are :class:`tqdm.tqdm`
objects: ``update``, ``set_postfix``, ``close``, iteration, ``with`` and ``write`` work as in tqdm.

Example:
    >>> import io
    >>> log = io.StringIO()                                     # not a terminal
    >>> with progress_bar(total=1000, desc="layers", file=log, step_percent=25) as bar:
    ...     for _ in range(1000):
    ...         _ = bar.update(1)
    >>> [line.split("%")[0] for line in log.getvalue().splitlines()]
    ['layers:   0', 'layers:  25', 'layers:  50', 'layers:  75', 'layers: 100']
    >>> "\\r" in log.getvalue()
    False
"""
import sys

from tqdm import tqdm

__all__ = ["progress_bar", "LineProgress"]

#: one line of a bar with a total: tqdm's left and right parts without the bar between them
LINE_FORMAT = "{percentage:3.0f}% {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]"


def is_terminal(stream):
    """Whether ``stream`` is an open terminal (``isatty``); False for files, pipes, closed or unusual streams."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


class _Silent:
    """The stream tqdm's own drawing (carriage returns, clears, cursor moves) goes to in a :class:`LineProgress`."""

    encoding = "utf-8"

    def write(self, text):
        return len(text)

    def flush(self):
        pass


class LineProgress(tqdm):
    """A tqdm bar that writes whole lines to ``stream``: one when it starts, one each time the count passes another
    ``step_percent`` of ``total`` (every ``interval_s`` seconds when there is no total) and the last state when it
    closes; never a carriage return or a cursor movement. Rates are averages over the whole bar.

    Args:
        iterable, total, desc, unit, leave, ...: as :class:`tqdm.tqdm` (``file`` is replaced by ``stream``).
        stream: where the lines go (a log file, a pipe); written and flushed line by line.
        step_percent: percent of ``total`` between lines, in (0, 100]: at most ``100 / step_percent + 2`` lines.
        interval_s: seconds between lines when the total is unknown, > 0.

    Raises:
        ValueError: ``step_percent`` or ``interval_s`` out of range.
    """

    def __init__(self, iterable=None, *args, stream, step_percent=5.0, interval_s=30.0, **kwargs):
        if not 0 < step_percent <= 100:
            raise ValueError(f"step_percent: expected a percentage in (0, 100], got {step_percent!r}")
        if not interval_s > 0:
            raise ValueError(f"interval_s: expected seconds > 0, got {interval_s!r}")
        self._stream, self._step, self._interval = stream, float(step_percent), float(interval_s)
        self._shown = None  # (count, mark) of the latest line
        kwargs.pop("file", None)
        kwargs.setdefault("smoothing", 0)    # the average rate: a line stands for a whole stretch of the run
        kwargs.setdefault("mininterval", 0)  # every update is looked at; a line is written only at a new step
        super().__init__(iterable, *args, file=_Silent(), **kwargs)

    def _mark(self):
        """Which step (of the total) or interval (of the time) the bar is in."""
        if self.total:
            return int(100.0 * self.n / self.total // self._step)
        start = getattr(self, "start_t", None)  # tqdm's first refresh comes before it sets its start time
        return 0 if start is None else int((self._time() - start) // self._interval)

    def _write_line(self, mark):
        self._shown = (self.n, mark)
        d = self.format_dict
        meter = self.format_meter(**{**d, "prefix": "", "ncols": None,
                                     "bar_format": LINE_FORMAT if d["total"] else None})
        head = self.desc if not self.desc or self.desc.endswith(": ") else self.desc + ": "
        self._stream.write(f"{head}{meter}\n")
        self._stream.flush()

    def display(self, msg=None, pos=None):
        """tqdm's refresh: a line when the bar entered a new step; a clear (``msg=''``) is ignored (a line in a log
        stays)."""
        if msg is None:
            mark = self._mark()
            if self._shown is None or mark > self._shown[1]:
                self._write_line(mark)
        return True

    def close(self):
        if not getattr(self, "disable", True) and (self._shown is None or self._shown[0] != self.n):
            self._write_line(self._mark())  # the last state, once
        super().close()


def progress_bar(iterable=None, *, total=None, desc=None, unit="it", disable=False, leave=True, file=None,
                 step_percent=5.0, interval_s=30.0, **kwargs):
    """A progress bar on ``file`` (default ``sys.stderr``): tqdm's bar when it is a terminal, else a
    :class:`LineProgress` (one line per ``step_percent`` of ``total``, no carriage returns).

    Args:
        iterable: optional, to iterate over with progress (its ``len`` is the total when it has one).
        total: the count at the end (None: unknown, or ``len(iterable)``). desc: the label. unit: what is counted.
        disable: True for no bar at all; None for a bar only on a terminal (as tqdm).
        leave: keep tqdm's bar on the terminal when it closes (a log's lines always stay).
        file: the stream; default ``sys.stderr`` at the time of the call.
        step_percent, interval_s: see :class:`LineProgress`. kwargs: further :class:`tqdm.tqdm` arguments.

    Returns:
        a :class:`tqdm.tqdm` (a :class:`LineProgress` when ``file`` is not a terminal).
    """
    stream = sys.stderr if file is None else file
    terminal = is_terminal(stream)
    if disable is None:
        disable = not terminal
    if disable or terminal:
        return tqdm(iterable, total=total, desc=desc, unit=unit, disable=bool(disable), leave=leave, file=stream,
                    **kwargs)
    return LineProgress(iterable, total=total, desc=desc, unit=unit, leave=leave, stream=stream,
                        step_percent=step_percent, interval_s=interval_s, **kwargs)
