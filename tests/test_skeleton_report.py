"""benchmarks/skeleton.py: which segment a marker's name says it rides, and the count of markers a subject
model carries elsewhere."""

from __future__ import annotations

import numpy as np

from benchmarks.skeleton import expected_segment, misplaced, residual_summary


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
    segments = {"S:LWRA": "l_upperarm", "S:LWRB": "l_forearm", "S:LELB": "l_forearm", "S:LL_TH1": "pelvis"}
    assert misplaced(segments) == (2, ["LWRA->l_upperarm"])
    assert misplaced({}) == (0, [])


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
