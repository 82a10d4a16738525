"""ta-select-inks (ink-set selection, paper Fig. 15) on a tiny slab: every combination run once on a shared
target, ranked by the final quantised CIEDE2000, finished runs skipped on a rerun, bad input → exit code 2."""
import csv
import json
import os

import pytest

from torch_appearance.fabrication.inks import INKS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def cli():
    from torch_appearance.cli import select_inks
    return select_inks


def _user_inks(path, g=0.4):
    teal = dict(INKS["cyan"].to_dict(), name="teal", albedo=[0.05, 0.9, 0.7], g=g)
    path.write_text(json.dumps([teal]))
    return str(path)


# a 4 × 6 texel ColorChecker, 2 voxel layers; 3 candidates, k = 1 → 3 runs of 3 iterations
def _tiny(out, user_inks, *extra):
    return ["--target", "colorchecker", "--width-mm", "1.5", "--dpi", "100", "--thickness-mm", "0.5",
            "--candidates", "cyan,yellow,teal", "--user-inks", user_inks, "-k", "1", "--iterations", "3",
            "--spp", "2", "--eval-spp", "4", "--eval-every", "2", "--table-steps", "2", "--seed", "5",
            "--out", str(out), *extra]


def test_selection_ranks_all_sets_and_resumes(cli, tmp_path, capsys):
    inks = _user_inks(tmp_path / "inks.json")
    out = tmp_path / "sel"
    assert cli.main(_tiny(out, inks)) == 0
    for name in ("ranking.csv", "ranking.json", "convergence.png", "summary.json", "inks.json"):
        assert (out / name).is_file(), name
    names = {"cyan", "yellow", "teal"}
    assert set(os.listdir(out / "runs")) == names
    for name in names:
        for f in ("summary.json", "log.csv", "config.json", "inks.json", "selection.json", "final.exr"):
            assert (out / "runs" / name / f).is_file(), (name, f)
        assert json.loads((out / "runs" / name / "selection.json").read_text())["inks"] == [name, "black", "white"]

    rows = list(csv.DictReader(open(out / "ranking.csv")))
    assert list(rows[0]) == cli.RANKING_FIELDS
    assert [int(r["rank"]) for r in rows] == [1, 2, 3] and {r["inks"] for r in rows} == names
    de = [float(r["dE00_mean"]) for r in rows]
    assert de == sorted(de) and all(0 < v < 100 for v in de)
    assert sorted(int(r["loss_rank"]) for r in rows) == [1, 2, 3] and all(float(r["loss_final"]) > 0 for r in rows)
    assert all(float(r["seconds"]) > 0 and float(r["run_seconds"]) >= float(r["seconds"]) for r in rows)
    ranking = json.loads((out / "ranking.json").read_text())
    assert "final quantised" in ranking["ordered_by"] and [r["inks"] for r in ranking["rows"]] == [r["inks"] for r in rows]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["best"]["inks"] == rows[0]["inks"] and summary["best"]["ink_set"][1:] == ["black", "white"]
    assert sorted(summary["ran"]) == sorted(names) and summary["skipped"] == []
    assert summary["settings"]["iterations"] == 3 and summary["timings"]["runs_ran"] == 3
    # the same seed and shared target for every set: each run's log starts from the same iteration-0 seed
    seeds = {list(csv.DictReader(open(out / "runs" / n / "log.csv")))[0]["seed"] for n in names}
    assert len(seeds) == 1

    # rerun: nothing is optimised again, the ranking is the same
    mtimes = {n: os.path.getmtime(out / "runs" / n / "summary.json") for n in names}
    capsys.readouterr()
    assert cli.main(_tiny(out, inks)) == 0
    err = capsys.readouterr().err
    assert all(f"skipping {n}" in err for n in names), err
    assert {n: os.path.getmtime(out / "runs" / n / "summary.json") for n in names} == mtimes
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ran"] == [] and sorted(summary["skipped"]) == sorted(names)
    assert [r["inks"] for r in csv.DictReader(open(out / "ranking.csv"))] == [r["inks"] for r in rows]

    # an interrupted set (no summary.json yet) is finished from its checkpoint, the others are skipped
    os.remove(out / "runs" / "teal" / "summary.json")
    assert cli.main(_tiny(out, inks, "--quiet")) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ran"] == ["teal"] and len(summary["skipped"]) == 2
    assert len(list(csv.DictReader(open(out / "runs" / "teal" / "log.csv")))) == 4  # iterations 0..3, not repeated

    # other settings in the same folder are refused before anything runs
    capsys.readouterr()
    assert cli.main(_tiny(out, inks, "--iterations", "4")) == 2
    assert "iterations: 3 there, 4 now" in capsys.readouterr().err
    teal = json.loads(open(inks).read())
    teal[0]["albedo"] = [0.1, 0.9, 0.7]
    changed = tmp_path / "changed.json"
    changed.write_text(json.dumps(teal))
    assert cli.main(_tiny(out, str(changed))) == 2
    assert "the same inks with other optical properties" in capsys.readouterr().err


@pytest.mark.parametrize("extra,match", [
    (["--candidates", "cyan,unobtainium"], "unknown ink(s) ['unobtainium']; known inks are ['black', 'cyan'"),
    (["-k", "4"], "-k: 4 inks per set but only 3 candidate(s)"),
    (["-k", "0"], "-k: expected >= 1"),
    (["--candidates", "cyan,Cyan"], "--candidates: duplicate ink(s) ['cyan']"),
    (["--candidates", "cyan,white"], "both name ['white']"),
    (["--always-inks", "black,black"], "--always-inks: duplicate ink(s)"),
    (["--user-inks", "missing.json"], "--user-inks: no such file"),
    (["--spp", "0"], "spp: expected > 0"),
    (["--target", "no_such_image.png"], "target: expected a built-in target"),
    (["--threads", "1000000000000"], "--threads: expected 1 ... "),  # issue 49: torch's overflow, a traceback
])
def test_bad_input_exit_code_2(cli, tmp_path, capsys, extra, match):
    inks = _user_inks(tmp_path / "inks.json")
    args = _tiny(tmp_path / "sel", inks)
    for i in range(0, len(extra), 2):  # override (or add) the flag
        if extra[i] in args:
            args[args.index(extra[i]) + 1] = extra[i + 1]
        else:
            args += extra[i:i + 2]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("ta-select-inks: error: ") and match in err, err
    assert not (tmp_path / "sel").exists()  # nothing written


def test_bad_user_inks(cli, tmp_path, capsys):
    other_g = _user_inks(tmp_path / "g.json", g=0.8)
    assert cli.main(_tiny(tmp_path / "sel", other_g)) == 2
    assert "one Henyey–Greenstein g" in capsys.readouterr().err
    clash = tmp_path / "clash.json"
    clash.write_text(json.dumps([INKS["cyan"].to_dict()]))
    assert cli.main(_tiny(tmp_path / "sel", str(clash))) == 2
    assert "are built-in inks" in capsys.readouterr().err
    assert not (tmp_path / "sel").exists()
