"""Progress bars for non-terminals (issue 49): a log file or a pipe gets a bounded number of whole lines, never a
carriage return; a terminal gets tqdm's bar."""
import io
import os
import subprocess
import sys

import pytest
from tqdm import tqdm

from torch_appearance.progress import LineProgress, progress_bar

_BARS = """
import sys
from torch_appearance.progress import progress_bar

with progress_bar(total=5000, desc="layers", unit="layer") as bar:      # a count with a total, many updates
    for i in range(5000):
        bar.update(1)
        if i % 50 == 0:
            bar.set_postfix(loss=f"{1 / (1 + i):.3g}")
        if i == 2500:
            bar.write("a message between the lines", file=sys.stderr)
for _ in progress_bar(range(3000), desc="iterable", leave=False):       # an iterable, cleared at the end by tqdm
    pass
bar = progress_bar(desc="no total", interval_s=60)                       # no total: a line per minute
for _ in range(20):
    bar.update(7)
bar.close()
"""


def test_a_bar_into_a_file_writes_bounded_whole_lines(tmp_path):
    """stderr redirected to a file (not a terminal): no carriage return or escape sequence; one line per 5 % of the
    total (21 at most) and the last state; the message written between them stays on its own line."""
    log = tmp_path / "stderr.log"
    with open(log, "w") as handle:
        done = subprocess.run([sys.executable, "-c", _BARS], stdout=subprocess.PIPE, stderr=handle, text=True,
                              env=dict(os.environ, OMP_NUM_THREADS="1"), timeout=300)
    text = log.read_text()
    assert done.returncode == 0, text
    assert "\r" not in text and "\x1b" not in text, repr(text[:300])
    lines = text.splitlines()
    layers = [line for line in lines if line.startswith("layers: ")]
    iterable = [line for line in lines if line.startswith("iterable: ")]
    untotalled = [line for line in lines if line.startswith("no total: ")]
    assert 2 <= len(layers) <= 21 and 2 <= len(iterable) <= 21, lines
    assert [int(line.split("%")[0].split()[-1]) for line in layers] == sorted(
        int(line.split("%")[0].split()[-1]) for line in layers)               # percentages only grow
    assert layers[-1].startswith("layers: 100% 5000/5000") and "loss=" in layers[-1]
    assert iterable[-1].startswith("iterable: 100% 3000/3000")
    assert len(untotalled) == 2 and untotalled[-1].startswith("no total: 140it")     # the start and the end
    assert "a message between the lines" in lines
    assert len(lines) == len(layers) + len(iterable) + len(untotalled) + 1   # nothing else, no blank lines


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_terminal_gets_tqdms_bar_and_disable_writes_nothing():
    terminal = _Terminal()
    bar = progress_bar(total=10, desc="x", file=terminal)
    assert type(bar) is tqdm
    bar.update(10)
    bar.close()
    assert "\r" in terminal.getvalue()
    log = io.StringIO()
    for disable in (True, None):   # None: tqdm's "only on a terminal"
        bar = progress_bar(total=10, file=log, disable=disable)
        bar.update(10)
        bar.close()
    assert log.getvalue() == ""
    bar = progress_bar(total=10, file=log)
    assert isinstance(bar, LineProgress)
    bar.close()


def test_line_progress_steps(tmp_path):
    log = io.StringIO()
    with progress_bar(total=7, desc="ink", file=log, step_percent=50) as bar:
        for _ in range(7):
            bar.update(1)
    percents = [line.split("%")[0] for line in log.getvalue().splitlines()]
    assert percents == ["ink:   0", "ink:  57", "ink: 100"]
    with pytest.raises(ValueError, match=r"step_percent: expected a percentage in \(0, 100\], got 0"):
        progress_bar(total=3, file=io.StringIO(), step_percent=0)
    with pytest.raises(ValueError, match="interval_s: expected seconds > 0, got -1"):
        progress_bar(file=io.StringIO(), interval_s=-1)


def test_commands_and_scripts_take_their_bars_from_progress_bar():
    """No command, pipeline or evaluation script builds a tqdm bar itself (a log that is not a terminal would get
    carriage returns): every bar comes from :func:`torch_appearance.progress.progress_bar`; only progress.py
    imports tqdm (read from each file's syntax)."""
    import ast

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    offenders = []
    for folder in ("torch_appearance", "scripts"):
        for base, _, files in os.walk(os.path.join(root, folder)):
            for name in files:
                path = os.path.join(base, name)
                if not name.endswith(".py") or path.endswith(os.path.join("torch_appearance", "progress.py")):
                    continue
                for node in ast.walk(ast.parse(open(path, encoding="utf-8").read())):
                    names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                             [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                    if any(n == "tqdm" or n.startswith("tqdm.") for n in names):
                        offenders.append(f"{os.path.relpath(path, root)}:{node.lineno}")
    assert offenders == [], offenders
