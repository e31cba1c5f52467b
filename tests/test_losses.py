"""benchmarks/losses.py: where a run loses its points, on hand-made sequences with known losses, and the
command's refusals."""

from __future__ import annotations

import dataclasses

import numpy as np

from benchmarks.losses import (SETTLE_FRAMES, main, never_in_seed, report, run_losses, summary, true_labeled_frames,
                              true_skeleton, unlabeled_in_view, wrong_pairs)
from protocol.skeleton import SEGMENTS
from recordings.corruption import CorruptedSequence
from tests.conftest import data_path

NAMES = ("s:A", "s:B", "s:C")


def _sequence(truth_per_frame):
    """Frames whose points are the given true marker indices (-1 = a ghost; None = a dropped frame)."""
    truth = [None if t is None else np.array(t, int) for t in truth_per_frame]
    points = [None if t is None else np.zeros((len(t), 3)) for t in truth]
    return CorruptedSequence(points, truth, NAMES, 100.0, "L2", 7, "x/file.c3d")


def test_wrong_pairs_count_each_given_label_on_each_true_point_from_the_first_scored_frame():
    seq = _sequence([[0, 1, -1]] * 6)
    given = [["s:A", "s:B", ""]] * 2 + [["s:B", "s:A", ""]] * 3 + [["s:A", "s:B", "s:C"]]
    assert wrong_pairs(seq, given, first=1) == [("s:B", "s:A", 3, 2), ("s:A", "s:B", 3, 2), ("s:C", "", 1, 5)]
    assert wrong_pairs(seq, given, first=6) == []


def test_a_marker_counts_as_lost_in_view_only_after_it_settled_and_a_dropped_frame_breaks_nothing():
    n = SETTLE_FRAMES + 6
    truth = [[0, 1]] * n
    truth[SETTLE_FRAMES + 2] = None  # dropped: neither counted nor a break in B's run in view
    seq = _sequence(truth)
    given = []
    for f in range(n):
        if truth[f] is None:
            given.append(None)
        elif f < SETTLE_FRAMES + 1:
            given.append(["s:A", "s:B"])
        else:  # B unlabeled from here; on the last frame its name is on A's point
            given.append(["s:B" if f == n - 1 else "s:A", ""])
    rows = unlabeled_in_view(seq, given, first=0)
    lost = list(range(SETTLE_FRAMES + 1, n))
    lost.remove(SETTLE_FRAMES + 2)
    assert rows == [("s:B", len(lost), 1, [(SETTLE_FRAMES + 1, SETTLE_FRAMES + 1), (SETTLE_FRAMES + 3, n - 1)])]


def test_a_marker_just_back_in_view_is_not_yet_lost():
    truth = [[0, 1]] * 5 + [[0]] * 3 + [[0, 1]] * 5  # B hidden three frames, then back but never labeled
    given = [["s:A", "s:B"]] * 5 + [["s:A"]] * 3 + [["s:A", ""]] * 5
    assert unlabeled_in_view(_sequence(truth), given, first=0) == []


def test_markers_never_in_the_seed_and_the_report():
    seq = _sequence([[0, -1]] * 3 + [[0, 2]] * 3)
    given = [["s:A", ""]] * 6
    assert never_in_seed(seq, first=3) == ["s:C"]
    text = "\n".join(report(seq, given, first=3))
    assert "file.c3d L2 seed 7: scored from frame 3 of 6" in text
    assert "never in the seed: s:C" in text and text.count("  none") == 2


def test_the_command_refuses_bad_data_and_files_matching_none_or_several_in_one_sentence(tmp_path, capsys):
    data = data_path("kineticstoolkit/kinematics_tennis_serve.c3d").parents[1]
    assert main(["x", "--data", str(tmp_path / "none")]) == 2
    assert main(["no-such-recording", "--data", str(data)]) == 2
    assert main(["tennis", "--data", str(data)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("benchmarks.losses: ") for line in err), err
    assert "data directory" in err[0] and "no labeled file matches" in err[1] and "matches 2 files" in err[2]


def test_true_skeleton_aligns_a_skeleton_with_misplaced_joints_to_the_true_labels():
    """A calibrated performer's skeleton with its knees and elbows moved 4 cm fits its true-labeled frames
    worse; aligned to them (`true_skeleton`) it fits them at least as well as the engine's own model (when
    written: 25 mm RMS median moved, 1.5 mm aligned, 24 mm the engine's model at frame 400)."""
    import dataclasses

    from recordings.corruption import corrupt
    from recordings.synthetic import perform
    from service import tracker
    from service.engine import Engine
    from tests.test_engine import run

    seq = corrupt(perform(3, duration_s=6.0).recording, "L0", 3)
    engine = Engine()
    part = CorruptedSequence(seq.points_m[:400], seq.truth[:400], seq.marker_names, seq.rate_hz)
    run(part, engine)
    (name, s), = engine._subjects.items()
    assert s.model.has_skeleton
    frames = true_labeled_frames(seq, name, s.model.markers)
    bent = s.model.joint_offsets_m.copy()
    knees_elbows = [SEGMENTS.index(k) for k in ("l_shank", "r_shank", "l_forearm", "r_forearm")]
    bent[knees_elbows] += [0.04, 0.0, 0.0]
    wrong = dataclasses.replace(s.model, joint_offsets_m=bent)

    def rms(model):  # median true-label fit over the frames after 400
        st, out = tracker.new_state(model, frames[400], 0), []
        st.t_root_m, st.R_parent_segment = s.state.t_root_m.copy(), s.state.R_parent_segment.copy()
        for f in range(400, len(frames), 4):
            seen = np.isfinite(frames[f, :, 0])
            fit = None
            for _ in range(2):
                fit = tracker._fit(model, st, engine.solver, frames[f], seen) or fit
            out.append(fit.residual_rms_m)
        return float(np.median(out))

    aligned = true_skeleton(wrong, s.state, engine.solver, frames, 400)
    before, after, calibrated = rms(wrong), rms(aligned), rms(s.model)
    assert after < 0.5 * before and after < calibrated + 0.002, (before, after, calibrated)


def test_the_command_runs_a_real_recording_again_with_the_true_skeleton_and_prints_both_accuracies(capsys):
    data = data_path("cmu/07_01.c3d").parents[1]
    assert main(["07_01", "--level", "L2", "--seed", "1", "--true-skeleton", "--data", str(data)]) == 0
    out = capsys.readouterr().out.splitlines()
    rows = {line.strip().rsplit(None, 3)[0]: line for line in out[out.index("accuracy / precision [%]:") + 1:]}
    assert set(rows) == {"as it runs", "with the true skeleton"}, out
    for line in rows.values():
        accuracy, precision = (float(x) for x in line.split()[-3::2])
        assert 90.0 <= accuracy <= 100.0 and 90.0 <= precision <= 100.0, line


def test_the_losses_of_several_runs_are_summed_by_marker_by_window_and_by_spell():
    """Two runs: the first gives A's label on B's point for 3 frames (A's own point unlabeled meanwhile) and
    a label on a ghost once; the second leaves B unlabeled in view for 4 frames after it settled. The
    summary sums them per marker (the ghost's points as a ghost), puts each loss in its window of the
    recording, and lists the longest spells with their seeds."""
    n = SETTLE_FRAMES + 6
    seq = _sequence([[0, 1, -1]] * n)
    first = SETTLE_FRAMES
    given1 = [["s:A", "s:B", ""]] * n
    for f in (first, first + 1, first + 2):
        given1[f] = ["", "s:A", ""]
    given1[first + 5] = ["s:A", "s:B", "s:C"]
    given2 = [["s:A", "s:B", ""]] * (first + 2) + [["s:A", "", ""]] * (n - first - 2)
    one = run_losses(seq, given1, first)
    two = run_losses(dataclasses.replace(seq, seed=8), given2, first)
    assert one.wrong == {"s:B": 3, "": 1} and one.unlabeled == {"s:A": 3}
    assert two.wrong == {} and two.unlabeled == {"s:B": 4} and two.seed == 8
    text = summary([one, two], window=4, n_frames=n, first=first)
    assert text[0] == f"2 runs: 4 wrong labels, 7 marker-frames unlabeled in view, from frame {first} of {n}"
    rows = {line.split()[0]: line for line in text[3:6]}
    assert "wrong     3, unlabeled in view     4, in  2 runs" in rows["s:B"]
    assert "wrong     0, unlabeled in view     3, in  1 runs" in rows["s:A"]
    at_spells = next(k for k, line in enumerate(text) if line.startswith("longest spells"))
    spells = text[at_spells + 1:]
    assert spells[0] == f"      4 frames, seed  8, s:B unlabeled, first {first + 2}"
    assert set(spells[1:3]) == {f"      3 frames, seed  7, s:A on s:B, first {first}",
                                f"      3 frames, seed  7, s:A unlabeled, first {first}"}
    windows = text[text.index("where the losses fall (4-frame windows):") + 1:at_spells - 1]
    assert sum(int(line.split()[3]) for line in windows) == 4 + 7  # (every loss in one window)


def test_the_command_sums_several_realizations_and_refuses_bad_seeds_in_one_sentence(capsys):
    data = data_path("cmu/07_01.c3d").parents[1]
    assert main(["07_01", "--level", "L2", "--seeds", "1-x", "--data", str(data)]) == 2
    assert main(["07_01", "--level", "L2", "--seeds", "1,2", "--true-skeleton", "--data", str(data)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("benchmarks.losses: ") for line in err), err
    assert main(["07_01", "--level", "L2", "--seeds", "1,2", "--data", str(data)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "07_01.c3d L2, seeds 1,2" and out[1].startswith("2 runs: "), out[:2]
