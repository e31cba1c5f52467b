"""The compiled loops against the plain numpy formulations they replaced (written out here as references),
on random data with the awkward cases: unlabeled markers, missing partners, NaN snapshots, reflections.
(`kabsch_rms` is checked against a Kabsch by scipy through its wrapper, in test_layouts.)"""

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from service import kernels


def _random_case(seed: int, m: int = 12, k: int = 6):
    rng = np.random.default_rng(seed)
    pos = rng.normal(0.0, 0.3, (m, 3))
    labeled = rng.random(m) > 0.25
    partners = np.array([rng.permutation(np.delete(np.arange(m), i))[:k] for i in range(m)])
    partners[rng.random((m, k)) < 0.1] = -1
    snap = pos[None] + rng.normal(0.0, 0.01, (m, m, 3))
    snap[rng.random((m, m)) < 0.1] = np.nan
    var = rng.uniform(0.0, 1e-4, (m, m))
    n = rng.integers(0, 30, (m, m)).astype(float)
    mean = cdist(pos, pos) + rng.normal(0.0, 0.01, (m, m))
    return pos, np.where(labeled[:, None], pos, np.nan), labeled, partners, snap, var, n, mean


def _rigid_reference(partners, snap, var, cur, labeled, i):
    """Weighted Kabsch of marker i's usable partners, by scipy's rotation fit."""
    js = [j for j in partners[i] if j >= 0 and labeled[j] and np.isfinite(snap[i, j, 0])]
    if len(js) < 3 or not np.isfinite(snap[i, i, 0]):
        return np.full(3, np.nan), np.nan
    w = np.array([1.0 / (np.sqrt(var[i, j]) + kernels.SKIN_M) ** 2 for j in js])
    src, dst = snap[i, js], cur[js]
    cs, cd = w @ src / w.sum(), w @ dst / w.sum()
    rot, _ = Rotation.align_vectors(dst - cd, src - cs, weights=w)
    resid = rot.apply(src - cs) - (dst - cd)
    return rot.apply(snap[i, i] - cs) + cd, np.sqrt((w * (resid**2).sum(1)).sum() / w.sum())


def test_rigid_predict_matches_a_weighted_kabsch_by_scipy():
    for seed in range(5):
        _, cur, labeled, partners, snap, var, _, _ = _random_case(seed)
        which = np.ones(len(cur), bool)
        which[::4] = False
        pred, spread, _ = kernels.rigid_predict(partners, snap, var, cur, labeled, which)
        for i in range(len(cur)):
            want_p, want_s = _rigid_reference(partners, snap, var, cur, labeled, i) if which[i] else (np.full(3, np.nan), np.nan)
            np.testing.assert_allclose(pred[i], want_p, atol=1e-9)
            np.testing.assert_allclose(spread[i], want_s, atol=1e-7)


def test_rigid_predict_reports_the_swing_of_partners_in_a_line_far_from_the_marker():
    """Three partners nearly in a line (a knee, a thigh and a shoulder marker) leave the turn about that
    line to their skin wobble (1 mm here), which swings a marker 30 cm off the line by centimetres: a
    swing over 5 cm, and the prediction that far off. The same marker near a spread-out set: a small
    swing, and predicted within a centimetre."""
    rng = np.random.default_rng(0)
    line = np.array([[0.0, 0.0, 0.5], [0.0, 0.003, 0.8], [0.002, 0.0, 1.4]])
    spread_out = np.array([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])
    for partners_at, marker, want in ((line, [0.3, 0.0, 0.0], False), (spread_out, [0.05, 0.05, 0.05], True)):
        pos = np.vstack([marker, partners_at])
        m = len(pos)
        partners = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], np.int64)
        snap = np.broadcast_to(pos, (m, m, 3)).copy()
        R = Rotation.from_rotvec([0.1, 0.2, 0.0]).as_matrix()
        now = pos @ R.T + rng.normal(0.0, 0.001, pos.shape)
        labeled = np.array([False, True, True, True])
        which = ~labeled
        pred, _, swing = kernels.rigid_predict(partners, snap, np.zeros((m, m)), np.where(labeled[:, None], now, np.nan), labeled, which)
        assert (swing[0] < 0.05) == want
        assert (np.linalg.norm(pred[0] - now[0]) < 0.01) == want


@pytest.mark.parametrize("cap", [np.inf, 2.0])
def test_distance_misfit_is_the_median_z_over_the_three_most_rigid_partners(cap):
    """... or, with a finite cap, the mean of those z each capped at it, where that is larger."""
    for seed in range(5):
        _, cur, labeled, partners, _, var, n, mean = _random_case(seed)
        rows = np.array([0, 2, 3, 5, 7, 11])
        got = kernels.distance_misfit(partners, n, mean, var, cur, labeled, rows, cap)
        for i in range(len(cur)):
            js = [j for j in partners[i] if j >= 0 and labeled[j] and n[i, j] >= 10] if labeled[i] and i in rows else []
            js = sorted(js, key=lambda j: np.sqrt(var[i, j]))[:3]  # (stable: the first listed wins a tie)
            z = sorted(abs(np.linalg.norm(cur[i] - cur[j]) - mean[i, j]) / (np.sqrt(var[i, j]) + kernels.SKIN_M) for j in js)
            want = z[(len(z) - 1) // 2] if len(z) >= 2 else np.nan
            if len(z) >= 2 and np.isfinite(cap):
                want = max(want, np.minimum(z, cap).mean())
            np.testing.assert_allclose(got[i], want, rtol=1e-12)


def test_update_distances_folds_labeled_pairs_into_running_means_and_variances():
    pos, _, labeled, _, _, _, n, mean = _random_case(3)
    var = np.full_like(mean, 1e-4)
    stats = [n.copy(), mean.copy(), var.copy(), mean.copy(), var.copy()]
    kernels.update_distances(*stats, pos, labeled, 0.02, 0.002)
    d = cdist(pos, pos)
    pair = labeled[:, None] & labeled[None, :]
    want_n = n + pair
    np.testing.assert_array_equal(stats[0], want_n)
    for (got_mean, got_var), a in (((stats[1], stats[2]), 0.02), ((stats[3], stats[4]), 0.002)):
        alpha = np.where(pair, np.maximum(1.0 / np.maximum(want_n, 1.0), a), 0.0)
        delta = d - mean
        np.testing.assert_allclose(got_mean, mean + alpha * delta, rtol=1e-12)
        np.testing.assert_allclose(got_var, (1 - alpha) * var + (1 - alpha) * alpha * delta**2, rtol=1e-12)


def test_gated_pairs_finds_the_pairs_in_the_gates_and_says_when_there_is_a_choice():
    pred = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [np.nan, 0, 0]])
    gates = np.array([0.1, 0.1, 0.0, 0.1])
    points = np.array([[1.05, 0, 0], [0.02, 0, 0], [2.0, 0, 0], [5.0, 0, 0]])
    rows, cols, cost, n_row, n_col = kernels.gated_pairs(pred, gates, points, np.ones(4, bool))
    assert cost.shape == (0, 0)  # one point in each gate, no point in two: the pairs themselves
    assert rows.tolist() == [0, 1] and cols.tolist() == [1, 0]
    points[2] = [0.06, 0, 0]  # a second point in marker 0's gate: a choice, for the Hungarian method
    rows, cols, cost, n_row, n_col = kernels.gated_pairs(pred, gates, points, np.array([True, True, True, False]))
    assert rows.tolist() == [0, 1] and cols.tolist() == [0, 1, 2]
    sharp = kernels.GATE_LOG_WEIGHT * np.log(0.1)
    np.testing.assert_allclose(cost, [[kernels.BIG, 0.02**2 / 0.01 + sharp, 0.06**2 / 0.01 + sharp],
                                      [0.05**2 / 0.01 + sharp, kernels.BIG, kernels.BIG]])
    assert n_row.tolist() == [2, 1] and n_col.tolist() == [1, 1, 1]
    r, c = linear_sum_assignment(cost)
    got_rows, got_cols, contested = kernels.assigned(rows, cols, cost, n_row, n_col, r, c)
    assert got_rows.tolist() == [0, 1] and got_cols.tolist() == [1, 0] and contested.tolist() == [True, False]
    # markers 0 and 1 share one point, marker 2 has two: the Hungarian method pairs all three, one of
    # the first two outside its gate (cost BIG), which is dropped
    pred, gates = np.array([[0.0, 0, 0], [0.05, 0, 0], [3.0, 0, 0]]), np.full(3, 0.1)
    points = np.array([[0.02, 0, 0], [3.0, 0, 0], [3.05, 0, 0]])
    rows, cols, cost, n_row, n_col = kernels.gated_pairs(pred, gates, points, np.ones(3, bool))
    r, c = linear_sum_assignment(cost)
    assert (cost[r, c] >= kernels.BIG).sum() == 1
    got_rows, got_cols, contested = kernels.assigned(rows, cols, cost, n_row, n_col, r, c)
    keep = cost[r, c] < kernels.BIG
    assert got_rows.tolist() == rows[r[keep]].tolist() and got_cols.tolist() == cols[c[keep]].tolist()
    assert len(got_rows) == 2 and 2 in got_rows.tolist() and contested.all()


def test_a_marker_placed_sharply_takes_a_contested_point_from_one_placed_loosely():
    # one point, two hidden markers: the waist marker's prediction (gate 7 cm) 6.2 cm off, the hand's (gate
    # 13.5 cm) 11.6 cm off; the hand is nearer in units of its gate (0.86 < 0.89), the waist far likelier
    pred = np.array([[0.062, 0, 0], [0, 0.116, 0]])
    gates = np.array([0.070, 0.135])
    points = np.zeros((1, 3))
    rows, cols, cost, _, _ = kernels.gated_pairs(pred, gates, points, np.ones(1, bool))
    r, c = linear_sum_assignment(cost)
    assert rows[r].tolist() == [0] and cols[c].tolist() == [0]


def test_track_predictions_and_labels_follow_velocity_acceleration_and_the_gate():
    pos = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    vel = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 0]])
    acc = np.array([[100.0, 0, 0], [0, 0, 0], [0, 0, 0]])
    labeled = np.array([True, True, False])
    pred, speed, gates = kernels.track_predictions(pos, vel, acc, labeled, 0.01, True, 0.03)
    np.testing.assert_allclose(pred, [[0.015, 0, 0], [1.0, 0.02, 0], [2.0, 0, 0]])
    np.testing.assert_allclose(speed, [1.0, 2.0, 0.0])
    np.testing.assert_allclose(gates, [0.03 + 0.35 * 0.01, 0.03 + 0.35 * 0.02, 0.0])  # none for a hidden marker
    pred_no_acc, _, _ = kernels.track_predictions(pos, vel, acc, labeled, 0.01, False, 0.03)
    np.testing.assert_allclose(pred_no_acc[0], [0.01, 0, 0])
    points = np.array([[1.0, 0.05, 0], [0.015, 0.0, 0]])  # marker 1's point 3 cm off its heading
    seen = np.ones(3, bool)
    idx, cur, lab, check = kernels.track_labels(points, np.array([0, 1]), np.array([1, 0]), np.array([False, False]),
                                                pred, speed, 0.01, 3, 0.006, seen, 0, 4)
    assert idx.tolist() == [1, 0, -1] and lab.tolist() == [True, True, False] and np.isnan(cur[2]).all()
    np.testing.assert_array_equal(cur[:2], points[[1, 0]])
    # marker 0 checked as the full check's turn (phase 0 of 4), 1 as off its heading, 2 as unlabeled
    assert check.tolist() == [True, True, True]
    _, _, _, check = kernels.track_labels(points, np.array([0, 1]), np.array([1, 0]), np.array([False, False]),
                                          pred, speed, 0.01, 3, 0.006, seen, 1, 4)
    assert check.tolist() == [False, True, True]
    seen[2] = False  # never seen: never checked
    _, _, _, check = kernels.track_labels(points, np.array([0, 1]), np.array([1, 0]), np.array([True, False]),
                                          pred, speed, 0.01, 3, 0.006, seen, 1, 4)
    assert check.tolist() == [True, True, False]  # (marker 0 contested)


def test_carried_labels_match_the_numpy_formulation():
    """A label is carried when no other labeled point lies in its gate and its step is short of half the
    way to the nearest other labeled point; as the numpy formulation it replaced."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        m = 12
        cur = rng.uniform(0.0, 0.3, (m, 3))
        point_index = np.arange(m)
        point_index[rng.random(m) < 0.3] = -1
        cur[point_index < 0] = np.nan
        pred = cur + rng.normal(0.0, 0.01, (m, 3))
        gates = rng.uniform(0.02, 0.08, m)
        speed = rng.uniform(0.0, 3.0, m)
        got = kernels.carried_labels(point_index, cur, pred, gates, speed, 0.01, 0.5)
        with np.errstate(invalid="ignore"):
            rival = np.linalg.norm(cur[None] - pred[:, None], axis=2) < gates[:, None]
            apart = np.linalg.norm(cur[None] - cur[:, None], axis=2)
        np.fill_diagonal(rival, False)
        np.fill_diagonal(apart, np.inf)
        slid = speed * 0.01 > 0.5 * np.min(np.where(np.isnan(apart), np.inf, apart), axis=1)
        want = np.where(rival.any(1) | slid, -1, point_index)
        np.testing.assert_array_equal(got, want)


def test_commit_motion_measures_velocity_on_two_frames_and_keeps_it_on_reacquisition():
    pos = np.zeros((3, 3))
    vel = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 3.0]])
    cur = np.array([[0.01, 0, 0], [9.0, 9.0, 9.0], [np.nan] * 3])
    was = np.array([True, False, True])
    now = np.array([True, True, False])
    fallback = np.full((3, 3), 7.0)
    p, v, a, measured, hidden = kernels.commit_motion(pos, vel, np.zeros((3, 3)), np.ones(3, bool), np.array([0, 4, 0]),
                                                      was, cur, now, fallback, 0.01, 15.0, 300.0)
    np.testing.assert_allclose(v, [[1.0, 0, 0], [0, 2.0, 0], [0, 0, 2.4]])  # measured 1 m/s; kept; decayed 0.8
    np.testing.assert_allclose(p, [[0.01, 0, 0], [9.0, 9.0, 9.0], [7.0, 7.0, 7.0]])
    assert measured.tolist() == [True, False, False] and hidden.tolist() == [0, 0, 1]
    np.testing.assert_allclose(a, 0.0)  # the velocity did not change
    cur[0] = [1.0, 0, 0]  # 100 m/s: capped at 15 m/s, the acceleration at 300 m/s^2
    _, v, a, _, _ = kernels.commit_motion(pos, vel, np.zeros((3, 3)), np.ones(3, bool), np.zeros(3, np.int64),
                                          was, cur, now, fallback, 0.01, 15.0, 300.0)
    np.testing.assert_allclose(v[0], [0.7 * 15.0 + 0.3, 0, 0])
    np.testing.assert_allclose(a[0], [300.0, 0, 0])


def test_snapshot_rewrites_the_rows_of_labeled_markers():
    snap = np.zeros((3, 3, 3))
    cur = np.arange(9.0).reshape(3, 3)
    kernels.snapshot(snap, cur, np.array([True, False, True]))
    want_row = np.where(np.array([True, False, True])[:, None], cur, np.nan)
    np.testing.assert_array_equal(snap[0], want_row)
    np.testing.assert_array_equal(snap[2], want_row)
    np.testing.assert_array_equal(snap[1], 0.0)


def test_world_transforms_match_the_batched_numpy_forward_kinematics():
    from protocol.skeleton import PARENTS
    from service import calibration

    rng = np.random.default_rng(2)
    R = Rotation.random(14, random_state=3).as_matrix()
    t, offsets = rng.normal(size=3), rng.normal(0.0, 0.3, (14, 3))
    Rs, ps = kernels.world_transforms(t, R, offsets, np.asarray(PARENTS, np.int64))
    want_R, want_p = calibration.world_transforms(t, R, offsets)
    np.testing.assert_allclose(Rs, want_R, atol=1e-12)
    np.testing.assert_allclose(ps, want_p, atol=1e-12)


def test_repeats_are_the_later_point_of_each_close_pair():
    points = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.004, 0, 0], [1.0, 0.003, 0], [0.0, 0.005, 0]])
    assert kernels.repeats(points, 0.005).tolist() == [2, 3, 4]
    assert kernels.repeats(points, 0.001).tolist() == []


def test_relabel_candidates_score_every_relabelling_as_the_batched_numpy_did():
    rng = np.random.default_rng(6)
    m = 9
    layout = rng.normal(0.0, 0.05, (m, 3))
    R = Rotation.random(random_state=7).as_matrix()
    cur = layout @ R.T + 1.0 + rng.normal(0.0, 0.002, (m, 3))
    cur[[7, 8]] = np.nan  # unlabeled: their last positions are in `pos`
    pos = layout @ R.T + 1.0 + rng.normal(0.0, 0.2, (m, 3))
    provisional = np.array([0, 5, 0, 0, 0, 0, 0, 0, 0])
    lab, slot = np.array([0, 1, 2, 3]), np.array([0, 1, 2, 3, 7, 8])
    maps = np.array(list(__import__("itertools").permutations(range(6), 4)))
    where = np.where(np.isfinite(cur), cur, pos)
    rms, blocked = kernels.relabel_candidates(layout, cur, where, provisional, lab, slot, maps, 0.2, 0.3)
    A, B = layout[slot[maps]], np.broadcast_to(cur[lab], maps.shape + (3,)).copy()
    np.testing.assert_allclose(rms, kernels.kabsch_rms(A, B, np.ones(maps.shape, bool)), atol=1e-12)
    assert rms[0] < 0.004 and rms[1:].min() > rms[0]  # the identity fits; no permutation does as well
    jump = np.linalg.norm(cur[lab][:, None] - where[slot][None], axis=2)[np.arange(4), maps].max(1)
    to_spare = maps >= 4
    want = (jump > np.where(to_spare.any(1), 0.2, 0.3)) | (to_spare & (provisional[lab] <= 0)).any(1)
    np.testing.assert_array_equal(blocked, want)
    assert not want.all() and want.any()


def test_rigid_motion_matches_scipy_and_keeps_a_rotation_for_mirrored_points():
    rng = np.random.default_rng(8)
    for case in range(20):
        a = rng.normal(0.0, 0.1, (5, 3))
        R = Rotation.random(random_state=case).as_matrix()
        b = a @ R.T + [0.5, -1.0, 2.0] + rng.normal(0.0, 0.003, (5, 3))
        if case % 4 == 0:
            b = b * [1.0, 1.0, -1.0]  # mirrored: the best proper rotation, never a reflection
        got_R, got_t = kernels.rigid_motion(a, b)
        want, _ = Rotation.align_vectors(b - b.mean(0), a - a.mean(0))
        np.testing.assert_allclose(got_R, want.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(got_R), 1.0, atol=1e-12)
        np.testing.assert_allclose(got_t, b.mean(0) - got_R @ a.mean(0), atol=1e-12)


def test_joint_hypotheses_register_and_place_as_numpy_did_one_by_one():
    """Each hypothesis as `segment_search._around_joint` scored it with numpy: registered (Kabsch) with the
    segment's joint and labeled markers (without the joint when pinned and one marker), kept if its
    residuals pass, and every lost marker placed on the nearest candidate point within the inlier radius."""
    from service.track_state import _norm

    rng = np.random.default_rng(9)
    off = rng.normal(0.0, 0.06, (8, 3))
    R0 = Rotation.random(random_state=3).as_matrix()
    joint = np.array([0.3, -0.2, 1.1])
    truth = off @ R0.T + joint
    points = np.vstack([truth + rng.normal(0.0, 0.002, truth.shape), rng.uniform(-0.2, 0.2, (30, 3)) + joint])
    los, pool = np.array([3, 4, 5, 6, 7]), np.arange(3, len(points))
    near = pool[_norm(points[pool] - joint) < 0.25]
    hyps = [((3, 3),), ((4, 4),), ((3, 9),), ((5, 5), (6, 6)), ((5, 12), (7, 7)), ((6, 6), (7, 20))]
    mk = np.array([[i for i, _ in h] + [-1] * (2 - len(h)) for h in hyps])
    pt = np.array([[p for _, p in h] + [-1] * (2 - len(h)) for h in hyps])
    for lab, pinned in ((np.array([0, 1, 2]), True), (np.array([0, 1]), False), (np.array([0]), False)):
        base_a = np.vstack([np.zeros((1, 3)), off[lab]])
        base_b = np.vstack([joint[None] + 0.004, points[lab]])
        keep, rms, Rs, ts, placed = kernels.joint_hypotheses(base_a, base_b, off, points, mk, pt, los, pool, near,
                                                             pinned, 0.03, 0.02)
        for h, hyp in enumerate(hyps):
            A = np.vstack([base_a, off[[i for i, _ in hyp]]])
            B = np.vstack([base_b, points[[p for _, p in hyp]]])
            one = pinned and len(hyp) == 1
            R, t = kernels.rigid_motion(A[1:], B[1:]) if one else kernels.rigid_motion(A, B)
            res = _norm(A @ R.T + t - B)
            want = not ((not one and res.max() > 0.06) or res[1:].max() > 0.04)
            assert keep[h] == want, (lab, h)
            if not want:
                continue
            np.testing.assert_allclose(rms[h], np.sqrt(np.mean(res[1:] ** 2 if one else res**2)), rtol=1e-12)
            np.testing.assert_allclose(Rs[h], R, atol=1e-14)
            np.testing.assert_allclose(ts[h], t, atol=1e-14)
            cands = pool if one else near
            d = _norm((off[los] @ R.T + t)[:, None] - points[cands][None])
            np.testing.assert_array_equal(placed[h], np.where(d.min(1) < 0.02, cands[d.argmin(1)], -1))
        assert keep.any() and not keep.all() and (placed[keep] >= 0).any()


def test_segment_fits_register_every_labelling_and_place_the_joint():
    rng = np.random.default_rng(9)
    off = rng.normal(0.0, 0.06, (6, 3))  # a segment of six markers; its joint at the offsets' origin
    R = Rotation.random(random_state=10).as_matrix()
    joint = np.array([0.3, 0.1, 1.2])
    pts = off[[4, 1, 2]] @ R.T + joint  # markers 4, 1, 2 seen
    perms = np.array(list(__import__("itertools").permutations(range(6), 3)))
    rms, dist = kernels.segment_fits(off, joint, pts, perms, 1.0)
    best = int(np.argmin(rms))
    # (an exact fit reads ~1e-5 m: the closed-form misfit is a difference of sums of squares)
    assert perms[best].tolist() == [4, 1, 2] and rms[best] < 1e-4 and dist[best] < 1e-9
    for c in range(0, len(perms), 17):  # against a Kabsch by scipy
        a = off[perms[c]]
        rot, _ = Rotation.align_vectors(pts - pts.mean(0), a - a.mean(0))
        t = pts.mean(0) - rot.apply(a.mean(0))
        np.testing.assert_allclose(rms[c], np.sqrt(np.mean(np.sum((rot.apply(a) + t - pts) ** 2, 1))), atol=5e-5)
        np.testing.assert_allclose(dist[c], np.linalg.norm(t - joint), atol=1e-9)
    _, dist = kernels.segment_fits(off, joint, pts, perms, 0.005)  # the misfitting ones skipped
    assert np.isfinite(dist).sum() < len(perms) / 10 and dist[best] < 1e-9


KERNELS = ("track_predictions", "track_labels", "carried_labels", "rigid_predict", "distance_misfit", "update_distances",
           "kabsch_rms", "gated_pairs", "commit_motion", "snapshot", "world_transforms", "repeats",
           "relabel_candidates", "segment_fits", "rigid_motion", "joint_hypotheses", "rigid_check", "far_from_fit",
           "reacquire_gates", "frame_outcome", "finite_rows", "probation", "label_errors", "assigned", "unswap")


_COMPILE_ONCE = """
import numpy as np
from recordings.corruption import corrupt
from recordings.synthetic import perform
from service import kernels
from service.config import EngineConfig
from service.engine import Engine, FrameInput

Engine().warm_up()
before = {name: len(getattr(kernels, name).signatures) for name in KERNELS}
seq = corrupt(perform(1, marker_set="cmu41", duration_s=6.0).recording, "L3", 1)
for seeded in (True, False):  # a seeded subject; an automatic one from its T-pose
    engine = Engine(EngineConfig(tpose_auto=not seeded))
    for f, points in enumerate(seq.points_m):
        if points is not None:
            labels = seq.true_labels(f) if seeded and f < seq.seed_frames else None
            outputs, _ = engine.step(FrameInput("default", f, int(f * 1e9 / seq.rate_hz), points, labels))
    assert outputs and outputs[0].point_index.max() >= 0
print(before, {name: len(getattr(kernels, name).signatures) for name in KERNELS})
"""


def test_each_kernel_compiles_once_for_the_types_the_tracker_passes():
    """`warm_up` compiles (or loads) every kernel for the types the tracker and engine pass: a seeded
    subject and an automatic one, tracked through occlusions, ghosts and swaps (L3), never wait for a
    compilation. In a fresh process, so other tests' calls with other types do not count."""
    import subprocess
    import sys

    code = f"KERNELS = {KERNELS!r}\n" + _COMPILE_ONCE
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    before, after = out.stdout.strip().splitlines()[-1].split("} {")
    assert before + "}" == "{" + after, out.stdout
    assert all(n == 1 for n in eval(before + "}").values()), out.stdout


def _outcome_case(seed: int, m: int = 14):
    """Random per-marker inputs of the tracker's step: labels, rigid predictions (NaN where none), spreads,
    swings (NaN where none), the fit's positions."""
    rng = np.random.default_rng(seed)
    cur = rng.normal(0.0, 0.3, (m, 3))
    labeled = rng.random(m) < 0.6
    cur[~labeled] = np.nan
    rpred = np.where(labeled[:, None], cur, 0.0) + rng.normal(0.0, 0.02, (m, 3))
    rpred[rng.random(m) < 0.3] = np.nan
    spread = np.where(np.isfinite(rpred[:, 0]), rng.uniform(0.0, 0.01, m), np.nan)
    swing = np.where(rng.random(m) < 0.2, np.nan, rng.uniform(0.0, 0.02, m)) * (spread >= 0)
    skel = rpred + rng.normal(0.0, 0.05, (m, 3))
    skel[np.isnan(skel)] = rng.normal(0.0, 0.3, (np.isnan(skel).sum(),))
    return rng, cur, labeled, rpred, spread, swing, skel


def test_rigid_check_and_far_from_fit_match_the_numpy_formulation():
    """The rigid check of tracked labels, and hidden markers placed far from the fit, as the numpy
    formulation they replaced."""
    n_far = n_near = 0
    for seed in range(20):
        rng, cur, labeled, rpred, spread, swing, skel = _outcome_case(seed)
        m = len(cur)
        got = kernels.rigid_check(cur, rpred, spread, swing, labeled, 0.01, 0.012)
        has_rigid = np.isfinite(rpred[:, 0])
        spread0 = np.where(has_rigid, spread, 0.0)
        with np.errstate(invalid="ignore"):
            steady = has_rigid & (swing <= 0.01)
        err = np.where(labeled & steady, np.linalg.norm(cur - rpred, axis=1), 0.0)
        for a, b in zip(got, (has_rigid, spread0, err, labeled & steady & (err > 0.012 + 4.0 * spread0))):
            np.testing.assert_allclose(a, b, rtol=1e-12)
        partners = np.array([rng.permutation(np.delete(np.arange(m), i))[:5] for i in range(m)])
        partners[rng.random(partners.shape) < 0.2] = -1
        segment = rng.integers(0, 4, m)
        placed = ~labeled & has_rigid
        far = kernels.far_from_fit(rpred, skel, placed, labeled, partners, segment, 0.03, 0.2)
        p = np.maximum(partners, 0)
        same = ((partners >= 0) & labeled[p] & (segment[p] == segment[:, None])).any(1)
        want = placed & (np.linalg.norm(rpred - skel, axis=1) > np.where(same, 0.03, 0.2))
        np.testing.assert_array_equal(far, want)
        n_far += far.sum()
        n_near += (placed & ~far).sum()
    assert n_far > 10 and n_near > 10  # (both cases are met)


def test_reacquire_gates_and_frame_outcome_match_the_numpy_formulation():
    """Where hidden markers are looked for and how far, and the frame's outcome (sources, where the state
    puts hidden markers, the published predictions, whether the fit is wanted), with and without a fit,
    as the numpy formulation they replaced."""
    for seed in range(20):
        rng, cur, labeled, rpred, spread, swing, skel = _outcome_case(seed)
        m = len(cur)
        has_rigid = np.isfinite(rpred[:, 0])
        spread0 = np.where(has_rigid, spread, 0.0)
        stale = rng.random(m) < 0.2
        ever_seen = labeled | (rng.random(m) < 0.7)
        missing = ~labeled & ever_seen
        hidden = rng.integers(0, 200, m)
        coast = rng.normal(0.0, 0.3, (m, 3))
        point_index = np.where(labeled, rng.permutation(m), -1)
        reacquired = labeled & (rng.random(m) < 0.3)
        for use_fit in (False, True):
            trusted = rng.random(m) < (0.0, 0.5, 1.0)[seed % 3]  # (per marker: `tracker._trusted_markers`)
            got = kernels.reacquire_gates(rpred, has_rigid, spread0, stale, missing, skel, use_fit, trusted, hidden,
                                          0.01, 0.05, 0.12, 0.004, 0.5, 2.0)
            pred = np.where(has_rigid[:, None], rpred, np.nan)
            gate = np.where(has_rigid, np.minimum(0.8 * 0.05 + 3.0 * spread0, 0.12), 0.0)
            use_skel = np.zeros(m, bool)
            if use_fit:
                loose = has_rigid & ((spread0 > 0.004) | stale) & trusted
                use_skel = missing & (~has_rigid | loose)
                pred[use_skel] = skel[use_skel]
                gate[use_skel] = 0.05 * (1.0 + np.minimum(hidden * 0.01 / 0.5, 1.0))[use_skel]
            np.testing.assert_array_equal(got[0][missing], pred[missing])
            np.testing.assert_allclose(got[1], np.where(missing, gate, 0.0), rtol=1e-12)
            np.testing.assert_array_equal(got[2], use_skel)

            source, fallback, predicted, unplaced = kernels.frame_outcome(
                point_index, reacquired, cur, has_rigid, rpred, coast, skel, use_fit, ever_seen, spread0, stale,
                0.004, trusted)
            want = np.where(has_rigid[:, None], rpred, coast)
            if use_fit:
                want = np.where((~has_rigid)[:, None], skel, want)
            np.testing.assert_array_equal(fallback, want)
            np.testing.assert_array_equal(predicted, np.where(labeled[:, None], skel if use_fit else cur, want))
            np.testing.assert_array_equal(source, np.where(labeled, np.where(reacquired, 2, 1), 0))
            loose = (spread0 > 0.004) & trusted
            assert unplaced == (missing & (~has_rigid | loose | stale)).any()


def test_finite_rows_are_the_rows_with_three_finite_coordinates():
    pts = np.random.default_rng(0).normal(size=(50, 3))
    pts[np.random.default_rng(1).random((50, 3)) < 0.05] = np.nan
    pts[7, 1], pts[9, 2] = np.inf, -np.inf
    want = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
    np.testing.assert_array_equal(kernels.finite_rows(pts), want)
    assert 7 not in want and 9 not in want and 0 < len(want) < 50
    assert len(kernels.finite_rows(np.empty((0, 3)))) == 0


def test_probation_and_label_errors_match_the_numpy_formulation():
    """Labels on probation whose distances stray, the counts one frame on, and the distances of labels to
    their predictions, as the numpy formulation they replaced."""
    n_wrong = 0
    for seed in range(10):
        pos, cur, labeled, partners, snap, var, n, mean = _random_case(seed)
        rng = np.random.default_rng(seed)
        m = len(cur)
        provisional = rng.integers(-1, 4, m)
        hold = rng.integers(0, 3, m)
        wrong, prov, held = kernels.probation(partners, n, mean, var, cur, labeled, provisional, hold, 1.0)
        on = labeled & (provisional > 0)
        with np.errstate(invalid="ignore"):
            want = on & (kernels.distance_misfit(partners, n, mean, var, cur, labeled, np.flatnonzero(on), np.inf) > 1.0)
        np.testing.assert_array_equal(wrong, want)
        np.testing.assert_array_equal(prov, np.maximum(provisional - 1, 0))
        np.testing.assert_array_equal(held, np.maximum(hold - 1, 0))
        n_wrong += wrong.sum()
        pred = pos + rng.normal(0.0, 0.01, pos.shape)
        use = labeled & (hold <= 0)
        np.testing.assert_allclose(kernels.label_errors(cur, pred, use),
                                   np.linalg.norm(np.where(use[:, None], cur - pred, 0.0), axis=1), rtol=1e-12)
    assert n_wrong > 0


def _unswap_reference(point_index, cur, pred, err, tol_m):
    """The numpy formulation `kernels.unswap` replaced (tracker._unswap before it)."""
    sus = np.flatnonzero((err > tol_m) & (point_index >= 0))
    if len(sus) < 2:
        return False
    d = np.linalg.norm(cur[sus][None, :, :] - pred[sus][:, None, :], axis=2)  # d[a, b] = |cur[b] - pred[a]|
    crossed = d + d.T
    straight = err[sus][:, None] + err[sus][None, :]
    ok = crossed < 0.5 * straight
    np.fill_diagonal(ok, False)
    if not ok.any():
        return False
    score = np.where(ok, crossed / straight, np.inf)
    for flat in np.argsort(score, axis=None)[: int(ok.sum())]:
        a, b = divmod(int(flat), len(sus))
        i, k = sus[a], sus[b]
        if err[i] == 0.0 or err[k] == 0.0:
            continue
        point_index[i], point_index[k] = point_index[k], point_index[i]
        cur[[i, k]] = cur[[k, i]]
        err[i] = err[k] = 0.0
    return True


def test_unswap_uncrosses_the_pairs_the_numpy_formulation_did():
    """Markers tracked through crossed (each on the point where another is predicted), with bystanders
    off their predictions: the same swaps, best pairs first, as the numpy formulation it replaced."""
    rng = np.random.default_rng(7)
    n_swapped = 0
    for _ in range(200):
        m = 12
        pred = rng.uniform(0.0, 0.4, (m, 3))
        point_index = np.arange(m)
        point_index[rng.random(m) < 0.2] = -1
        cur = pred + rng.normal(0.0, 0.004, (m, 3))
        crossed = rng.permutation(m)[: rng.integers(0, 6)]
        cur[crossed] = cur[np.roll(crossed, 1)] + rng.normal(0.0, 0.01, (len(crossed), 3))  # a cycle of swaps
        cur[point_index < 0] = np.nan
        err = np.where(point_index >= 0, np.linalg.norm(cur - pred, axis=1), 0.0)
        args = [point_index.copy(), cur.copy(), pred, err.copy(), 0.01]
        want = _unswap_reference(*[a.copy() if isinstance(a, np.ndarray) else a for a in args])
        ref = [a.copy() if isinstance(a, np.ndarray) else a for a in args]
        _unswap_reference(*ref)
        got = kernels.unswap(*args)
        assert got == want
        np.testing.assert_array_equal(args[0], ref[0])
        np.testing.assert_array_equal(args[1], ref[1])
        n_swapped += int((args[0] != point_index).sum())
    assert n_swapped > 100
