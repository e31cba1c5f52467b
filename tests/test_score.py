"""benchmarks.score on hand-made sequences whose answers are known."""

import numpy as np
import pytest

from benchmarks.score import CORRECT, UNLABELED, WRONG, match_ids, plot_errors, score
from recordings.corruption import CorruptedSequence

NAMES = ("S:A", "S:B", "S:C")


def sequence(truths: list[list[int] | None]) -> CorruptedSequence:
    """Points are irrelevant to scoring; only their count and truth matter."""
    return CorruptedSequence(
        points_m=[None if t is None else np.zeros((len(t), 3)) for t in truths],
        truth=[None if t is None else np.array(t) for t in truths],
        marker_names=NAMES,
        rate_hz=100.0,
    )


# 4 frames, ghost (-1) in frame 1, marker C hidden in frame 2, points in varying order
SEQ = sequence([[0, 1, 2], [2, -1, 0, 1], [1, 0], [2, 1, 0]])


def truthful(seq: CorruptedSequence) -> list[list[str]]:
    return [seq.true_labels(f) for f in range(seq.n_frames)]


def test_perfect_labeler_scores_100():
    s = score(SEQ, truthful(SEQ), "seeded")
    assert (s.accuracy, s.precision, s.ghost_rate) == (1.0, 1.0, 0.0)
    assert s.n_true_points == 11 and s.n_correct == 11 and s.n_ghost_points == 1
    assert s.frame_errors.sum() == 0 and s.worst_markers() == []
    assert s.status[2, 2] == 0 and s.status[2, 0] == CORRECT


def test_permuted_labels_score_zero_in_seeded_mode():
    rename = {"S:A": "S:B", "S:B": "S:C", "S:C": "S:A", "": ""}
    given = [[rename[l] for l in labels] for labels in truthful(SEQ)]
    s = score(SEQ, given, "seeded")
    assert s.accuracy == 0.0 and s.precision == 0.0 and s.n_wrong == 11
    assert s.marker_wrong.tolist() == [4, 4, 3]
    assert (s.status[s.status != 0] == WRONG).all()


def test_seeded_compares_the_full_label():
    given = [[l.replace("S:", "Other:") for l in labels] for labels in truthful(SEQ)]
    assert score(SEQ, given, "seeded").accuracy == 0.0


def test_consistent_renaming_scores_100_in_tpose_mode():
    rename = {"S:A": "me:x", "S:B": "me:y", "S:C": "me:z", "": ""}
    given = [[rename[l] for l in labels] for labels in truthful(SEQ)]
    s = score(SEQ, given, "tpose")
    assert s.accuracy == 1.0 and s.precision == 1.0
    assert s.mapping == {"me:x": "S:A", "me:y": "S:B", "me:z": "S:C"}


def test_tpose_matching_is_one_to_one_by_co_occurrence():
    # id "p" sits on A in 3 frames and on B in 1; id "q" on B in 3 frames: p->A, q->B, the rest wrong
    seq = sequence([[0, 1]] * 4)
    given = [["p", "q"], ["p", "q"], ["p", "q"], ["q", "p"]]
    s = score(seq, given, "tpose")
    assert match_ids(seq, given) == {"p": "S:A", "q": "S:B"}
    assert s.n_correct == 6 and s.n_wrong == 2
    assert s.accuracy == pytest.approx(6 / 8)


def test_abstaining_costs_accuracy_not_precision():
    given = truthful(SEQ)
    given[3] = ["", "", ""]
    s = score(SEQ, given, "seeded")
    assert s.accuracy == pytest.approx(8 / 11)
    assert s.precision == 1.0
    assert s.n_unlabeled == 3 and (s.status[3] == UNLABELED).all()


def test_labeled_ghost_counts_against_ghost_rate_and_precision():
    given = truthful(SEQ)
    given[1][1] = "S:B"  # the ghost gets B's name (B is also labeled correctly: a duplicate label)
    s = score(SEQ, given, "seeded")
    assert s.accuracy == 1.0
    assert s.ghost_rate == 1.0
    assert s.precision == pytest.approx(11 / 12)
    assert s.frame_errors.tolist() == [0, 1, 0, 0]


def test_unanswered_and_dropped_frames():
    given = truthful(SEQ)
    given[0] = None  # never answered: all unlabeled
    s = score(SEQ, given, "seeded")
    assert s.n_unlabeled == 3 and s.accuracy == pytest.approx(8 / 11) and s.precision == 1.0
    dropped = sequence([[0, 1, 2], None])  # a dropped frame has no points: nothing to score
    assert score(dropped, [dropped.true_labels(0), None]).n_true_points == 3


def test_scoring_starts_at_first_scored_frame():
    given = truthful(SEQ)
    given[0] = ["S:C", "S:A", "S:B"]  # wrong, but in the seed window
    s = score(SEQ, given, "seeded", first_scored_frame=1)
    assert s.accuracy == 1.0 and s.n_true_points == 8
    assert (s.status[0] == 0).all()


def test_bad_arguments_say_what_is_valid():
    with pytest.raises(ValueError, match="seeded, tpose"):
        score(SEQ, truthful(SEQ), "magic")
    with pytest.raises(ValueError, match="frame 1"):
        score(SEQ, [["S:A"] * 3, ["S:A"]] + truthful(SEQ)[2:])


def test_plot_errors_writes_a_png(tmp_path):
    given = truthful(SEQ)
    given[2] = ["S:A", ""]
    path = tmp_path / "errors.png"
    plot_errors(score(SEQ, given), path, title="hand-made", rate_hz=100.0)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ceiling_counts_names_the_seed_never_gave_and_copied_points_as_a_coin_toss():
    # A and B apart; C never seen in the 1-frame seed; in frame 2 a ghost sits 1 mm from A (a copy of it)
    pts = {0: [0.0, 0, 0], 1: [1.0, 0, 0], 2: [0, 1.0, 0]}
    truths = [[0, 1], [0, 1, 2], [0, 1, 2, -1]]
    points = [np.array([pts[t] if t >= 0 else [0.001, 0, 0] for t in tr]) for tr in truths]
    seq = CorruptedSequence(points_m=points, truth=[np.array(t) for t in truths], marker_names=NAMES, rate_hz=100.0)
    s = score(seq, truthful(seq), "seeded", first_scored_frame=1)
    assert s.n_true_points == 6
    assert s.ceiling == pytest.approx((6 - 2 - 0.5) / 6)  # C twice unnameable; A once a coin toss
    assert s.accuracy == 1.0  # the truth itself is not bound by it: it knows which copy is which
    assert score(seq, truthful(seq), "tpose").ceiling == pytest.approx((8 - 0.5) / 8)  # tpose names its own
