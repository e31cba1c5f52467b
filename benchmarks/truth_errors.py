"""Spells where a recording's own labels, the ground truth the scorer reads, name the wrong markers.

The files in `../shared/data` carry the labels of the capture system or operator that made them, and those
are not flawless. Where they swap markers, a labeler that follows the markers is scored wrong. The benchmark
scores against the files as they are (EVALUATION.md), and that stays the figure. `benchmarks.realizations`
also prints its means with these spells left unscored, so that the part of a gap that is the file's own is
measured rather than guessed.

A spell is listed here only with evidence from the file itself, checked by `tests/test_truth_errors.py`: a
labeled marker far off a rigid partner inside the spell, and on it in the second before and after.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from recordings.corruption import CorruptedSequence


@dataclasses.dataclass(frozen=True)
class LabelError:
    """Frames first..last (inclusive, the file's own numbering) where `markers` ("Subject:Marker") are labeled
    wrong in the file, and the evidence: `marker` sits off its rigid partner `partner`."""

    first: int
    last: int
    markers: tuple[str, ...]
    marker: str
    partner: str


#: The tennis serve (Derrick) at 50 Hz, the arm whipping forward: the file's labels cycle the right upper arm,
#: elbow and forearm markers for seven frames. Its RUPA is 279-301 mm from RSHO in frames 193-194 against
#: 154-172 mm before and after (a rigid upper arm), and its RFRM 154-157 mm from RSHO in frames 191-192, where
#: RUPA's own distance was; the engine's labels there follow the markers. The two-player file holds the
#: same take of Derrick 51 frames earlier.
_SERVE = ("Derrick:RUPA", "Derrick:RELB", "Derrick:RFRM")
KNOWN: dict[str, tuple[LabelError, ...]] = {
    "kineticstoolkit/kinematics_tennis_serve.c3d": (
        LabelError(190, 196, _SERVE, "Derrick:RUPA", "Derrick:RSHO"),),
    "kineticstoolkit/kinematics_tennis_serve_2players.c3d": (
        LabelError(139, 145, _SERVE, "Derrick:RUPA", "Derrick:RSHO"),),
}


def unscored(file: str, seq: CorruptedSequence, given: list) -> tuple[CorruptedSequence, list] | None:
    """`seq` and a labeler's `given` labels without the points of the file's known label errors (truth and
    label both left out, as if those points were not there), or None where the file has none listed."""
    errors = KNOWN.get(file)
    if not errors:
        return None
    points, truth, given = list(seq.points_m), list(seq.truth), list(given)
    for e in errors:
        out = np.array([seq.marker_names.index(m) for m in e.markers if m in seq.marker_names])
        for f in range(e.first, min(e.last, seq.n_frames - 1) + 1):
            if truth[f] is None:
                continue
            keep = ~np.isin(truth[f], out)
            points[f], truth[f] = points[f][keep], truth[f][keep]
            if given[f] is not None:
                given[f] = [g for g, k in zip(given[f], keep) if k]
    return dataclasses.replace(seq, points_m=points, truth=truth), given
