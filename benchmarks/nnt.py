"""The reference baseline: plain nearest-neighbour tracking from a labeled seed, no skeleton.

Each marker keeps its last observed position. Every frame, points are assigned one-to-one to markers by
minimum total distance (Hungarian), and only pairs closer than the gate (3 cm) count; a marker left
unmatched keeps its last position and waits for a point to come back near it. Labels given in a frame
(the seed) are taken as they are. EVALUATION.md quotes this baseline at ~85 % (L0) and 36-42 % (L2) on
135_02 / HDM_mm, which is the floor the engine has to beat.

With ``velocity=True`` a marker seen in the two previous frames is looked for at its constant-velocity
prediction instead of its last position (still no skeleton; a marker that missed a frame falls back to
its last position). Plain last-position tracking loses every marker that moves more than the gate in one
frame (3.6 m/s at 120 Hz: hands, feet), so this variant is the fairer reading of "plain NNT"; the
benchmark reports both.

It takes the same inputs as `service.engine.Engine.step` (points + optional labels per frame), so the
benchmark drives both the same way.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from recordings.corruption import CorruptedSequence

GATE_M = 0.03


class NearestNeighbourTracker:
    """Per-marker last position + gated one-to-one assignment. Mutable: one instance per sequence."""

    def __init__(self, gate_m: float = GATE_M, velocity: bool = False):
        self.gate_m = gate_m
        self.velocity = velocity
        self.names: list[str] = []
        self.last_m = np.zeros((0, 3))  # (M, 3) last observed position of each marker in `names`
        self.step_m = np.zeros((0, 3))  # (M, 3) displacement over the last frame, 0 unless seen twice in a row
        self._index: dict[str, int] = {}
        self._seen_last = np.zeros(0, dtype=bool)  # (M,) whether each marker was observed in the previous frame

    def step(self, points_m: np.ndarray, labels: Sequence[str] | None = None) -> list[str]:
        """Label one frame's points; returns a label per point ("" = unlabeled)."""
        points_m = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        out = [""] * len(points_m)
        valid = np.all(np.isfinite(points_m), axis=1)
        seeded = [(i, self._marker(l)) for i, l in enumerate(labels or []) if l and valid[i]]
        predicted_m = self.last_m + self.step_m if self.velocity else self.last_m.copy()
        taken = np.zeros(len(self.names), dtype=bool)
        for i, k in seeded:
            self._observe(k, points_m[i])
            taken[k] = True
            out[i] = self.names[k]
        free_points = np.flatnonzero(valid & np.array([not l for l in out], dtype=bool))
        free_markers = np.flatnonzero(~taken)
        if len(free_points) == 0 or len(free_markers) == 0:
            self._forget_steps(taken)
            return out
        dist = cdist(np.nan_to_num(predicted_m[free_markers], nan=np.inf), points_m[free_points])
        # Only markers and points with some pair inside the gate take part; out-of-gate pairs cost more
        # than any in-gate assignment could save, and are dropped after the assignment.
        rows = np.flatnonzero((dist < self.gate_m).any(axis=1))
        cols = np.flatnonzero((dist < self.gate_m).any(axis=0))
        if len(rows) == 0:
            self._forget_steps(taken)
            return out
        sub = dist[np.ix_(rows, cols)]
        r, c = linear_sum_assignment(np.where(sub < self.gate_m, sub, 1e3))
        for ri, ci in zip(r, c):
            if sub[ri, ci] < self.gate_m:
                k, i = free_markers[rows[ri]], free_points[cols[ci]]
                self._observe(k, points_m[i])
                taken[k] = True
                out[i] = self.names[k]
        self._forget_steps(taken)
        return out

    def _observe(self, k: int, position_m: np.ndarray) -> None:
        # A marker without a position yet (NaN) or missed last frame gets no velocity (step_m was zeroed).
        self.step_m[k] = np.nan_to_num(position_m - self.last_m[k]) if self._seen_last[k] else 0.0
        self.last_m[k] = position_m

    def _forget_steps(self, seen: np.ndarray) -> None:
        """Markers not seen this frame lose their velocity; remember who was seen for the next frame."""
        self.step_m[~seen] = 0.0
        self._seen_last = seen.copy()

    def _marker(self, label: str) -> int:
        k = self._index.get(label)
        if k is None:
            k = self._index[label] = len(self.names)
            self.names.append(label)
            self.last_m = np.vstack([self.last_m, np.full((1, 3), np.nan)])
            self.step_m = np.vstack([self.step_m, np.zeros((1, 3))])
            self._seen_last = np.append(self._seen_last, False)
        return k


def run_nnt(
    seq: CorruptedSequence, seeded: bool = True, gate_m: float = GATE_M, velocity: bool = False
) -> list[list[str] | None]:
    """Label a whole sequence; in seeded mode the first `seq.seed_frames` frames carry the true labels.

    Without a seed there is nothing to track (NNT cannot initialise itself): every point stays unlabeled.
    """
    tracker = NearestNeighbourTracker(gate_m, velocity)
    given: list[list[str] | None] = []
    for f, points in enumerate(seq.points_m):
        if points is None:
            given.append(None)
            continue
        labels = seq.true_labels(f) if seeded and f < seq.seed_frames else None
        given.append(tracker.step(points, labels))
    return given
