"""service/partners.py: rigid partners learned online. Their prediction against a known rigid motion, a
pair distance sampled too few times that must not make partners, and a swap the running statistics absorbed
that the long-memory ones still see and repair."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service import partners, track_state, tracker
from tests.tracker_fixtures import seeded_state


def test_rigid_predictions_follow_a_known_rigid_motion():
    rng = np.random.default_rng(0)
    body = rng.uniform(-0.2, 0.2, (10, 3)) + [0, 0, 1]
    history = np.stack([body + [0.001 * k, 0, 0] for k in range(40)])  # rigid: distances never vary
    model, st = seeded_state(history, 40)
    partners._update_partners(st)
    R = Rotation.from_rotvec([0.2, -0.4, 0.9]).as_matrix()
    moved = (body - body.mean(0)) @ R.T + [1.0, 2.0, 0.5]
    labeled = np.ones(10, bool)
    labeled[3] = False
    now = np.where(labeled[:, None], moved, np.nan)
    pred, spread, _ = partners.rigid_predictions(st, now, labeled, ~labeled)
    np.testing.assert_allclose(pred[3], moved[3], atol=1e-9)
    assert spread[3] < 1e-6  # closed-form misfit: exact up to ~1e-8 m of rounding
    assert np.all(np.isnan(pred[labeled]))  # only the markers asked for


def test_partners_need_a_distance_sampled_often_enough():
    """A pair seen together in a few frames only looks perfectly rigid (no spread yet): it must not outrank
    a pair whose small spread was measured over many frames."""
    model = track_state.SubjectModel("P", tuple("abc"), np.full(3, -1), np.zeros((3, 3)), np.zeros((14, 3)))
    st = tracker.new_state(model, np.zeros((3, 3)), 0)
    st.dist_n[:] = [[0, 5, 100], [5, 0, 5], [100, 5, 0]]
    st.dist_mean_m[:] = 0.1
    st.dist_var_m2[:] = [[0, 0, 0.002**2], [0, 0, 0], [0.002**2, 0, 0]]
    partners._update_partners(st)
    assert st.partners[0, 0] == 2 and 1 not in st.partners[0]
    assert (st.partners[1] == -1).all()  # nothing sampled often enough yet


@pytest.mark.parametrize("long_memory", [True, False])
def test_a_swap_the_running_distance_statistics_absorbed_is_swapped_back(monkeypatch, long_memory):
    """Two rigid bodies move apart after one marker of each was tracked through a crossing swapped (a wrist
    passing 1.3 cm from a waist marker, 135_02 at L2). Within ten updates the running statistics widen
    enough for the swapped labels to look normal; the long-memory ones do not, and the repair swaps back."""
    if not long_memory:
        monkeypatch.setattr(partners, "SLOW_ALPHA", 0.02)  # the long memory as short as the running one
    rng = np.random.default_rng(3)
    plate = rng.uniform(-0.05, 0.05, (4, 3))
    hist = []
    for f in range(300):  # body B wanders about body A, each turning on its own
        ra = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        rb = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        hist.append(np.vstack([plate @ ra.T, plate @ rb.T + [0.3, 0, 0] + rng.normal(0, 0.1, 3)]))
    hist = np.array(hist)
    model = track_state.SubjectModel("P", tuple(f"M{i}" for i in range(8)), np.zeros(8, int), np.zeros((8, 3)), np.zeros((14, 3)))
    st = tracker.new_state(model, hist[-1], 0, hist)
    # A's marker 0 and B's marker 4 met 1.3 cm apart and their labels crossed; B then moves off 15 cm over
    # ten updates of the statistics (20 frames), the labels still crossed
    a, b = plate.copy(), plate.copy()
    b += a[0] - b[0] + [0.013, 0, 0]
    for k in range(10):
        now = np.vstack([a, b + [0.015 * k, 0, 0]])
        crossed = now.copy()
        crossed[[0, 4]] = now[[4, 0]]
        partners._update_distances(st, crossed, np.ones(8, bool))
    point_index = np.array([4, 1, 2, 3, 0, 5, 6, 7])  # point 0 is A's marker 0 ...
    cur = now[point_index]
    assert partners.distance_misfit(st, cur, np.ones(8, bool))[[0, 4]].max() < partners.Z_SUSPECT  # absorbed
    partners._repair_by_distances(st, point_index, cur, now, np.zeros(8, bool))
    assert (point_index == np.arange(8)).all() == long_memory


@pytest.mark.parametrize("offset_m", [0.10, 0.03])
def test_a_far_reacquisition_needs_more_than_the_median_of_its_partners(offset_m):
    """A hidden left forearm marker and its three most rigid partners (the wrist pair and the elbow); a
    serving right wrist's point at distances that stray from the long-run means by 0.8, 9.0 and 3.7 z (tennis
    at L2): the median, 3.7, passes Z_SUSPECT. Taken 10 cm from where the marker was predicted (a gate
    widened to 135 mm), the capped mean (4.2) refuses it; 3 cm from it, within the re-acquisition gate's
    base, the median stays the rule."""
    model = track_state.SubjectModel("P", ("LFRM", "LWRA", "LELB", "LWRB"), np.full(4, -1), np.zeros((4, 3)),
                                     np.zeros((14, 3)))
    st = tracker.new_state(model, np.zeros((4, 3)), 0)
    means, sigmas = np.array([0.163, 0.109, 0.153]), np.array([0.0032, 0.0060, 0.0063])
    st.dist_n[:] = 200
    st.dist_mean_m[0, 1:] = st.dist_mean_m[1:, 0] = means
    st.dist_var_m2[0, 1:] = st.dist_var_m2[1:, 0] = sigmas**2
    st.partners[:] = -1
    st.partners[0, :3] = [1, 2, 3]
    z = np.array([0.8, 9.0, 3.7])
    dist = means + np.array([1, 1, -1]) * z * (sigmas + 0.003)
    # three partners placed on the axes, the marker's point where those distances meet
    cur = np.zeros((4, 3))
    cur[1:] = np.eye(3) * 0.1
    x = _trilaterate(cur[1:], dist)
    cur[0] = x
    labeled = np.ones(4, bool)
    got = partners.distance_misfit(st, cur, labeled, np.array([0]))[0]
    np.testing.assert_allclose(got, 3.7, atol=1e-6)  # the median passes
    capped = partners.distance_misfit(st, cur, labeled, np.array([0]), cap=partners.FAR_Z_CAP)[0]
    np.testing.assert_allclose(capped, (0.8 + partners.FAR_Z_CAP + 3.7) / 3, atol=1e-6)
    pred = cur.copy()
    pred[0] = x + [offset_m, 0.0, 0.0]
    refused = partners.far_reacquisitions_misfit(st, cur, labeled, np.array([0]), pred, 0.045)
    assert refused[0] == (offset_m > 0.045)


def _trilaterate(anchors: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """A point at distances `dist` from three `anchors` (least squares, to rounding)."""
    from scipy.optimize import least_squares

    return least_squares(lambda x: np.linalg.norm(anchors - x, axis=1) - dist, np.full(3, 0.1), xtol=1e-15, ftol=1e-15, gtol=1e-15).x
