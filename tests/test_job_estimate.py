"""Estimates that do not mislead (issue 49 §8): the seconds per iteration a print run logs are those of one of its
own iterations (timed, not guessed from a probe), the rest of the job is given with them, a change of pace is
logged again, and a count of iterations that cannot end within a year is refused before any work."""
import re
import time
from types import SimpleNamespace

import pytest

from torch_appearance.pipelines.print import PrintConfig, optimize_print
from torch_appearance.pipelines.print import loop as print_loop
from torch_appearance.pipelines.print.loop import duration_text, job_estimate
from torch_appearance.testing import run_command, tiny_print_target

TOOK = re.compile(r"^optimize_print: (?:iteration (\d+) took|iterations (\d+)-(\d+) took) (\S+) s(?: each)? at "
                  r"(\d+) spp; the rest of the job about (\S+) (s|min|h|days|years) \((\d+) iterations of \S+ s, "
                  r"(\d+) evaluations of \S+ s, the results \S+ s\)$")


def _cfg(tmp_path, **kw):
    base = dict(target=tiny_print_target(tmp_path / "t.exr"), thickness_mm=0.34, spp=2, eval_spp=4, eval_every=5,
                table_steps=2, iterations=6, out=str(tmp_path / "run"), seed=5)
    base.update(kw)
    return PrintConfig(**base)


@pytest.mark.parametrize("estimator,timed", [("ema", 2), ("plain", 1)])
def test_the_logged_iteration_time_is_the_runs_own(tmp_path, monkeypatch, estimator, timed):
    """One line after the first iteration that walks as the later ones (the second with ``ema``, whose first
    iteration also replays): its seconds are within 2× of that iteration's time in log.csv, and the rest of the job
    counts the iterations and evaluations left."""
    lines = []
    optimize_print(_cfg(tmp_path, estimator=estimator), progress=False, log=lines.append)
    took = [m for m in map(TOOK.match, lines) if m]
    assert len(took) == 1, lines
    m = took[0]
    assert int(m.group(1)) == timed and int(m.group(5)) == 2
    assert int(m.group(8)) == 6 - timed and int(m.group(9)) == 2  # evaluations at 5 and 6
    import csv
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    logged = float(rows[timed]["wall_s"]) - float(rows[timed - 1]["wall_s"]) if timed > 1 else None
    if logged is not None:  # the row's wall time: from the previous row's to this one's
        assert 0.5 * logged <= float(m.group(4)) <= 2 * logged, (m.group(4), logged)
    assert not any("per iteration" in line for line in lines)  # no probe's guess before the run


def test_a_change_of_pace_is_logged_again(tmp_path, monkeypatch):
    """Iterations that become much slower than the one timed (the mixture's paths grew) are logged again after
    ``PACE_WINDOW`` iterations, with the rest of the job at the new pace (the loop's clock advanced by the steps:
    0.01 s for the first two, 10 s after)."""
    real_step, offset, calls = print_loop._Run.step, [0.0], []

    def step(self, seed, record):
        calls.append(seed)
        offset[0] += 0.01 if len(calls) <= 2 else 10.0
        return real_step(self, seed, record)

    monkeypatch.setattr(print_loop, "time", SimpleNamespace(perf_counter=lambda: time.perf_counter() + offset[0]))
    monkeypatch.setattr(print_loop._Run, "step", step)
    monkeypatch.setattr(print_loop, "PACE_WINDOW", 3)
    lines = []
    optimize_print(_cfg(tmp_path, iterations=8, eval_every=8), progress=False, log=lines.append)
    took = [m for m in map(TOOK.match, lines) if m]
    assert [(m.group(1), m.group(2), m.group(3)) for m in took] == [("2", None, None), (None, "3", "5")], lines
    assert float(took[0].group(4)) < 5 <= float(took[1].group(4))
    assert int(took[1].group(8)) == 3 and took[1].group(7) == "s" and float(took[1].group(6)) >= 30


def test_job_estimate_counts_what_is_left():
    assert job_estimate(300, 2, 50, 0.5, 2.0, 4.0)[0] == 298 * 0.5 + 6 * 2.0 + 4.0
    assert job_estimate(7, 2, 5, 1.0, 10.0, 0.0)[0] == 5 + 2 * 10.0  # at 5 and at the end (7)
    assert job_estimate(10, 5, 5, 1.0, 10.0, 0.0)[0] == 5 + 10.0  # 5 was evaluated already
    assert duration_text(90) == "90 s" and duration_text(3 * 3600) == "3 h" and duration_text(4e9).endswith("years")


def test_iterations_that_cannot_end_within_a_year_are_refused(tmp_path):
    out = tmp_path / "run"
    rc, stdout, err = run_command("optimize_print", "--target", tiny_print_target(tmp_path / "t.exr"),
                                  "--iterations", str(10 ** 12), "--out", out, "--quiet")
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert re.match(r"^ta-optimize-print: error: --iterations: 1000000000000 iterations take at least 31\.7 years "
                    r"\(an iteration takes at least 1 ms\); expected a job under a year", err), err
    assert not out.exists() and stdout == ""
    PrintConfig(iterations=10 ** 9).validate()  # 11.6 days at the least: admitted, its time is logged once timed
