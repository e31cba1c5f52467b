"""benchmarks/truth_errors.py: the recordings' own label errors, each checked against the file, and the
points they leave unscored."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.score import score
from benchmarks.truth_errors import KNOWN, unscored
from recordings.c3d import read_c3d
from recordings.corruption import CorruptedSequence
from tests.conftest import data_path


@pytest.mark.parametrize("file", sorted(KNOWN))
def test_each_listed_spell_breaks_a_rigid_pair_in_the_file_and_only_there(file):
    """Inside the spell the marker's labeled point is far off its rigid partner (the labels name another
    marker); in the second before and after, on it (the same marker and partner, labeled right)."""
    rec = read_c3d(data_path(file))
    names = list(rec.labels)
    for e in KNOWN[file]:
        a, b = names.index(e.marker), names.index(e.partner)
        d = np.linalg.norm(rec.points_m[:, a] - rec.points_m[:, b], axis=1)
        margin = int(rec.rate_hz)
        around = np.r_[d[e.first - margin:e.first], d[e.last + 1:e.last + 1 + margin]]
        usual = np.nanmedian(around)
        assert np.nanmax(np.abs(around - usual)) < 0.02  # rigid around the spell
        assert np.nanmax(np.abs(d[e.first:e.last + 1] - usual)) > 0.1  # and broken, by 10 cm or more, in it
        assert set(e.markers) <= set(names)


def test_the_points_of_a_spell_are_left_out_of_the_score_truth_and_label_alike():
    """A labeler that named the listed markers' points otherwise in the spell (following the markers, not
    the file's labels) is scored wrong; with the spell unscored, only its other points count."""
    file = sorted(KNOWN)[0]
    e = KNOWN[file][0]
    names = tuple(sorted(set(e.markers) | {"Derrick:RSHO"}))
    n = e.last + 3
    truth = [np.arange(len(names)) for _ in range(n)]
    seq = CorruptedSequence([np.zeros((len(names), 3)) for _ in range(n)], truth, names, 50.0)
    given = [list(names) for _ in range(n)]
    turned = dict(zip(e.markers, e.markers[1:] + e.markers[:1]))  # each listed marker named as the next
    for f in range(e.first, e.last + 1):
        given[f] = [turned.get(name, name) for name in names]
    as_is = score(seq, given)
    seq2, given2 = unscored(file, seq, given)
    out = score(seq2, given2)
    assert as_is.n_wrong == 3 * (e.last - e.first + 1) and out.n_wrong == 0 and out.precision == 1.0
    assert out.n_true_points == as_is.n_true_points - 3 * (e.last - e.first + 1)
    assert unscored("some/other.c3d", seq, given) is None
