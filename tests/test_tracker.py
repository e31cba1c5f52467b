"""service/tracker.py, the pure per-subject step: labels that survive shuffling, a 0.5 s occlusion and
ghosts beside the markers (no skeleton, no solver: what the tracker does on its own before a subject is
calibrated); the re-acquisition gates, a lost subject found again, the NNT prediction of an accelerating
marker; the skip budget of the solve (a counting stand-in for the solver). The machinery of its steps is
tested beside its own module: test_partners, test_segment_search, test_layouts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recordings.synthetic import perform
from service import layouts, partners, track_state, tracker
from tests.tracker_fixtures import CONFIG, RATE_HZ, run_tracker, seeded_state, t_ns


def _spy_on_gates(monkeypatch) -> list:
    """The gates of every `tracker._assign` call from now on (each step's first is the tracking one), in
    the list returned."""
    gates_seen = []
    assign = tracker._assign

    def spy(pred, gates, points, cand):
        gates_seen.append(gates.copy())
        return assign(pred, gates, points, cand)

    monkeypatch.setattr(tracker, "_assign", spy)
    return gates_seen


@pytest.mark.parametrize("has_skeleton", [True, False])
def test_reacquisition_gate_is_capped_however_loose_the_partners(monkeypatch, has_skeleton):
    """A hidden marker whose partners misfit a lot (a bending limb) gets a wider gate; once the subject has
    a skeleton, never beyond 3 x reacquire_gate_m (a 20 cm gate around a hidden wrist marker took its
    neighbour's point); without one, the partners are all there is and the gate stays wide."""
    rng = np.random.default_rng(1)
    body = rng.uniform(-0.15, 0.15, (10, 3)) + [0, 0, 1]
    history = np.stack([body + [0.001 * k, 0, 0] for k in range(40)])
    model, st = seeded_state(history, 40)
    model = dataclasses.replace(model, has_skeleton=has_skeleton)  # no solver: no fit, partners only
    partners._update_partners(st)
    gates_seen = _spy_on_gates(monkeypatch)
    drift = rng.normal(0, 0.0015, body.shape)  # per frame: the body bends out of shape, 8 cm in 60 frames
    for k in range(1, 61):
        now = history[-1] + k * drift
        cloud = np.delete(now, 3, axis=0)  # marker 3 hidden throughout
        st, res = tracker.step(model, st, cloud, np.ones(len(cloud), bool), t_ns(40 + k), CONFIG)
    assert (res.point_index >= 0).sum() == 9  # the partners were tracked through it
    labeled = res.point_index >= 0
    _, spread, _ = partners.rigid_predictions(st, res.positions_m, labeled, ~labeled)
    wide = 0.8 * CONFIG.reacquire_gate_m + 3.0 * spread[3]
    assert wide > 5 * CONFIG.reacquire_gate_m  # the gate the partners' misfit asks for
    if has_skeleton:
        assert 2 * CONFIG.reacquire_gate_m < gates_seen[-1][3] <= 3 * CONFIG.reacquire_gate_m + 1e-12
    else:
        assert gates_seen[-1][3] > 5 * CONFIG.reacquire_gate_m


@pytest.mark.parametrize("rate_hz", [50.0, 120.0])
def test_the_tracking_gate_widens_with_the_frame_interval(monkeypatch, rate_hz):
    """A marker standing still is tracked within nnt_gate_m plus the way an acceleration the prediction
    does not model carries it in one frame interval (NNT_UNMODELED_ACC_M_S2): 5 mm at 50 Hz, where serving
    wrists outran the 30 mm gate, under 1 mm at 120 Hz."""
    body = np.random.default_rng(2).uniform(-0.15, 0.15, (6, 3)) + [0, 0, 1]
    model, st = seeded_state(np.stack([body] * 5), 5)
    gates_seen = _spy_on_gates(monkeypatch)
    dt = 1.0 / rate_hz
    t0 = st.last_t_ns
    for k in range(1, 4):
        first = len(gates_seen)  # (the step's first assignment is the tracking one)
        st, res = tracker.step(model, st, body, np.ones(len(body), bool), t0 + int(round(k * dt * 1e9)), CONFIG)
    assert (res.point_index >= 0).all()
    widening = 0.5 * tracker.NNT_UNMODELED_ACC_M_S2 * dt**2
    np.testing.assert_allclose(gates_seen[first], CONFIG.nnt_gate_m + widening, atol=1e-9)
    assert (widening > 0.004) if rate_hz == 50.0 else (widening < 0.001)


def test_relocate_finds_a_lost_subject_moved_and_turned():
    """A lost subject's last marker cloud is registered onto the unclaimed points: found 1 m away and
    turned 100 degrees, among ghosts; not found where nothing like it is."""
    rng = np.random.default_rng(5)
    body = rng.uniform([-0.2, -0.15, 0.0], [0.2, 0.15, 1.7], (30, 3))
    model, st = seeded_state(np.stack([body] * 5), 5)
    R = Rotation.from_rotvec([0.0, 0.0, np.radians(100)]).as_matrix()
    now = (body - body.mean(0)) @ R.T + body.mean(0) + [1.0, 0.3, 0.0]
    ghosts = rng.uniform(-3, 3, (8, 3)) + [0, 0, 1]
    points = np.concatenate([now[5:], ghosts])  # five of its markers still hidden
    found = tracker._relocate(st, points, np.ones(len(points), bool), 0.02)
    np.testing.assert_allclose(found, now, atol=1e-6)
    assert tracker._relocate(st, ghosts, np.ones(len(ghosts), bool), 0.02) is None


def test_markers_of_an_unobserved_segment_are_taken_together_at_the_model_distances():
    """On a segment none of whose markers is labeled, one skeleton-predicted re-acquisition alone is held
    back (it could be any of the segment's markers) unless its point is where the fit puts it and far from
    where it puts the others, and it did not hide moving fast; two are taken if their points are as far
    apart as the model says, and held back if not."""
    seg = np.array([0, 0, 1, 1, 1])
    off = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0, 0], [0.05, 0, 0], [0, 0.08, 0]], float)
    model = track_state.SubjectModel("P", tuple("abcde"), seg, off, np.zeros((14, 3)), True)
    labeled = np.array([True, True, False, False, False])  # segment 1 unobserved
    use_skel = np.ones(5, bool)
    cur = np.full((5, 3), np.nan)
    cur[2], cur[3], cur[4] = [1.0, 0, 0], [1.05, 0, 0], [1.0, 0.2, 0]
    seen = np.ones(5, bool)

    skel = cur + [0.0, 0.0, 0.02]  # the fit puts each 2 cm from its point: 5 cm from a neighbour's

    def hold(rows, labeled=labeled, seen=seen, skel=skel, drift=None):
        return tracker._unsure_on_unseen_segment(model, labeled, np.array(rows), cur, use_skel, seen, skel, drift)

    assert hold([3]).all()  # alone, 5 cm from where the fit puts marker 2
    far = skel.copy()
    far[2] = cur[3] + [0.0, 0.1, 0.0]
    assert not hold([3], skel=far).any()  # alone, but where the fit puts it and 10 cm from the others
    far[3] = cur[3] + [0.0, 0.0, 0.04]
    assert hold([3], skel=far).all()  # ... 4 cm from where the fit puts it
    far[3] = cur[3] + [0.0, 0.0, 0.02]
    fast = np.where(np.arange(5) == 3, 0.15, 0.0)  # it hid moving: 15 cm coasted (speed x time hidden)
    assert not hold([3], skel=far, drift=fast / 3).any()  # 5 cm: taken, where the fit puts it
    assert hold([3], skel=far, drift=fast).all()  # 15 cm: the fit's word on where it is counts for little
    assert not hold([2, 3]).any()  # 5 cm apart, as modelled
    assert hold([2, 4]).all()  # 20 cm apart, 8 cm modelled
    assert not hold([3], seen=np.array([1, 1, 0, 1, 0], bool)).any()  # the segment's only marker ever seen
    assert not hold([3], labeled=np.array([1, 1, 1, 0, 0], bool)).any()  # the segment is observed


def test_a_label_with_another_markers_point_in_its_gate_is_unsettled():
    """Tracking unsettles the labels it carried where a choice was possible: two markers whose points lie
    2 cm apart, inside each other's gates; the others stay settled (no skeleton: no layout check)."""
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-0.5, 0.5, (8, 3)) * [1.0, 1.0, 0.1] + [0.0, 0.0, 1.0]
    cloud[:, 0] += 0.3 * np.arange(8)  # spread out: no two points within 20 cm ...
    cloud[1] = cloud[0] + [0.02, 0.0, 0.0]  # ... but these two
    P = np.repeat(cloud[None], 241, axis=0)
    model, st = seeded_state(P, 240)
    assert st.settled.all()  # given labels
    st, res = tracker.step(model, st, P[240], np.ones(8, bool), t_ns(240), CONFIG)
    assert (res.point_index == np.arange(8)).all()
    assert not st.settled[0] and not st.settled[1]
    assert st.settled[2:].all()


@pytest.mark.parametrize("m", [0, 1, 2])
def test_a_subject_of_fewer_markers_than_a_partner_set_steps_without_error(m):
    """Degenerate subjects (no marker, one, two: fewer than three partners) step through random clouds,
    their partner lists rebuilt on the way, and label nothing they cannot tell."""
    model = track_state.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)),
                                     np.zeros((14, 3)))
    st = tracker.new_state(model, np.zeros((m, 3)), t_ns(0))
    rng = np.random.default_rng(m)
    for f in range(1, 70):  # past the partner update (every 30 frames)
        st, res = tracker.step(model, st, rng.normal(size=(5, 3)), np.ones(5, bool), t_ns(f), CONFIG)
        assert res.point_index.shape == (m,)
    assert st.partners.shape == (m, partners.N_PARTNERS)


def test_labels_survive_shuffling():
    P = perform(1, duration_s=4.0).recording.points_m
    got = run_tracker(P, 240)
    expected = np.arange(P.shape[1])
    assert np.all(got[240:] == expected)


def test_marker_occluded_for_half_a_second_comes_back_with_its_name():
    perf = perform(2, duration_s=5.0)
    P = perf.recording.points_m.copy()
    names = list(perf.marker_names)
    hidden = [names.index(n) for n in ("LFRM", "RKNE", "LBHD", "RTOE")]
    gap = slice(int(3.0 * RATE_HZ), int(3.5 * RATE_HZ))
    P[gap, hidden] = np.nan
    got = run_tracker(P, 240, shuffle_seed=2)
    assert np.all(got[gap, hidden] == -1)
    back = gap.stop + 3  # a few frames to be re-found
    for j in hidden:
        assert np.all(got[back:, j] == j), names[j]
    expected = np.where(np.isnan(P[:, :, 0]), -1, np.arange(P.shape[1]))
    assert np.all(got[240:] == expected[240:])


def test_ghosts_beside_markers_stay_unlabeled():
    """A ghost 4-8 cm from a marker in every frame, on a random marker: never labeled, never steals."""
    P = perform(3, duration_s=4.0).recording.points_m
    rng = np.random.default_rng(3)
    n = len(P)
    near = rng.integers(0, P.shape[1], n)
    direction = rng.standard_normal((n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    ghosts = (P[np.arange(n), near] + direction * rng.uniform(0.04, 0.08, (n, 1)))[:, None]
    got = run_tracker(P, 240, shuffle_seed=3, ghosts_m=ghosts)
    assert not np.any(got[240:] == -2)
    assert np.all(got[240:] == np.arange(P.shape[1]))


def _still_point_case(mates_speed, point_speed, own_mate_speed=None):
    """`_still_on_moving` for marker 0 re-acquired onto a point that moved at `point_speed` [m/s] along x
    over the last 3 frames, while its rigid partners (markers 1-4, on another segment) moved at
    `mates_speed`; with `own_mate_speed`, marker 5 (on marker 0's own segment) is labeled, moving so."""
    m = 6
    segment = np.array([2, 1, 1, 1, 1, 2])
    model = track_state.SubjectModel("P", tuple(f"M{i}" for i in range(m)), segment, np.zeros((m, 3)),
                                     np.zeros((14, 3)), has_skeleton=True)
    st = tracker.new_state(model, np.zeros((m, 3)), t_ns(3))
    st.partners[0] = [1, 2, 3, 4, 5, -1, -1, -1]
    st.vel_m_s[1:5] = [mates_speed, 0.0, 0.0]
    st.vel_measured[:] = True
    st.labeled[:] = [False, True, True, True, True, own_mate_speed is not None]
    if own_mate_speed is not None:
        st.vel_m_s[5] = [own_mate_speed, 0.0, 0.0]
    st.skel_vel_m_s = np.zeros((m, 3))
    point = np.array([0.5, 0.2, 1.0])
    for f in range(3):  # the point on frames 0-2, and a far one beside it
        st.free_history.append((t_ns(f), np.array([point - [point_speed * (3 - f) / RATE_HZ, 0, 0], [3.0, 3.0, 3.0]])))
    return tracker._still_on_moving(model, st, np.array([0]), point[None], st.labeled, t_ns(3))[0]


@pytest.mark.parametrize("mates_speed, point_speed, own_mate_speed, refused", [
    (1.5, 0.0, 1.5, True),  # a reflection standing still beside a limb moving at 1.5 m/s
    (1.5, 1.5, 1.5, False),  # the marker, moving with them
    (0.1, 0.0, 0.1, False),  # the limb still too: nothing told
    (1.5, 0.0, 0.0, False),  # a foot planted (a marker of its own still) while the shank turns over it
    (1.5, 0.0, None, False),  # no marker of its own segment labeled: the partners alone may be across a joint
])
def test_a_point_standing_still_while_the_markers_partners_move_is_not_taken(mates_speed, point_speed,
                                                                               own_mate_speed, refused):
    assert _still_point_case(mates_speed, point_speed, own_mate_speed) == refused


def test_the_tracker_keeps_the_points_it_left_unlabeled_for_the_stillness_check():
    """Each step keeps the points no label took (and no other subject claimed), for STILL_FRAMES frames."""
    P = perform(3, duration_s=0.5).recording.points_m
    model, st = seeded_state(P, 40)
    ghost = np.array([[2.0, 2.0, 1.0]])
    for f in range(40, 45):
        cloud = np.concatenate([P[f], ghost])
        free = np.ones(len(cloud), bool)
        free[0] = False  # claimed by another subject
        st, _ = tracker.step(model, st, cloud, free, t_ns(f), CONFIG)
    assert len(st.free_history) == track_state.STILL_FRAMES
    t, kept = st.free_history[-1]
    assert t == t_ns(44)
    np.testing.assert_allclose(kept, ghost)


def test_a_reacquired_marker_keeps_its_measured_velocity():
    """A velocity needs two observations: a marker found again where its (wrong) prediction was not gets
    the velocity it was last measured with, not (point - prediction) / dt, which turned prediction errors
    into speed and walked fast arms onto their neighbours (tennis serve at 50 Hz)."""
    m = 6
    st = tracker.new_state(
        track_state.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)), np.zeros((14, 3))),
        np.zeros((m, 3)), t_ns(0))
    st.vel_m_s[:] = [1.0, 0.0, 0.0]
    st.labeled[0] = False  # marker 0 hidden last frame: its position is a prediction, 10 cm off
    st.pos_m[0] = [0.1, 0.0, 0.0]
    cur = np.zeros((m, 3))
    cur[1:] += [1.0 / RATE_HZ, 0.0, 0.0]  # the tracked markers moved at 1 m/s
    tracker._commit(st, cur, np.ones(m, bool), cur, t_ns(1), 1.0 / RATE_HZ)
    np.testing.assert_allclose(st.vel_m_s[0], [1.0, 0.0, 0.0])  # not (0 - 0.1) * 120 = -12 m/s
    np.testing.assert_allclose(st.vel_m_s[1:, 0], 1.0)


def test_nnt_follows_an_accelerating_marker():
    """A marker swinging on a tight circle at 50 Hz (3.8 m/s, 123 m/s^2: a serving hand) curves 5 cm off a
    straight line each frame. Predicted with its measured acceleration it is tracked every frame; the
    control, a constant-velocity prediction (acceleration capped at 0), loses it. (At 3.6 m/s the control
    kept it once the gate widened with the frame interval, NNT_UNMODELED_ACC_M_S2.)"""
    rate, r, w = 50.0, 0.12, 32.0
    t = np.arange(100) / rate
    P = np.stack([r * np.cos(w * t), r * np.sin(w * t), np.ones_like(t)], axis=1)[:, None]
    model = track_state.SubjectModel("P", ("M0",), np.zeros(1, int), np.zeros((1, 3)), np.zeros((14, 3)))

    def lost_frames(max_acc: float) -> int:
        old, tracker.MAX_ACC_M_S2 = tracker.MAX_ACC_M_S2, max_acc
        try:
            ns = [int(round(f * 1e9 / rate)) for f in range(len(P))]
            st = tracker.new_state(model, P[0], ns[0], P[:1])
            for f in range(1, 5):
                st, _ = tracker.observe(model, st, P[f], ns[f], CONFIG)
            lost = 0
            for f in range(5, len(P)):
                st, res = tracker.step(model, st, P[f], np.ones(1, bool), ns[f], CONFIG)
                lost += int(res.point_index[0] < 0)
            return lost
        finally:
            tracker.MAX_ACC_M_S2 = old

    assert lost_frames(tracker.MAX_ACC_M_S2) == 0
    assert lost_frames(0.0) > 50


class _CountingSolver:
    """Stands in for PoseSolver: counts launches; every fit fails, so the tracker keeps its pose."""

    def __init__(self):
        self.launches = 0

    def launch(self, *args):
        self.launches += 1
        nan = np.full(3, np.nan)
        from service.solver import FitResult

        result = FitResult(nan, np.tile(np.eye(3), (14, 1, 1)), np.zeros((0, 3)), float("nan"), 0, False)
        return type("Pending", (), {"result": lambda self: result})()


def test_the_solve_is_skipped_at_most_max_skip_frames_and_max_skip_s():
    """Nothing hidden, so only the skip budget launches solves: every 11th frame at 120 Hz (10 skipped),
    every 6th at 50 Hz (0.1 s = 5 frames skipped)."""
    perf = perform(1, duration_s=3.0)
    for rate, every in ((120.0, 11), (50.0, 6)):
        P = perf.recording.points_m[:: int(round(120 / rate))]
        m = P.shape[1]
        model = track_state.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)),
                                         np.zeros((14, 3)), has_skeleton=True)
        ns = [int(round(f * 1e9 / rate)) for f in range(len(P))]
        st = tracker.new_state(model, P[0], ns[0], P[:1])
        solver = _CountingSolver()
        n = 66
        for f in range(1, n + 1):
            st, res = tracker.step(model, st, P[f], np.ones(m, bool), ns[f], CONFIG, solver)
        assert solver.launches == n // every, rate


def _swinging_hand(n: int, swing_from: int):
    """A trunk of six markers and a hand marker 0.5 m out on a joint that swings +-12 degrees (so the
    hand's distances to the trunk vary by centimetres), then 10 degrees further from frame `swing_from`."""
    rng = np.random.default_rng(5)
    trunk = rng.uniform(-0.15, 0.15, (6, 3)) + [0.0, 0.0, 1.0]
    pivot = np.array([0.2, 0.0, 1.2])
    angle = np.deg2rad(12.0) * np.sin(np.arange(n) / 15.0)
    angle[swing_from:] += np.deg2rad(10.0)
    hand = pivot + 0.5 * np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)
    return np.concatenate([np.broadcast_to(trunk, (n, 6, 3)), hand[:, None]], axis=1)


@pytest.mark.parametrize("fit_error_m", [0.005, 0.06])
def test_a_marker_its_partners_misplace_is_taken_where_a_well_fitting_skeleton_puts_it(fit_error_m):
    """A hand marker hid for two frames while its joint bent 10 degrees: its trunk partners, which agree
    among themselves, put it 8 cm from where it is, beyond their gate, and nothing else would place it.
    A skeleton that fits well and puts it 5 mm off has it re-acquired (the second opinion); one that puts
    it 6 cm off leaves it unlabeled."""
    n, seed, hide = 140, 120, (124, 126)
    P = _swinging_hand(n, hide[0])
    model, st = seeded_state(P, seed)
    model = dataclasses.replace(model, marker_segment=np.array([0] * 6 + [1]), has_skeleton=True)
    partners._update_partners(st)
    rng = np.random.default_rng(6)
    for f in range(seed, n):
        error = np.zeros((7, 3))
        error[6] = fit_error_m * np.array([0.0, 0.0, 1.0])
        st.skel_pred_m, st.skel_vel_m_s, st.skel_t_ns, st.fit_rms_m = P[f] + error, np.zeros((7, 3)), t_ns(f), 0.005
        seen = np.arange(6) if hide[0] <= f < hide[1] else np.arange(7)
        order = rng.permutation(len(seen))
        if f == hide[1]:  # where the partners put it as it comes back
            rpred, _, _ = partners.rigid_predictions(st, np.where(np.arange(7)[:, None] < 6, P[f], np.nan),
                                                     np.arange(7) < 6, np.arange(7) == 6)
            assert 0.06 < np.linalg.norm(rpred[6] - P[f, 6]) < tracker.CROSS_JOINT_DISAGREE_M
        st, res = tracker.step(model, st, P[f, seen[order]], np.ones(len(seen), bool), t_ns(f), CONFIG)
        if f == hide[1]:
            got = seen[order][res.point_index[6]] if res.point_index[6] >= 0 else -1
            assert got == (6 if fit_error_m < tracker.SECOND_OPINION_GATE_M else -1)


@pytest.mark.parametrize("hold", [False, True])
def test_labels_the_layout_checks_moved_are_not_swapped_back_by_a_fit_that_followed_the_old_ones(hold):
    """Two trunk markers' labels just put back by the layout checks, while the latest fit (made on the old,
    permuted labels) puts each where the other is: the skeleton's unswap would permute them again, and
    for SHAPE_HOLD_FRAMES it may not."""
    n, seed = 124, 120
    P = _swinging_hand(n, n)
    model, st = seeded_state(P, seed)
    model = dataclasses.replace(model, marker_segment=np.array([0] * 6 + [1]), has_skeleton=True)
    partners._update_partners(st)
    f = seed
    fit = P[f].copy()
    fit[[3, 4]] = fit[[4, 3]]
    assert np.linalg.norm(P[f, 3] - P[f, 4]) > 2 * CONFIG.rigid_check_m
    st.skel_pred_m, st.skel_vel_m_s, st.skel_t_ns, st.fit_rms_m = fit, np.zeros((7, 3)), t_ns(f), 0.005
    if hold:
        st.layout_hold = np.zeros(7, int)
        st.layout_hold[[3, 4]] = tracker.SHAPE_HOLD_FRAMES
    st, res = tracker.step(model, st, P[f], np.ones(7, bool), t_ns(f), CONFIG)
    expected = np.arange(7) if hold else np.array([0, 1, 2, 4, 3, 5, 6])
    assert res.point_index.tolist() == expected.tolist()
    if hold:
        assert st.layout_hold.tolist() == [0, 0, 0] + [tracker.SHAPE_HOLD_FRAMES - 1] * 2 + [0, 0]


def test_a_fast_hand_held_only_by_loose_partners_keeps_its_tracked_label():
    """A hand marker 0.5 m out whose only partners are trunk markers across the joint (their distances to it
    vary by centimetres: it swung during the seed) whips round, up to 6 cm a frame. Tracking follows it; its
    partners, which hold it no better than the spread of those distances (`_partner_sigma`), put it where it
    was a frame ago. The correct label is kept on every frame: withdrawn, a neighbour's label took its point
    (the serving arm of the two-player tennis file). Fails with RIGID_LOOSE_K = 0."""
    n, seed = 165, 120
    P = _swinging_hand(n, n)
    pivot = np.array([0.2, 0.0, 1.2])
    speed = np.minimum(np.arange(1, n - seed + 1) / 15.0, 1.0) * 0.12  # [rad / frame], to 6 cm a frame
    angle = np.deg2rad(12.0) * np.sin((seed - 1) / 15.0) + np.cumsum(speed)
    P[seed:, 6] = pivot + 0.5 * np.stack([np.cos(angle), np.sin(angle), np.zeros(n - seed)], axis=1)
    got = run_tracker(P, seed, shuffle_seed=3)
    assert np.all(got[seed:, 6] == 6)
    assert np.all(got[seed:, :6] == np.arange(6))


def test_a_label_the_layout_check_takes_off_a_neighbours_point_is_found_where_its_partners_put_it_before(monkeypatch):
    """A wrist label re-acquired, then carried onto the finger marker's point while on probation (the finger
    marker hidden; a serving arm's partners too loose for probation to tell): its partners' snapshot is
    retaken there every frame. The layout check hands the point to the finger marker; the wrist marker,
    back in view, is placed by the snapshot from before its re-acquisition, not by the one taken on the
    finger's point, 8-10 cm from it and beyond its gate (two players at L2: a serving wrist unlabeled in
    view for 30 frames)."""
    for module in (partners, layouts, tracker):  # every module that reads it
        monkeypatch.setattr(module, "Z_SUSPECT", np.inf)
    perf = perform(3, duration_s=2.0)
    P = perf.recording.points_m
    m, seed = len(perf.marker_names), 120
    model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                     perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                     layout_rms_m=np.full(m, 0.002))
    st = tracker.new_state(model, P[0], t_ns(0), P[:1])
    for f in range(1, seed):
        st, _ = tracker.observe(model, st, P[f], t_ns(f), CONFIG)
    st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
    wrist, finger = perf.marker_names.index("RWRA"), perf.marker_names.index("RFIN")
    assert np.linalg.norm(P[seed:, wrist] - P[seed:, finger], axis=1).min() > 2 * CONFIG.reacquire_gate_m
    shown = np.ones(m, bool)
    for f in range(seed, len(P)):
        shown[:] = True
        if f < seed + 6:
            shown[wrist] = False  # hidden ...
        elif f == seed + 8:
            st.pos_m[wrist] = P[f - 1, finger]  # ... re-acquired, then carried onto the finger's point
            st.vel_m_s[wrist] = (P[f - 1, finger] - P[f - 2, finger]) * RATE_HZ
        if seed + 8 <= f < seed + 30:
            shown[wrist] = False
        if seed <= f < seed + 8:
            shown[finger] = False
        seen = np.flatnonzero(shown)
        st, res = tracker.step(model, st, P[f, seen], np.ones(len(seen), bool), t_ns(f), CONFIG)
        got = np.where(res.point_index >= 0, seen[np.maximum(res.point_index, 0)], -1)
        if f == seed + 6:
            assert got[wrist] == wrist and st.provisional[wrist] > 0
        if f == seed + 10:
            assert got[wrist] == finger  # the wrong label
    assert got[wrist] == wrist and got[finger] == finger


def test_a_fit_that_misses_part_of_the_body_is_trusted_on_the_segments_it_places():
    """A fit whose RMS is over SKELETON_TRUSTED_RMS_M (shoulder markers on the torso with the arms overhead)
    still places the markers of a segment whose three or more labeled markers sit where it puts them; not
    those of a segment it misplaces, of one with fewer labeled markers (two leave a turn about their line
    free), nor of a marker on no segment. Under the threshold it places every marker."""
    seg = np.array([2, 2, 2, 7, 7, 7, 7, 13, 13, 5, 5, 5, -1])
    m = len(seg)
    model = track_state.SubjectModel("P", tuple(f"M{i}" for i in range(m)), seg, np.zeros((m, 3)), np.zeros((14, 3)),
                                     has_skeleton=True)
    rng = np.random.default_rng(0)
    skel = rng.normal(0.0, 0.3, (m, 3))
    cur = skel + rng.normal(0.0, 0.004, (m, 3))
    cur[:3] += [0.12, 0.0, 0.0]  # the torso's markers 12 cm off
    cur[9:12, 2] += [0.03, -0.03, 0.02]  # the left forearm's 2-3 cm off
    labeled = np.ones(m, bool)
    labeled[6] = labeled[8] = False  # a hidden wrist marker; the foot has one label
    cur[~labeled] = np.nan
    got = tracker._trusted_markers(model, cur, labeled, skel, 0.05)
    np.testing.assert_array_equal(np.flatnonzero(got), [3, 4, 5, 6])
    assert tracker._trusted_markers(model, cur, labeled, skel, 0.01).all()
    assert not tracker._trusted_markers(model, cur, labeled, None, 0.05).any()
