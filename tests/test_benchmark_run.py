"""benchmarks/run.py: the command line (flags that contradict each other, unknown files and directories get
one sentence and exit code 2) and where each kind of report goes."""

from __future__ import annotations

import pytest

from benchmarks import run


def test_speed_only_writes_beside_the_other_outputs_not_over_benchmark_md(tmp_path):
    args = run.parse_args(["--speed-only", "--data", str(tmp_path)])
    assert args.output == run.OUT_DIR / "SPEED.md"
    assert run.parse_args(["--data", str(tmp_path)]).output == run.REPO / "BENCHMARK.md"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--speed-only", "--no-speed"], "leave nothing to measure"),
        (["--workers", "0"], "--workers"),
        (["--data", "/nonexistent/dir"], "does not exist"),
        (["--files", "no_such_recording"], "no labeled file matches"),
    ],
)
def test_bad_flags_get_one_sentence_and_exit_2(argv, message, capsys, tmp_path):
    if "--data" not in argv:
        argv = argv + ["--data", str(tmp_path)]
    assert run.main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and err.count("\n") == 1


def test_an_unreadable_recording_is_skipped_with_a_sentence(tmp_path, capsys):
    (tmp_path / "broken.c3d").write_bytes(b"not a c3d file")
    assert run.labeled_files(tmp_path) == []
    err = capsys.readouterr().err
    assert "skipping broken.c3d" in err and "Traceback" not in err
