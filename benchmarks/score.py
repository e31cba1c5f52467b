"""Score a labeler's answers against a CorruptedSequence's ground truth, as EVALUATION.md defines it.

`given[f][i]` is the label the labeler gave point i of frame f ("" = none); `given[f] is None` means the
frame was never answered, which counts as all points unlabeled (a labeler cannot gain by dropping frames).

Modes:
- ``seeded``: labels are compared as full "Subject:Marker" strings. A labeler that renames the subject is
  wrong: the seed told it the names, and consumers key on them.
- ``tpose``: the labeler's ids are its own. Each id is matched to at most one true marker (and vice
  versa) by maximum co-occurrence over the scored frames (Hungarian assignment); an id left unmatched is
  a wrong label wherever it is given.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from recordings.corruption import CorruptedSequence

MODES = ("seeded", "tpose")

# Codes of Score.status, one per (frame, true marker).
ABSENT, CORRECT, UNLABELED, WRONG = 0, 1, 2, 3
# A ghost point this close to a true marker's point is a copy of it (HDM05's `*N` points repeat three markers
# exactly; the corruption's noise, up to 0.8 mm per axis, parts them by a few mm): which of the two is "the"
# marker no labeler can know, so the ceiling counts such a point as a coin toss.
COPY_M = 0.005


@dataclasses.dataclass(frozen=True, eq=False)  # array fields: a generated == would raise
class Score:
    """The figures of one run, plus where the errors were, so failures can be looked at."""

    mode: str
    first_scored_frame: int
    marker_names: tuple[str, ...]
    n_true_points: int  # true-marker points in scored frames
    n_correct: int  # true-marker points given their own label
    n_wrong: int  # true-marker points given another label
    n_unlabeled: int  # true-marker points given no label
    n_labels_given: int  # labels given to any point (true or ghost)
    n_ghost_points: int
    n_ghost_labeled: int  # ghost points given any label
    marker_wrong: np.ndarray  # (M,) int: per true marker, scored frames where it got a wrong label
    marker_unlabeled: np.ndarray  # (M,) int: per true marker, scored frames where it was seen but unlabeled
    frame_errors: np.ndarray  # (F,) int: wrong + unlabeled true-marker points + labeled ghosts per frame
    status: np.ndarray  # (F, M) int8: ABSENT / CORRECT / UNLABELED / WRONG (ABSENT before scoring starts)
    mapping: dict[str, str]  # tpose: labeler id -> true marker name (seeded: empty)
    n_reachable: float = float("nan")  # expected correct points of the best possible labeler (see `ceiling`)

    @property
    def accuracy(self) -> float:
        """Correct / true-marker points (the paper's figure); NaN if there were none."""
        return self.n_correct / self.n_true_points if self.n_true_points else float("nan")

    @property
    def ceiling(self) -> float:
        """The best accuracy any labeler could expect: seeded, a marker whose name no seed frame gave cannot
        be named (03_rolling: 8 of 68 markers, 11 % of its points); either mode, a point with a copy among the
        ghosts (within COPY_M) is a coin toss between the two, so half of it. NaN if nothing was scored."""
        return self.n_reachable / self.n_true_points if self.n_true_points else float("nan")

    @property
    def precision(self) -> float:
        """Correct / labels given; NaN if the labeler gave no label at all."""
        return self.n_correct / self.n_labels_given if self.n_labels_given else float("nan")

    @property
    def ghost_rate(self) -> float:
        """Ghost points given any label / ghost points; NaN if there were no ghosts."""
        return self.n_ghost_labeled / self.n_ghost_points if self.n_ghost_points else float("nan")

    def worst_markers(self, n: int = 5) -> list[tuple[str, int, int]]:
        """The n markers with the most errors: (name, wrong, unlabeled), worst first, errors only."""
        errors = self.marker_wrong + self.marker_unlabeled
        order = np.argsort(-errors, kind="stable")[:n]
        return [
            (self.marker_names[i], int(self.marker_wrong[i]), int(self.marker_unlabeled[i]))
            for i in order
            if errors[i] > 0
        ]


def score(
    seq: CorruptedSequence,
    given: Sequence[Sequence[str] | None],
    mode: str = "seeded",
    first_scored_frame: int = 0,
) -> Score:
    """Score `given` (one list of labels per frame, or None) against `seq` from `first_scored_frame` on."""
    if mode not in MODES:
        raise ValueError(f"unknown scoring mode {mode!r}; valid modes: {', '.join(MODES)}")
    if len(given) != seq.n_frames:
        raise ValueError(f"{len(given)} answered frames for a sequence of {seq.n_frames}")
    frames = range(first_scored_frame, seq.n_frames)
    for f in frames:
        if seq.points_m[f] is not None and given[f] is not None and len(given[f]) != len(seq.points_m[f]):
            raise ValueError(f"frame {f}: {len(given[f])} labels for {len(seq.points_m[f])} points")

    names = seq.marker_names
    mapping: dict[str, str] = {}
    if mode == "seeded":
        index_of = {name: i for i, name in enumerate(names)}
    else:
        mapping = match_ids(seq, given, first_scored_frame)
        index_of = {label: names.index(name) for label, name in mapping.items()}

    n_markers = len(names)
    status = np.zeros((seq.n_frames, n_markers), dtype=np.int8)
    frame_errors = np.zeros(seq.n_frames, dtype=np.int64)
    n_labels = n_ghosts = n_ghosts_labeled = 0
    n_reachable = 0.0
    nameable = np.ones(n_markers, dtype=bool)
    if mode == "seeded":  # the names the seed frames gave
        nameable[:] = False
        for f in range(first_scored_frame):
            if seq.truth[f] is not None:
                nameable[seq.truth[f][seq.truth[f] >= 0]] = True
    for f in frames:
        truth = seq.truth[f]
        if truth is None:
            continue
        labels = given[f] if given[f] is not None else [""] * len(truth)
        # -2: a label that names no true marker (always wrong); -1: no label.
        claimed = np.array([index_of.get(l, -2) if l else -1 for l in labels], dtype=np.int64)
        is_true = truth >= 0
        marker = truth[is_true]
        got = claimed[is_true]
        status[f, marker] = np.where(got == marker, CORRECT, np.where(got == -1, UNLABELED, WRONG))
        ghost_labeled = int(np.count_nonzero(claimed[~is_true] != -1))
        n_labels += int(np.count_nonzero(claimed != -1))
        n_ghosts += int(np.count_nonzero(~is_true))
        n_ghosts_labeled += ghost_labeled
        frame_errors[f] = int(np.count_nonzero(got != marker)) + ghost_labeled
        n_reachable += np.count_nonzero(nameable[marker]) - 0.5 * _copies(seq.points_m[f], is_true, nameable[marker])

    return Score(
        mode=mode,
        first_scored_frame=first_scored_frame,
        marker_names=names,
        n_true_points=int(np.count_nonzero(status != ABSENT)),
        n_correct=int(np.count_nonzero(status == CORRECT)),
        n_wrong=int(np.count_nonzero(status == WRONG)),
        n_unlabeled=int(np.count_nonzero(status == UNLABELED)),
        n_labels_given=n_labels,
        n_ghost_points=n_ghosts,
        n_ghost_labeled=n_ghosts_labeled,
        marker_wrong=np.count_nonzero(status == WRONG, axis=0),
        marker_unlabeled=np.count_nonzero(status == UNLABELED, axis=0),
        frame_errors=frame_errors,
        status=status,
        mapping=mapping,
        n_reachable=n_reachable,
    )


def _copies(points: np.ndarray, is_true: np.ndarray, counted: np.ndarray) -> int:
    """How many of the true-marker points (`counted` among them) have a ghost point within COPY_M."""
    ghosts = points[~is_true]
    if len(ghosts) == 0 or not counted.any():
        return 0
    marks = points[is_true][counted]
    d = np.linalg.norm(marks[:, None] - ghosts[None], axis=2)
    return int(np.count_nonzero(d.min(axis=1) < COPY_M))


def match_ids(
    seq: CorruptedSequence, given: Sequence[Sequence[str] | None], first_scored_frame: int = 0
) -> dict[str, str]:
    """Labeler id -> true marker name, one-to-one, maximising co-occurrence over the scored frames.

    Co-occurrence counts the points where the labeler said id and the truth was that marker. Pairs that
    never co-occur are not matched (an id that never sat on a marker names nothing).
    """
    ids: dict[str, int] = {}
    pairs: list[tuple[int, int]] = []
    for f in range(first_scored_frame, seq.n_frames):
        truth = seq.truth[f]
        if truth is None or given[f] is None:
            continue
        for label, t in zip(given[f], truth):
            if label:
                k = ids.setdefault(label, len(ids))
                if t >= 0:
                    pairs.append((k, int(t)))
    if not ids or not pairs:
        return {}
    counts = np.zeros((len(ids), len(seq.marker_names)), dtype=np.int64)
    np.add.at(counts, tuple(np.array(pairs).T), 1)
    rows, cols = linear_sum_assignment(counts, maximize=True)
    id_names = list(ids)
    return {id_names[r]: seq.marker_names[c] for r, c in zip(rows, cols) if counts[r, c] > 0}


def plot_errors(result: Score, path, title: str = "", rate_hz: float | None = None) -> None:
    """Save a PNG of every marker's status over time (rows = markers), for looking at failures.

    matplotlib is imported here, with the Agg backend, so scoring needs no plotting library or display.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    colours = ListedColormap(["#ffffff", "#c8e6c9", "#ffb300", "#d32f2f"])  # absent/correct/unlabeled/wrong
    n_frames, n_markers = result.status.shape
    scale = 1.0 / rate_hz if rate_hz else 1.0
    fig, (ax, ax_f) = plt.subplots(
        2, 1, figsize=(12, 2 + 0.16 * n_markers), sharex=True, gridspec_kw={"height_ratios": [5, 1]}
    )
    ax.imshow(
        result.status.T, aspect="auto", interpolation="nearest", cmap=colours, vmin=0, vmax=3,
        extent=(0, n_frames * scale, n_markers - 0.5, -0.5),
    )
    ax.set_yticks(range(n_markers), [n.rpartition(":")[2] for n in result.marker_names], fontsize=6)
    ax.set_title(
        f"{title}  accuracy {result.accuracy:.1%}  precision {result.precision:.1%}  "
        "(green correct, amber unlabeled, red wrong)",
        fontsize=9,
    )
    ax_f.plot(np.arange(n_frames) * scale, result.frame_errors, lw=0.6, color="#d32f2f")
    ax_f.set_ylabel("errors", fontsize=7)
    ax_f.set_xlabel("time [s]" if rate_hz else "frame")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
