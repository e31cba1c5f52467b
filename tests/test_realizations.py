"""benchmarks/realizations.py: the summary over many realizations, and the command's refusals. (The runs
themselves are `benchmarks.run`'s jobs, tested in test_benchmark_run.py.)"""

from __future__ import annotations

from benchmarks.realizations import main, summary
from tests.conftest import data_path


def _row(file, level, seed, acc, prec=100.0, fit_p90_mm=20.0):
    return dict(file=file, level=level, seed=seed, acc=acc, prec=prec, n=100, wrong=0, unlabeled=0,
                fit_p90_mm=fit_p90_mm, error="")


def test_summary_gives_mean_and_worst_per_file_and_level_and_what_moved():
    before = [_row("a.c3d", "L3", 0, 90.0, fit_p90_mm=500.0), _row("a.c3d", "L3", 1, 98.0), _row("b.c3d", "L3", 0, 99.0)]
    after = [_row("a.c3d", "L3", 0, 96.0, fit_p90_mm=24.0), _row("a.c3d", "L3", 1, 98.0), _row("b.c3d", "L3", 0, 99.0, 99.5)]
    text = "\n".join(summary(after, before))
    # the paired change: a's runs moved by +6 and 0 points (mean 3, standard error 3)
    assert "| a.c3d | L3 | 2 | 97.00 / 96.00 | 100.00 | 22 / 24 | 94.00 / 90.00 | 100.00 | 260 / 500 | +3.000 +- 3.000 (1 up, 0 down) |" in text
    assert "| b.c3d | L3 | 1 | 99.00 / 99.00 | 99.50 | 20 / 20 | 99.00 / 99.00 | 100.00 | 20 / 20 | +0.000 (0 up, 0 down) |" in text
    assert ("L3: 3 runs, accuracy mean 97.667 %, precision mean 99.833 % (before, same runs: 95.667 / 100.000 %;"
            " change +2.000 +- 2.000 (1 up, 0 down))") in text
    assert "runs that moved: 2" in text
    assert "- a.c3d L3 seed 0: accuracy 90.000 -> 96.000, precision 100.000 -> 100.000" in text
    assert "seed 1" not in text  # unchanged runs are not listed


def test_summary_without_an_earlier_run():
    text = "\n".join(summary([_row("a.c3d", "L2", 0, 99.0)]))
    assert "| a.c3d | L2 | 1 | 99.00 / 99.00 | 100.00 | 20 / 20 |" in text and "moved" not in text
    no_solves = "\n".join(summary([_row("a.c3d", "L2", 0, 99.0, fit_p90_mm=float("nan"))]))
    assert "| a.c3d | L2 | 1 | 99.00 / 99.00 | 100.00 | – |" in no_solves


def test_the_command_refuses_bad_seeds_data_and_comparisons_in_one_sentence(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["--seeds", "x"]) == 2
    assert main(["--data", str(tmp_path / "none")]) == 2
    assert main(["--compare", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("benchmarks.realizations: ") for line in err), err


def test_tpose_mode_refuses_files_without_a_t_pose(capsys):
    data_path("cmu/135_02.c3d")  # (the shared recordings: fails under CI=true if missing)
    assert main(["--mode", "tpose", "--files", "135_02"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["benchmarks.realizations: none of the files is one with a T-pose "
                   "(hdm05/HDM_mm_01-02_03_120.c3d, georgiatech/squat.c3d)"], err
