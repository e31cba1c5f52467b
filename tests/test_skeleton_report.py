"""benchmarks/skeleton.py: which segment a marker's name says it rides, and the count of markers a subject
model carries elsewhere."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.skeleton import expected_segment, misplaced, residual_summary, side_crossed


def test_expected_segment_reads_the_cmu_and_plug_in_gait_names():
    assert expected_segment("male:LWRA") == "l_forearm"
    assert expected_segment("RFIN") == "r_forearm"  # no hand segment: the fingers ride the forearm
    assert expected_segment("Derrick:RASI") == "pelvis"
    assert expected_segment("LFWT") == "pelvis"
    assert expected_segment("rtib") == "r_shank"
    assert expected_segment("C7") == expected_segment("RBAK") == "torso"
    assert expected_segment("LFHD") == "head"
    # joint markers and names we cannot read are not judged
    for name in ("LSHO", "RELB", "LKNE", "RANK", "subject:LL_FLE", "*12", ""):
        assert expected_segment(name) is None, name


def test_misplaced_counts_only_judged_markers():
    segments = {"S:LWRA": "l_upperarm", "S:LWRB": "l_forearm", "S:LELB": "l_forearm", "S:LLAC": "torso"}
    assert misplaced(segments) == (2, ["LWRA->l_upperarm"])
    assert misplaced({}) == (0, [])


def test_numediarts_names_are_judged_after_the_l_every_one_starts_with():
    """numediart's set (03_rolling) starts every name with L, then the side: LL_TH1 is the left thigh's,
    LRUA2 the right upper arm's, LR-SK1 the right shank's; its acromions and epicondyles are not judged."""
    segments = {"S:LL_TH1": "pelvis", "S:LRUA2": "r_upperarm", "S:LR-SK1": "r_shank", "S:LLFHD": "head",
                "S:LCV7": "torso", "S:LRAC": "r_upperarm", "S:LL_FLE": "l_shank", "S:LR_FCC": "r_shank"}
    assert misplaced(segments) == (6, ["LL_TH1->pelvis", "LR_FCC->r_shank"])
    assert side_crossed({"S:LL_TH1": "r_thigh", "S:LR_TH1": "r_thigh", "S:LCV7": "torso"}) == (2, 1)


def test_residual_summary():
    assert residual_summary(np.zeros(0)) == "–"
    assert residual_summary(np.array([10.0, 10.0, 20.0])) == "10.0 / 18.0"


def test_the_report_section_counts_seeded_runs_and_says_when_there_is_no_skeleton():
    from benchmarks import run

    job = run.Job("f.c3d", "L2", "seeded", "adaptive", None)
    r = run.JobResult(job=job, n_frames=1, rate_hz=1.0, score=None, step_s=np.zeros(0), solved_fraction=0.0,
                      subjects=(), peak_rss_mb=0.0, fit_rms_mm=np.array([10.0, 20.0]),
                      segments={"S:LWRA": "l_upperarm", "S:LWRB": "l_forearm"})
    lines = run.skeleton_lines([r, run.dataclasses.replace(r, segments={}, fit_rms_mm=np.zeros(0))])
    assert "| f.c3d | L2 | seeded | 15.0 / 19.0 | 1 of 2: LWRA->l_upperarm |" in lines
    assert "| f.c3d | L2 | seeded | – | no skeleton |" in lines
    assert lines[-1] == "Seeded runs: 1 of 2 judged markers off their segment (50.0 %)."


def test_side_crossed_counts_markers_on_the_other_sides_segments():
    from benchmarks.skeleton import side_crossed

    facing = {"S:LWRA": "l_forearm", "S:RWRA": "r_forearm", "S:LTHI": "l_thigh", "S:RTHI": "r_thigh", "S:C7": "torso"}
    turned = {"S:LWRA": "r_forearm", "S:RWRA": "l_forearm", "S:LTHI": "r_thigh", "S:RTHI": "r_thigh", "S:C7": "torso"}
    assert side_crossed(facing) == (4, 0)
    assert side_crossed(turned) == (4, 3)  # the torso marker has no side; RTHI stayed


def test_calibration_sweep_judges_each_seed_calibration():
    """Real data: one realization of 85_12 (hands on the hips through the seed; the wrists once went to the
    pelvis) calibrated as the engine calibrates it from the seed's labels."""
    from benchmarks.skeleton import calibration_sweep
    from tests.conftest import data_path

    path = data_path("cmu/85_12.c3d")
    (row,) = calibration_sweep(path.parent.parent, ["cmu/85_12.c3d"], ["L3"], [15])
    assert row["calibrated"] and row["judged"] == 33 and not row["backwards"]
    assert not any(off.startswith(("LWRA", "RWRA")) for off in row["off"]), row["off"]


def test_the_sweep_command_refuses_bad_seeds_and_data_in_one_sentence(tmp_path, capsys):
    from benchmarks.skeleton import main

    assert main(["--seeds", "a-b"]) == 2
    assert main(["--data", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("benchmarks.skeleton: ") for line in err)


def test_parse_seeds_reads_ranges_and_lists():
    from benchmarks.skeleton import parse_seeds

    assert parse_seeds("0-3") == [0, 1, 2, 3]
    assert parse_seeds("1,4,7") == [1, 4, 7]
    assert parse_seeds("5") == [5]
    with pytest.raises(ValueError):
        parse_seeds("a-b")
