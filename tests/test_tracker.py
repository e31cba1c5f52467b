"""service/tracker.py, the pure per-subject step: rigid-partner prediction against a known rigid motion,
and labels that survive shuffling, a 0.5 s occlusion and ghosts beside the markers (no skeleton, no solver:
what the tracker does on its own before a subject is calibrated); the NNT prediction of an accelerating
marker; the skip budget of the solve (a counting stand-in for the solver)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recordings.synthetic import perform
from service import tracker
from service.config import EngineConfig

CONFIG = EngineConfig()
RATE_HZ = 120.0


def t_ns(f: int) -> int:
    return int(round(f * 1e9 / RATE_HZ))


def seeded_state(points_m: np.ndarray, seed_frames: int):
    """A subject model without skeleton, and its state after `seed_frames` of given labels (observe)."""
    m = points_m.shape[1]
    model = tracker.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)),
                                 np.zeros((14, 3)))
    st = tracker.new_state(model, points_m[0], t_ns(0), points_m[:1])
    for f in range(1, seed_frames):
        st, _ = tracker.observe(model, st, points_m[f], t_ns(f), CONFIG)
    return model, st


def test_rigid_predictions_follow_a_known_rigid_motion():
    rng = np.random.default_rng(0)
    body = rng.uniform(-0.2, 0.2, (10, 3)) + [0, 0, 1]
    history = np.stack([body + [0.001 * k, 0, 0] for k in range(40)])  # rigid: distances never vary
    model, st = seeded_state(history, 40)
    tracker._update_partners(st)
    R = Rotation.from_rotvec([0.2, -0.4, 0.9]).as_matrix()
    moved = (body - body.mean(0)) @ R.T + [1.0, 2.0, 0.5]
    labeled = np.ones(10, bool)
    labeled[3] = False
    now = np.where(labeled[:, None], moved, np.nan)
    pred, spread, _ = tracker.rigid_predictions(st, now, labeled, ~labeled)
    np.testing.assert_allclose(pred[3], moved[3], atol=1e-9)
    assert spread[3] < 1e-6  # closed-form misfit: exact up to ~1e-8 m of rounding
    assert np.all(np.isnan(pred[labeled]))  # only the markers asked for


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
    tracker._update_partners(st)
    gates_seen = []
    assign = tracker._assign

    def spy(pred, gates, points, cand):
        gates_seen.append(gates.copy())
        return assign(pred, gates, points, cand)

    monkeypatch.setattr(tracker, "_assign", spy)
    drift = rng.normal(0, 0.0015, body.shape)  # per frame: the body bends out of shape, 8 cm in 60 frames
    for k in range(1, 61):
        now = history[-1] + k * drift
        cloud = np.delete(now, 3, axis=0)  # marker 3 hidden throughout
        st, res = tracker.step(model, st, cloud, np.ones(len(cloud), bool), t_ns(40 + k), CONFIG)
    assert (res.point_index >= 0).sum() == 9  # the partners were tracked through it
    labeled = res.point_index >= 0
    _, spread, _ = tracker.rigid_predictions(st, res.positions_m, labeled, ~labeled)
    wide = 0.8 * CONFIG.reacquire_gate_m + 3.0 * spread[3]
    assert wide > 5 * CONFIG.reacquire_gate_m  # the gate the partners' misfit asks for
    if has_skeleton:
        assert 2 * CONFIG.reacquire_gate_m < gates_seen[-1][3] <= 3 * CONFIG.reacquire_gate_m + 1e-12
    else:
        assert gates_seen[-1][3] > 5 * CONFIG.reacquire_gate_m


def test_partners_need_a_distance_sampled_often_enough():
    """A pair seen together in a few frames only looks perfectly rigid (no spread yet): it must not outrank
    a pair whose small spread was measured over many frames."""
    model = tracker.SubjectModel("P", tuple("abc"), np.full(3, -1), np.zeros((3, 3)), np.zeros((14, 3)))
    st = tracker.new_state(model, np.zeros((3, 3)), 0)
    st.dist_n[:] = [[0, 5, 100], [5, 0, 5], [100, 5, 0]]
    st.dist_mean_m[:] = 0.1
    st.dist_var_m2[:] = [[0, 0, 0.002**2], [0, 0, 0], [0.002**2, 0, 0]]
    tracker._update_partners(st)
    assert st.partners[0, 0] == 2 and 1 not in st.partners[0]
    assert (st.partners[1] == -1).all()  # nothing sampled often enough yet


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
    model = tracker.SubjectModel("P", tuple("abcde"), seg, off, np.zeros((14, 3)), True)
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


def _turned_unseen(rng, turns: dict, measured_layouts: bool = False):
    """The synthetic performer (seed 3) at a random pose, tracked with its skeleton there, and the same
    pose after `turns` ({segment: (axis, degrees)}) turned those segments at their joints unseen.
    Returns (perf, model, state, markers before (M, 3), markers after (M, 3), after(root) the turned pose
    with its root moved to `root`)."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf = perform(3, duration_s=0.1)
    layout = dict(layout_offsets_m=perf.marker_offsets_m, layout_rms_m=np.full(len(perf.marker_names), 0.002))
    model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                 perf.joint_offsets_m, True, **(layout if measured_layouts else {}))
    R_old = Rotation.from_rotvec(rng.normal(0.0, 0.2, (14, 3))).as_matrix()
    t = np.array([0.3, -0.2, 0.95])
    R_new = R_old.copy()
    for name, (axis, degrees) in turns.items():
        k = SEGMENTS.index(name)
        R_new[k] = Rotation.from_euler(axis, degrees, degrees=True).as_matrix() @ R_old[k]

    def markers(R, root=t):
        Rw, pw = world_transforms(root, R, perf.joint_offsets_m)
        return np.einsum("mij,mj->mi", Rw[perf.marker_segment], perf.marker_offsets_m) + pw[perf.marker_segment]

    old = markers(R_old)
    st = tracker.new_state(model, old, t_ns(0))
    st.t_root_m, st.R_parent_segment = t, R_old
    return perf, model, st, old, markers(R_new), lambda root: markers(R_new, root)


@pytest.mark.parametrize("off_mm, found", [(18, True), (40, False)])
def test_a_lost_marker_is_found_where_three_labeled_markers_of_its_segment_put_it_despite_skin_motion(off_mm, found):
    """A forearm's three other markers labeled, its fourth unlabeled in view: its point sits 18 mm from where
    their layout puts it (skin and joint motion: a serving forearm's marker, 12-21 mm) and is found
    (SEARCH_PLACED_INLIER_M); 40 mm away, it is not theirs to place."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf, model, st, old, _, _ = _turned_unseen(np.random.default_rng(5), {})
    forearm = np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))
    assert len(forearm) == 4
    lost_one = forearm[0]
    _, pw = world_transforms(st.t_root_m, st.R_parent_segment, perf.joint_offsets_m)
    elbow = pw[SEGMENTS.index("r_forearm")]
    radial = old[lost_one] - elbow
    side = np.cross(radial, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    points = old.copy()
    points[lost_one] += off_mm * 1e-3 * side  # (about the same distance from the elbow: on its sphere)
    labeled = np.arange(len(old)) != lost_one
    cur = np.where(labeled[:, None], points, np.nan)
    free = ~labeled
    lost = ~labeled
    want = {int(lost_one): int(lost_one)} if found else {}
    assert tracker._search_segments(model, st, points, free, labeled, cur, lost) == want


@pytest.mark.parametrize("upper_arm_deg", [0.0, 20.0])
def test_a_lost_marker_three_labeled_markers_of_its_segment_place_is_found_wherever_the_fit_left_the_joint(upper_arm_deg):
    """A forearm's three other markers labeled, its fourth unlabeled in view where they put it, and the fit
    (a serving arm, 35-45 mm RMS) holding the elbow 10 cm off: the three place it without the joint (its
    distance from the joint would rule its point out: a serving wrist marker stayed unlabeled in view for
    20 frames, two players at L2)."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf, model, st, old, _, _ = _turned_unseen(np.random.default_rng(5), {})
    forearm = np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))
    lost_one, k = forearm[1], SEGMENTS.index("r_forearm")
    _, before = world_transforms(st.t_root_m, st.R_parent_segment, perf.joint_offsets_m)
    upper = SEGMENTS.index("r_upperarm")
    st.R_parent_segment[upper] = Rotation.from_euler("x", upper_arm_deg, degrees=True).as_matrix() @ st.R_parent_segment[upper]
    _, after = world_transforms(st.t_root_m, st.R_parent_segment, perf.joint_offsets_m)
    assert np.linalg.norm(after[k] - before[k]) > (0.08 if upper_arm_deg else -1.0)
    labeled = np.arange(len(old)) != lost_one
    cur = np.where(labeled[:, None], old, np.nan)
    assert tracker._search_segments(model, st, old, ~labeled, labeled, cur, ~labeled) == {int(lost_one): int(lost_one)}


def test_a_segment_the_fit_lost_is_found_around_its_joint():
    """A forearm turned 80 degrees at the elbow while its markers went unlabeled: the fit (which had no
    word on it) still holds it where it was, its wrist 12 cm from its markers. Registered around the
    elbow, every forearm marker gets its own point, not a ghost beside it; with the forearm's points gone,
    nothing is found."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(3)
    perf, model, st, old, now, _ = _turned_unseen(rng, {"r_forearm": ("y", 80)})
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    assert on_forearm.sum() >= 3 and np.linalg.norm(now - old, axis=1)[on_forearm].max() > 0.1
    labeled = ~on_forearm
    cur = np.where(labeled[:, None], now, np.nan)
    ghosts = now[on_forearm] + rng.normal(0.0, 0.04, (on_forearm.sum(), 3))
    order = rng.permutation(len(now) + len(ghosts))
    points = np.concatenate([now, ghosts])[order]
    truth = np.concatenate([np.arange(len(now)), np.full(len(ghosts), -2)])[order]
    free = np.isin(truth, np.flatnonzero(on_forearm)) | (truth == -2)

    found = tracker._search_segments(model, st, points, free, labeled, cur, on_forearm)
    assert found == {int(i): int(np.flatnonzero(truth == i)[0]) for i in np.flatnonzero(on_forearm)}
    assert tracker._search_segments(model, st, points, truth == -2, labeled, cur, on_forearm) == {}


def test_a_forearm_whose_upper_arm_swung_too_is_found_by_its_layout():
    """The whole arm swung while unlabeled (70 degrees at the shoulder, 60 at the elbow): the fit holds
    the elbow where it was, so no search around it can work. The forearm's markers are found by their
    layout, with the elbow at the upper arm's length from the shoulder; not with their layouts unmeasured,
    and not among points whose layout matches but that lie out of the arm's reach."""
    import dataclasses

    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(4)
    turns = {"r_upperarm": ("x", 70), "r_forearm": ("y", 60)}
    perf, model, st, old, now, turned_at = _turned_unseen(rng, turns, measured_layouts=True)
    arm = np.isin(perf.marker_segment, [SEGMENTS.index(name) for name in turns])
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    assert on_forearm.sum() >= 4 and np.linalg.norm(now - old, axis=1)[on_forearm].min() > 0.1
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)
    ghosts = now[arm] + rng.normal(0.0, 0.05, (arm.sum(), 3))
    points = np.concatenate([now, ghosts])
    free = np.concatenate([arm, np.ones(len(ghosts), bool)])

    found = tracker._search_segments(model, st, points, free, labeled, cur, arm)
    assert {i: p for i, p in found.items() if on_forearm[i]} == {int(i): int(i) for i in np.flatnonzero(on_forearm)}
    assert all(p == i for i, p in found.items())
    unmeasured = dataclasses.replace(model, layout_rms_m=None)
    assert not any(on_forearm[i] for i in tracker._search_segments(unmeasured, st, points, free, labeled, cur, arm))
    away = turned_at(st.t_root_m + [0.0, 1.5, 0.0])  # the same arm 1.5 m to the side: out of this one's reach
    far = np.concatenate([now[~arm], away[arm]])
    far_free = np.concatenate([np.zeros((~arm).sum(), bool), np.ones(arm.sum(), bool)])
    assert tracker._search_segments(model, st, far, far_free, labeled, cur, arm) == {}


def test_a_forearm_found_by_its_layout_is_hung_from_the_elbow_refinement_moved():
    """Refinement moved the elbow (here 6 cm: the calibration's was off, the motion placed it) and the
    forearm's offsets with it, but keeps the calibrated layout, whose origin stays where the calibration
    put the elbow. The search places the layout and asks where the model's elbow is in it
    (`SubjectModel.layout_joints_m`), so the arm swung unseen is found. (At the layout's own origin, the
    elbow lay 6 cm off the upper arm's length from the shoulder: a serving forearm whose elbow refinement
    had moved 66 mm stayed unlabeled in view for 45 frames, two players at L2.)"""
    from protocol.skeleton import SEGMENTS

    perf, model, st, now, arm, forearm = _arm_swung_unseen()
    shoulder = tracker._joints_m(model, st)[SEGMENTS.index("r_upperarm")]
    R, elbow = tracker.rigid_motion(model.marker_offsets_m[forearm], now[forearm])  # the forearm's pose now
    up_the_arm = (shoulder - elbow) / np.linalg.norm(shoulder - elbow)
    layout = model.layout_offsets_m.copy()
    layout[forearm] -= 0.06 * R.T @ up_the_arm  # the calibration's elbow, 6 cm nearer the shoulder
    calibrated = dataclasses.replace(model, layout_offsets_m=layout)
    np.testing.assert_allclose(calibrated.layout_joints_m[SEGMENTS.index("r_forearm")],
                               -0.06 * R.T @ up_the_arm, atol=1e-12)
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)

    found = tracker._search_segments(calibrated, st, now, arm.copy(), labeled, cur, arm)
    assert {i: p for i, p in found.items() if i in forearm} == {int(i): int(i) for i in forearm}


@pytest.mark.parametrize("raised_m, found", [(0.065, True), (0.12, False)])
def test_a_forearm_found_by_its_layout_may_hang_from_a_shoulder_the_shoulder_blade_raised(raised_m, found):
    """The arm swung unseen and the shoulder blade carried it 6.5 cm up along itself (an arm raised to
    serve); the upper arm's markers are labeled again, the forearm's not. The fit holds the shoulder where
    the trunk puts it and the elbow where it was, so the elbow the forearm's layout places lies 6.5 cm
    beyond the upper arm's length from that shoulder, and is taken (SEARCH_BONE_TOL_M; two players at L3,
    a serving forearm unlabeled in view for 0.4 s); 12 cm beyond, it is no arm of this shoulder's."""
    from protocol.skeleton import SEGMENTS

    perf, model, st, now, arm, forearm = _arm_swung_unseen()
    shoulder = tracker._joints_m(model, st)[SEGMENTS.index("r_upperarm")]
    _, elbow = tracker.rigid_motion(model.marker_offsets_m[forearm], now[forearm])
    along = (elbow - shoulder) / np.linalg.norm(elbow - shoulder)
    points = now.copy()
    points[arm] += raised_m * along
    lost = np.zeros(len(points), bool)
    lost[forearm] = True
    cur = np.where(~lost[:, None], points, np.nan)

    got = tracker._search_segments(model, st, points, lost.copy(), ~lost, cur, lost)
    assert got == ({int(i): int(i) for i in forearm} if found else {})


def test_the_models_joint_in_a_layout_refinement_reshaped_is_where_the_rigid_motion_between_them_puts_it():
    """Refinement reshapes a segment a little as it moves its joint: the layout is the offsets turned 10
    degrees about their centre and shifted by c, so the joint (the offsets' origin) lies where that motion
    puts it, not at the mean shift of the markers. No layout measured: zeros."""
    rng = np.random.default_rng(7)
    offsets = rng.uniform(-0.05, 0.05, (4, 3)) + [0.0, 0.0, -0.15]
    turn = Rotation.from_rotvec([0.0, np.radians(10), 0.0]).as_matrix()
    c = np.array([0.01, -0.03, 0.05])
    layout = (offsets - offsets.mean(0)) @ turn.T + offsets.mean(0) + c
    model = tracker.SubjectModel("P", ("a", "b", "c", "d"), np.full(4, 6), offsets, np.zeros((14, 3)), True,
                                 layout_offsets_m=layout, layout_rms_m=np.full(4, 0.002))
    expected = offsets.mean(0) + c - turn @ offsets.mean(0)
    np.testing.assert_allclose(model.layout_joints_m[6], expected, atol=1e-9)
    assert np.linalg.norm(np.mean(layout - offsets, axis=0) - expected) > 0.02  # (the mean shift is not it)
    assert not np.delete(model.layout_joints_m, 6, axis=0).any()
    assert not dataclasses.replace(model, layout_rms_m=None).layout_joints_m.any()


def _arm_swung_unseen():
    """A synthetic performer whose right upper arm and forearm turned 70 and 60 degrees while unlabeled,
    its layouts measured: (perf, model, st, the points now, the arm's markers (mask), the forearm's)."""
    from protocol.skeleton import SEGMENTS

    turns = {"r_upperarm": ("x", 70), "r_forearm": ("y", 60)}
    perf, model, st, _, now, _ = _turned_unseen(np.random.default_rng(4), turns, measured_layouts=True)
    arm = np.isin(perf.marker_segment, [SEGMENTS.index(name) for name in turns])
    return perf, model, st, now, arm, np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))


def test_three_markers_of_a_forearm_whose_upper_arm_swung_too_are_found_where_one_bone_pins_them():
    """The whole arm swung unseen, and the forearm's fourth marker hid with the upper arm: its other three
    (a serving forearm's wrist pair and finger, in view for 0.5 s in tennis at L3) are a triangle matched
    to the points, taken because the elbow it places lies at the upper arm's length from the shoulder.
    Not when the same triangle turned about the shoulder is free too (the bone cannot tell the two
    apart), and not when the trunk is unlabeled as well (the chain's reach is too loose for a triangle)."""
    from protocol.skeleton import SEGMENTS

    perf, model, st, now, arm, forearm = _arm_swung_unseen()
    assert len(forearm) == 4
    shoulder = tracker._joints_m(model, st)[SEGMENTS.index("r_upperarm")]
    hidden = forearm[np.argmin(np.linalg.norm(now[forearm] - shoulder, axis=1))]  # the one nearest the elbow
    shown = np.setdiff1d(forearm, [hidden])
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)
    points = now.copy()
    points[hidden] = [9.0, 9.0, 9.0]  # out of reach: hidden
    free = arm.copy()

    found = tracker._search_segments(model, st, points, free, labeled, cur, arm)
    assert {i: p for i, p in found.items() if i in forearm} == {int(i): int(i) for i in shown}
    # the same three turned 40 degrees about the shoulder: their elbow at the bone's length too
    turn = Rotation.from_rotvec([0.0, 0.0, np.radians(40)]).as_matrix()
    twin = (now[shown] - shoulder) @ turn.T + shoulder
    both = np.concatenate([points, twin])
    found = tracker._search_segments(model, st, both, np.concatenate([free, np.ones(3, bool)]), labeled, cur, arm)
    assert not any(i in forearm for i in found)
    trunk_too = labeled & (perf.marker_segment != SEGMENTS.index("torso"))
    found = tracker._search_segments(model, st, points, free, trunk_too, np.where(trunk_too[:, None], now, np.nan), arm)
    assert not any(i in forearm for i in found)


def test_a_forearm_fitting_no_rigid_layout_is_found_by_the_triangles_that_agree():
    """The arm swung unseen and the forearm twisted out of its layout: one marker sits 20 mm off where the
    other three put it (a five-marker forearm under pronation: two players at L3, the left forearm
    unlabeled 100 frames in view). No triangle places all four, but several place three, and they agree:
    all four are found. (Two placements that disagree, each alone: the three-marker test's twin.)"""
    perf, model, st, now, arm, forearm = _arm_swung_unseen()
    a, b, c, d = now[forearm]
    normal = np.cross(b - a, c - a)
    points = now.copy()
    points[forearm[3]] = d + 0.02 * normal / np.linalg.norm(normal)  # off the plane: sides barely change
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)

    found = tracker._search_segments(model, st, points, arm.copy(), labeled, cur, arm)
    assert {i: p for i, p in found.items() if i in forearm} == {int(i): int(i) for i in forearm}


def test_placements_agree_unless_a_marker_or_a_point_is_given_twice():
    assert tracker._agrees({1: 10, 2: 20}, {2: 20, 3: 30})
    assert not tracker._agrees({1: 10, 2: 20}, {2: 30})  # marker 2 on two points
    assert not tracker._agrees({1: 10, 2: 20}, {3: 20})  # point 20 for two markers
    merged, support = tracker._consensus({1: 10, 2: 20, 3: 30}, [(3, 0.001, {1: 10, 2: 20, 3: 30}),
                                                                 (3, 0.002, {2: 20, 3: 30, 4: 40}),
                                                                 (3, 0.002, {2: 30, 3: 20, 4: 40}),
                                                                 (3, 0.003, {1: 10, 4: 40, 5: 50})])
    assert merged == {1: 10, 2: 20, 3: 30, 4: 40, 5: 50} and support == 3


def test_an_upper_arm_of_two_markers_in_view_is_found_with_its_forearm_around_the_elbow_it_places():
    """The whole arm swung while unlabeled, and one of the upper arm's three markers is hidden: the two
    left and the shoulder (held by the trunk) cannot tell the upper arm's placement from its mirror image,
    and the fit holds the elbow where it was, so the forearm cannot be searched around it. Each placement
    of the upper arm puts the elbow somewhere; the forearm is found around the right one, and both are
    labeled (a tennis player's serving arm stayed unlabeled for 20 frames, in view), also with the shoulder
    slid a few centimetres from where the trunk puts it. With the forearm's points gone, the two upper-arm
    points alone stay unlabeled."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(4)
    turns = {"r_upperarm": ("x", 70), "r_forearm": ("y", 60)}
    perf, model, st, old, now, _ = _turned_unseen(rng, turns)  # layouts unmeasured: no layout search
    names = list(perf.marker_names)
    arm = np.isin(perf.marker_segment, [SEGMENTS.index(name) for name in turns])
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    assert np.linalg.norm(now - old, axis=1)[on_forearm].min() > 0.1
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)
    in_view = np.ones(len(now), bool)
    in_view[names.index("RSHO")] = False
    ghosts = now[arm] + rng.normal(0.0, 0.05, (arm.sum(), 3))
    points = np.concatenate([now[in_view], ghosts])
    truth = np.concatenate([np.flatnonzero(in_view), np.full(len(ghosts), -2)])
    free = np.concatenate([arm[in_view], np.ones(len(ghosts), bool)])

    found = tracker._search_segments(model, st, points, free, labeled, cur, arm)
    expected = {i for i in np.flatnonzero(arm) if in_view[i]}
    assert set(found) == expected and all(truth[p] == i for i, p in found.items())
    upper_only = free & ~np.isin(truth, np.flatnonzero(on_forearm))
    assert tracker._search_segments(model, st, points, upper_only, labeled, cur, arm) == {}
    # the shoulder slid 4.5 cm against the trunk markers that hold its joint (an arm raised overhead):
    # beyond a search around the joint, not beyond the arm's
    slid = points.copy()
    slid[np.isin(truth, np.flatnonzero(arm))] += [0.0, 0.0, 0.045]
    found = tracker._search_segments(model, st, slid, free, labeled, cur, arm)
    assert set(found) == expected and all(truth[p] == i for i, p in found.items())


def test_a_shank_with_one_marker_labeled_is_found_with_its_foot_around_the_ankle_it_places():
    """The knee bent and the foot turned while the shank's ankle marker and the whole foot went unlabeled;
    the shank's other marker stayed labeled. That one marker and the knee leave the shank free to turn
    about them, so the fit holds the ankle where it was and the foot cannot be searched around it. Each
    point that fits the ankle marker's distance from the knee places the shank, and with it the ankle,
    around which the foot is found (a foot back from a second's occlusion stayed unlabeled in view, until
    two of its markers were taken on the heel's point and a ghost: HDM05 at L3). With the foot's points
    gone, the ankle marker is still found, alone, at its distances from the knee and from the labeled
    shank marker (a segment of two markers), and not on any ghost."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(5)
    turns = {"r_shank": ("y", 60), "r_foot": ("y", -40)}
    perf, model, st, old, now, _ = _turned_unseen(rng, turns)
    names = list(perf.marker_names)
    lost = np.isin(perf.marker_segment, [SEGMENTS.index(name) for name in turns])
    lost[names.index("RSHN")] = False
    on_foot = perf.marker_segment == SEGMENTS.index("r_foot")
    assert np.linalg.norm(now - old, axis=1)[on_foot].min() > 0.1
    labeled = ~lost
    cur = np.where(labeled[:, None], now, np.nan)
    ghosts = now[lost] + rng.normal(0.0, 0.05, (lost.sum(), 3))
    points = np.concatenate([now, ghosts])
    truth = np.concatenate([np.arange(len(now)), np.full(len(ghosts), -2)])
    free = np.concatenate([lost, np.ones(len(ghosts), bool)])

    found = tracker._search_segments(model, st, points, free, labeled, cur, lost)
    assert set(found) == set(np.flatnonzero(lost)) and all(truth[p] == i for i, p in found.items())
    without_foot = free & ~np.isin(truth, np.flatnonzero(on_foot))
    ankle = names.index("RANK")
    assert tracker._search_segments(model, st, points, without_foot, labeled, cur, lost) == {ankle: ankle}


def test_a_thigh_held_by_one_marker_is_found_with_its_knee_marker_around_the_hip():
    """A thigh turned 35 degrees at the hip while its knee marker went unlabeled: the fit, held by the thigh
    marker alone, keeps the knee where it was. The knee marker's point is the one at its distances from the
    hip and from the thigh marker; a ghost as far from the hip, but not from the thigh marker, is not it;
    and with a second point at both distances (turned about the hip-thigh-marker axis) neither is taken."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(5)
    perf, model, st, old, now, _ = _turned_unseen(rng, {"r_thigh": ("x", 35)})
    names = list(perf.marker_names)
    knee, thigh = names.index("RKNE"), names.index("RTHI")
    assert np.linalg.norm(now[knee] - old[knee]) > 0.1
    lost = np.zeros(len(now), bool)
    lost[knee] = True
    cur = np.where(~lost[:, None], now, np.nan)
    hip = tracker._joints_m(model, st)[SEGMENTS.index("r_thigh")]
    r = now[knee] - hip
    axis = (now[thigh] - hip) / np.linalg.norm(now[thigh] - hip)
    bend = np.cross(r, axis) / np.linalg.norm(np.cross(r, axis))  # turns the knee toward the thigh marker
    ghost = hip + Rotation.from_rotvec(0.6 * bend).apply(r)
    assert abs(np.linalg.norm(ghost - now[thigh]) - np.linalg.norm(now[knee] - now[thigh])) > 0.02
    twin = hip + Rotation.from_rotvec(np.pi * axis).apply(r)  # as far from the hip and from the thigh marker
    assert np.linalg.norm(twin - now[knee]) > 0.05

    def search(*extra):
        points = np.concatenate([now, np.array(extra).reshape(-1, 3)])
        free = np.zeros(len(points), bool)
        free[knee] = free[len(now):] = True
        return tracker._search_segments(model, st, points, free, ~lost, cur, lost)

    assert search(ghost) == {knee: knee}
    assert search(ghost, twin) == {}


def test_a_lost_marker_is_found_where_its_segments_labeled_markers_and_joint_put_it():
    """A forearm marker lost while the others stay labeled (its partners place it far off: its last labeled
    point was another marker's): the elbow and two labeled markers fix the forearm, and the one point where
    they put it is it; not a ghost a few centimetres from there, however well it matches its distance from
    the elbow."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(3)
    perf, model, st, old, now, _ = _turned_unseen(rng, {})
    names = list(perf.marker_names)
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    i = names.index("RWRA")
    lost = np.zeros(len(now), bool)
    lost[i] = True
    labeled = ~lost
    cur = np.where(labeled[:, None], now, np.nan)
    elbow = tracker._joints_m(model, st)[SEGMENTS.index("r_forearm")]
    r = now[i] - elbow
    ghost = elbow + Rotation.from_rotvec(0.2 * np.cross(r, [0.0, 0.0, 1.0]) / np.linalg.norm(r)).apply(r)  # as far from the elbow
    assert 0.03 < np.linalg.norm(ghost - now[i]) < 0.06 and on_forearm.sum() >= 3
    points = np.concatenate([now, ghost[None]])
    free = np.zeros(len(points), bool)
    free[[i, len(now)]] = True

    assert tracker._search_segments(model, st, points, free, labeled, cur, lost) == {i: i}
    free[i] = False
    assert tracker._search_segments(model, st, points, free, labeled, cur, lost) == {}


def test_a_forearm_swung_out_of_reach_of_where_the_fit_left_its_elbow_is_found_by_its_layout():
    """The arm swung far while its forearm was unlabeled (a serve), and the fit still holds the elbow where
    it was: not one free point lies within the forearm's reach of that joint, so the search around it has
    nothing to try. The layout search must still run (it did not: a tennis player's serving forearm stayed
    unlabeled for 0.7 s, in view)."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    rng = np.random.default_rng(4)
    turns = {"r_upperarm": ("x", 150), "r_forearm": ("y", 60)}
    perf, model, st, old, now, _ = _turned_unseen(rng, turns, measured_layouts=True)
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    elbow = world_transforms(st.t_root_m, st.R_parent_segment, model.joint_offsets_m)[1][SEGMENTS.index("r_forearm")]
    reach = np.linalg.norm(model.marker_offsets_m[on_forearm], axis=1).max() + tracker.SEARCH_JOINT_TOL_M
    assert np.linalg.norm(now[on_forearm] - elbow, axis=1).min() > reach
    labeled = ~on_forearm
    cur = np.where(labeled[:, None], now, np.nan)

    found = tracker._search_segments(model, st, now, on_forearm, labeled, cur, on_forearm)
    assert found == {int(i): int(i) for i in np.flatnonzero(on_forearm)}
    # the layout is the calibrated one (`layout_offsets_m`), not the offsets refinements on the engine's own
    # labels moved: one marker's refined 3 cm off (labeled on a neighbour's point while it was refined)
    # must not leave the forearm unfound (cmu/85_12 at L3: a foot stayed unlabeled in view for 0.5 s)
    i = int(np.flatnonzero(on_forearm)[0])
    moved = model.marker_offsets_m.copy()
    moved[i] += [0.03, 0.0, 0.0]
    refined = dataclasses.replace(model, marker_offsets_m=moved)
    found = tracker._search_segments(refined, st, now, on_forearm, labeled, cur, on_forearm)
    assert found == {int(i): int(i) for i in np.flatnonzero(on_forearm)}


def test_a_swap_the_layout_cannot_see_is_told_by_the_joint():
    """A foot whose heel is as far from the toe as from the fifth metatarsal: the toe and metatarsal labels
    swapped fit the three markers' layout exactly (a turn of the foot about its long axis), so the layout
    check cannot undo the swap (HDM05 at L3: 3 s). The ankle, which the shank holds, is a fourth point off
    their plane: with it the swap shows, and the relabelling that undoes it is found; the true labels are
    left alone."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    rng = np.random.default_rng(6)
    perf, model, st, old, _, _ = _turned_unseen(rng, {}, measured_layouts=True)
    names = list(perf.marker_names)
    k = SEGMENTS.index("r_foot")
    lab = np.array([names.index(n) for n in ("RHEE", "RTOE", "RMT5")])
    assert set(lab) == set(np.flatnonzero(perf.marker_segment == k))
    layout = model.layout_offsets_m.copy()
    layout[lab] = [[-0.05, 0.0, -0.06], [0.15, 0.03, -0.06], [0.15, -0.03, -0.06]]  # isosceles, ankle 6 cm above
    model = dataclasses.replace(model, layout_offsets_m=layout, marker_offsets_m=layout)
    Rw, pw = world_transforms(st.t_root_m, st.R_parent_segment, model.joint_offsets_m)
    cur = old.copy()
    cur[lab] = layout[lab] @ Rw[k].T + pw[k]
    st.skel_pred_m = cur.copy()
    maps = tracker._relabellings(3, 3)
    symmetric = np.ones(len(maps), bool)
    swapped = cur.copy()
    swapped[lab[[1, 2]]] = cur[lab[[2, 1]]]

    found = tracker._mirror_by_joint(model, st, k, lab, lab, maps, swapped, symmetric)
    assert found is not None and list(lab[maps[found]]) == [lab[0], lab[2], lab[1]]
    assert tracker._mirror_by_joint(model, st, k, lab, lab, maps, cur, symmetric) is None


def test_points_that_fit_the_mirror_segment_as_well_are_not_given_to_either():
    """Left and right forearms carry mirror-image marker layouts, and three markers of one fit three of
    the other's by a rotation. Points the left forearm's search took (three of the right hand's) stay
    unassigned while the right forearm, searched for too, fits them as well with its elbow about as near;
    they are the left's when the right is not searched for, or when its elbow is far from them."""
    seg = np.array([5, 5, 5, 5, 7, 7, 7, 7])
    left = np.array([[0.0, 0.0, -0.25], [0.03, 0.0, -0.26], [-0.03, 0.0, -0.26], [0.0, 0.02, -0.33]])
    off = np.vstack([left, left * [1.0, -1.0, 1.0]])  # the right is the left mirrored
    model = tracker.SubjectModel("P", tuple("abcdefgh"), seg, off, np.zeros((14, 3)), True)
    R = Rotation.from_rotvec([0.3, -0.5, 1.2]).as_matrix()
    elbow_r = np.array([0.2, 0.4, 1.3])
    points = off[4:7] @ R.T + elbow_r  # three of the right forearm's markers
    pw = np.zeros((14, 3))  # both elbows stale, a few centimetres apart
    pw[7] = elbow_r + [0.0, 0.0, 0.03]
    pw[5] = pw[7] + [0.0, 0.02, 0.0]
    left_gets = {0: 0, 1: 2, 2: 1}  # mirrored, the second and third markers trade places
    assert tracker._joint_residual(off[[0, 2, 1]], pw[5], points)[0] < 0.002
    assert tracker._rival_fits(model, pw, points, left_gets, 5, np.array([5, 7]))
    assert not tracker._rival_fits(model, pw, points, left_gets, 5, np.array([5]))
    pw[7] = elbow_r + [0.0, 0.3, 0.0]  # the right elbow held 30 cm away: it cannot be the right forearm
    assert not tracker._rival_fits(model, pw, points, left_gets, 5, np.array([5, 7]))


def test_kabsch_rms_matches_a_kabsch_by_svd():
    """The closed-form misfit equals the residual of scipy's best rotation, masked points left out."""
    rng = np.random.default_rng(4)
    A = rng.normal(0.0, 0.05, (30, 5, 3))
    R = Rotation.random(30, random_state=5).as_matrix()
    B = np.einsum("cij,cnj->cni", R, A) + rng.normal(0.0, 0.004, A.shape) + 1.0
    B[:10] = rng.normal(0.0, 0.05, (10, 5, 3))  # unrelated clouds: large misfits, reflections possible
    w = np.ones((30, 5), bool)
    w[::3, 4] = False
    want = []
    for a, b, m in zip(A, B, w):
        a, b = a[m] - a[m].mean(0), b[m] - b[m].mean(0)
        rot = Rotation.align_vectors(b, a)[0]
        want.append(np.sqrt(np.mean(np.sum((rot.apply(a) - b) ** 2, axis=1))))
    np.testing.assert_allclose(tracker._kabsch_rms(A, B, w), want, atol=1e-9)


def _checked(layout_check, points: np.ndarray, point_index: np.ndarray) -> np.ndarray:
    """Run one of the tracker's layout checks, `layout_check(point_index, cur)`, which relabels in place;
    the positions it was given must follow the labels it leaves. Returns the markers whose point changed."""
    cur = tracker._gather(points, point_index)
    changed = layout_check(point_index, cur)
    np.testing.assert_array_equal(cur, tracker._gather(points, point_index))
    return changed


def _with_layouts(segment: str):
    """A synthetic performer's first frame, its model with layouts measured (2 mm residuals), a state whose
    layouts have been fitting, and the markers of `segment`: (perf, model, points, st, markers)."""
    from protocol.skeleton import SEGMENTS

    perf = perform(3, duration_s=0.1)
    model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                 perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                 layout_rms_m=np.full(len(perf.marker_names), 0.002))
    points = perf.recording.points_m[0]
    st = tracker.new_state(model, points, t_ns(0))
    st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
    return perf, model, points, st, np.flatnonzero(perf.marker_segment == SEGMENTS.index(segment))


@pytest.mark.parametrize("segment, first", [("r_forearm", 1), ("r_foot", 0)])
def test_labels_permuted_within_a_segment_are_put_back_by_its_layout(segment, first):
    """Three labels of a segment cycled among their points (a wrist triad after a fast pass; a foot's heel,
    toe and fifth metatarsal, the heel's label 20 cm from its point) are put back in the order the
    segment's calibrated layout says, once SHAPE_CONFIRM checks agree; correct labels are left alone, and
    so is a model whose layout was never measured."""
    perf, model, points, st, fore = _with_layouts(segment)
    m, fore = len(perf.marker_names), fore[first:]
    assert len(fore) >= 3 and np.isfinite(points).all()
    right = np.arange(m)
    wrong = right.copy()
    wrong[fore[:3]] = right[fore[[1, 2, 0]]]  # the wrist pair and the finger marker 8-11 cm apart; the foot's up to 20 cm

    def check(point_index, model=model):
        return _checked(lambda idx, cur: tracker._relabel_by_shape(model, st, points, idx, cur), points, point_index)

    idx = right.copy()
    assert not check(idx).any() and (idx == right).all()
    unmeasured = dataclasses.replace(model, layout_rms_m=None)
    idx = wrong.copy()
    st.settled[fore[:3]] = False  # as the fast pass that permuted them left them (a choice in tracking)
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        assert not check(idx, unmeasured).any()
    assert (idx == wrong).all()
    for _ in range(tracker.SHAPE_CONFIRM - 1):
        assert not check(idx).any()
    changed = check(idx)
    assert (idx == right).all()
    assert set(np.flatnonzero(changed)) == set(fore[:3])


def test_labels_tracked_since_their_layout_confirmed_them_are_not_permuted_by_it():
    """A forearm's labels confirmed by its layout (every layout marker labeled and fitting) and tracked
    since are settled: when the layout later prefers a permutation of them (a forearm twisting under
    pronation moves its wrist markers against its proximal one), the check leaves them be. Labels
    re-acquired meanwhile are not settled, and the permutation is taken."""
    perf, model, points, st, fore = _with_layouts("r_forearm")
    m = len(perf.marker_names)
    assert len(fore) >= 4
    assert not st.settled.any()
    right = np.arange(m)
    idx = right.copy()
    assert not tracker._relabel_by_shape(model, st, points, idx, tracker._gather(points, idx)).any()
    assert st.settled[fore].all()  # confirmed: the whole forearm labeled, fitting its layout
    # the layout now says three of the forearm's labels sit cycled on each other's points
    three = fore[1:4]
    cycled = perf.marker_offsets_m.copy()
    cycled[three] = perf.marker_offsets_m[three[[1, 2, 0]]]
    twisted = dataclasses.replace(model, layout_offsets_m=cycled)
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        assert not tracker._relabel_by_shape(twisted, st, points, idx, tracker._gather(points, idx)).any()
    assert (idx == right).all()
    st.settled[three] = False  # re-acquired since (a forearm back from an occlusion)
    changed = np.zeros(m, bool)
    for _ in range(tracker.SHAPE_CONFIRM):
        changed |= tracker._relabel_by_shape(twisted, st, points, idx, tracker._gather(points, idx))
    assert set(np.flatnonzero(changed)) == set(three)
    assert (idx[three] == three[[1, 2, 0]]).all() or (idx[three] == three[[2, 0, 1]]).all()


@pytest.mark.parametrize("on, taken", [("RFRM", True), ("RWRA", False)])
def test_a_tracked_wrist_label_on_a_neighbours_point_is_handed_over_only_on_overwhelming_evidence(on, taken):
    """A wrist label tracked all along sits on another forearm marker's point (its own marker hid), that
    marker unlabeled. On the forearm marker's point, the labels misfit the layout by 50 mm and fit it
    exactly with the wrist label handed over: it is, though tracked (SHAPE_SETTLED_HANDOVER_MISFIT_M;
    85_12 at L2, a wrist label so on the forearm marker's point for 2.3 s). On the other wrist marker's
    point they misfit by 15 mm, which skin and twist can do: a tracked label is not suspected there."""
    perf, model, points, st, fore = _with_layouts("r_forearm")
    m = len(perf.marker_names)
    wrist, other = perf.marker_names.index("RWRB"), perf.marker_names.index(on)
    assert {wrist, other} <= set(fore) and len(fore) == 4
    points = points.copy()
    points[wrist] = [9.0, 9.0, 9.0]  # hidden
    idx = np.arange(m)
    idx[wrist], idx[other] = other, -1
    cur = tracker._gather(points, idx)
    misfit = tracker._layout_fits(model, cur, idx >= 0, np.array([model.marker_segment[wrist]]))[3][0]
    assert (misfit > 0.045) if taken else (0.01 < misfit < tracker.SHAPE_SETTLED_HANDOVER_MISFIT_M)
    assert st.provisional[wrist] <= 0  # tracked all along
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        _checked(lambda i, c: tracker._relabel_by_shape(model, st, points, i, c), points, idx)
    want = np.arange(m)
    want[wrist] = -1
    if not taken:
        want[wrist], want[other] = other, -1
    np.testing.assert_array_equal(idx, want)


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


@pytest.mark.parametrize("elbow_fits", ["labels", "swap"])
def test_a_twisted_forearms_wrist_labels_are_swapped_only_where_its_joint_agrees(elbow_fits):
    """A forearm's wrist markers turned 135 degrees about its axis from the seed's pose (pronation, which
    a rigid layout does not model): the wrist labels on their own points misfit the layout by 18 mm, and
    swapped they fit it to 3 mm, as a mirror-symmetric pair does. Where the fit puts the elbow where the
    labels, registered on the layout, put it, the swap fits the joint worse and the labels are left be (on
    135_02 at L3 such swaps lasted 1-2.5 s); where it puts the elbow where the swap puts it, the swap is
    taken (TWISTING_SEGMENTS)."""
    from service.calibration import world_transforms

    perf, model, points, st, _ = _with_layouts("r_forearm")
    m, layout, k = len(perf.marker_names), model.layout_offsets_m, perf.marker_segment[perf.marker_names.index("RFRM")]
    frm, wra, wrb, fin = (perf.marker_names.index(n) for n in ("RFRM", "RWRA", "RWRB", "RFIN"))
    assert k in tracker.TWISTING_SEGMENTS
    R = Rotation.from_quat(perf.rotations_xyzw[0]).as_matrix()
    elbow = world_transforms(perf.root_position_m[0], R, perf.joint_offsets_m)[1][k]
    points = points.copy()
    axis = (points[wra] + points[wrb]) / 2 - elbow
    points[[wra, wrb]] = elbow + Rotation.from_rotvec(np.radians(135) * axis / np.linalg.norm(axis)).apply(points[[wra, wrb]] - elbow)
    labels, swap = [frm, wra, wrb], [frm, wrb, wra]
    misfit = tracker._kabsch_rms(layout[[labels, swap]], np.broadcast_to(points[labels], (2, 3, 3)), np.ones((2, 3), bool))
    assert misfit[0] > 0.015 and misfit[1] < 0.004
    # the fit's elbow where the labels (or their swap), registered on the layout, put the segment's origin
    _, origin = tracker.rigid_motion(layout[labels if elbow_fits == "labels" else swap], points[labels])
    st.t_root_m, st.R_parent_segment = perf.root_position_m[0] + origin - elbow, R
    st.skel_pred_m = points.copy()  # (a fit to ask)
    idx = np.arange(m)
    idx[fin] = -1  # hidden
    changed = np.zeros(m, bool)
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        changed |= _checked(lambda i, cur: tracker._relabel_by_shape(model, st, points, i, cur), points, idx)
    if elbow_fits == "labels":
        assert not changed.any() and (idx[[frm, wra, wrb]] == labels).all()
    else:
        assert set(np.flatnonzero(changed)) == {wra, wrb} and idx[wra] == wrb and idx[wrb] == wra


def test_layouts_are_trusted_from_the_frames_they_were_calibrated_from():
    """A calibration that lands after the seed starts with every segment's layout trusted where the
    labeled history fits it, so a swap right after it can be undone (a tennis serve at 50 Hz swapped the
    wrist labels 0.4 s after the seed, and they stayed swapped 40 frames while the layout earned trust);
    not a segment whose labels in the history misfit it (a layout calibrated wrong)."""
    from protocol.skeleton import SEGMENTS

    perf = perform(3, duration_s=1.0)
    m = len(perf.marker_names)
    model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                 perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                 layout_rms_m=np.full(m, 0.002))
    history = perf.recording.points_m[:80].copy()
    st = tracker.new_state(model, history[-1], t_ns(0))
    assert not tracker._trusted_layouts(st).any()
    fore = np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))
    history[:, fore[:2]] = history[:, fore[[1, 0]]]  # two forearm labels swapped all along
    tracker.learn_layout_trust(model, st, history)
    trusted = tracker._trusted_layouts(st)
    for k in (SEGMENTS.index(name) for name in ("pelvis", "torso", "head", "l_forearm", "r_foot", "l_foot")):
        assert trusted[k], SEGMENTS[k]
    assert not trusted[SEGMENTS.index("r_forearm")]


def test_layout_trust_learned_from_a_history_at_once_is_what_its_frames_checked_one_by_one_give():
    """`learn_layout_trust` registers every frame's segments in one batch; the shares it leaves are those of
    registering each checked frame's segments on its own (`_layout_fits`) and counting them in frame order,
    with markers hidden on some frames (segments checked on some frames only) and a segment swapped on
    others."""
    from protocol.skeleton import SEGMENTS

    perf = perform(5, duration_s=1.0)
    m = len(perf.marker_names)
    rng = np.random.default_rng(0)
    model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                 perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                 layout_rms_m=rng.uniform(0.0005, 0.004, m))
    history = perf.recording.points_m[:90] + rng.normal(0.0, 0.004, (90, m, 3))
    history[rng.random((90, m)) < 0.3] = np.nan
    fore = np.flatnonzero(perf.marker_segment == SEGMENTS.index("l_forearm"))
    history[40:70, fore[:2]] = history[40:70, fore[[1, 0]]]
    st, ref = (tracker.new_state(model, perf.recording.points_m[0], t_ns(0)) for _ in range(2))
    for s in (st, ref):  # checked before (a recalibration's): the shares are running means, the order counts
        s.shape_fit[:], s.shape_checks[:] = 0.5, 60
    tracker.learn_layout_trust(model, st, history)

    checked = 0
    for frame in history[:: tracker.SHAPE_EVERY_FRAMES]:
        sel = np.isfinite(frame[:, 0]) & tracker._layout_slots(model, ref)
        counts = np.bincount(model.marker_segment[sel], minlength=tracker.N_SEGMENTS)
        ks = np.flatnonzero(counts >= tracker.SHAPE_MIN_LABELED)
        _, _, n_lab, rms, typical = tracker._layout_fits(model, frame, sel, ks)
        tracker._count_layout_fits(ref, ks, rms <= tracker._fit_tolerance(n_lab, typical)[1])
        checked += len(ks)
    assert checked > 200 and (ref.shape_checks < ref.shape_checks.max()).any()  # segments left out on some frames
    assert 0.0 < ref.shape_fit[SEGMENTS.index("l_forearm")] < 1.0
    np.testing.assert_array_equal(st.shape_checks, ref.shape_checks)
    np.testing.assert_allclose(st.shape_fit, ref.shape_fit, rtol=0, atol=1e-12)


def _right_foot(heel_m, toe_m, mt5_m):
    """A synthetic performer's first frame with its right foot's heel, toe and fifth metatarsal markers
    moved to these offsets (its layout, calibrated to 1 mm): (perf, model, R_parent_segment, points,
    the ankle joint's position)."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf = perform(3, duration_s=0.1)
    m, k = len(perf.marker_names), SEGMENTS.index("r_foot")
    foot = [perf.marker_names.index(n) for n in ("RHEE", "RTOE", "RMT5")]
    off = perf.marker_offsets_m.copy()
    off[foot] = [heel_m, toe_m, mt5_m]
    model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, off, perf.joint_offsets_m, True,
                                 layout_offsets_m=off, layout_rms_m=np.full(m, 0.001))
    R = Rotation.from_quat(perf.rotations_xyzw[0]).as_matrix()
    Rs, ps = world_transforms(perf.root_position_m[0], R, perf.joint_offsets_m)
    points = perf.recording.points_m[0].copy()
    points[foot] = off[foot] @ Rs[k].T + ps[k]
    return perf, model, R, points, ps[k]


@pytest.mark.parametrize("heel_off_m", [0.0, 0.007])
def test_two_labels_swapped_on_a_mirror_symmetric_foot_are_put_back_by_its_joint_and_a_free_point(heel_off_m):
    """A foot whose toe and fifth metatarsal markers are mirror images about the plane of its heel marker
    and ankle: with the heel hidden, the toe and metatarsal labels swapped fit every layout distance. The
    heel's point, in view and free, and the ankle where the fit puts it tell them apart (their mirror image
    is no rotation of them): after SHAPE_CONFIRM checks the two labels are swapped back and the heel
    labeled. Correct labels are left alone, and so are swapped ones with no free point to tell. Also with
    the heel's point 7 mm off its place in a layout calibrated to 1 mm (skin and ankle motion the seed did
    not show): the triangle then misfits the layout by more than COMPLETE_FIT_FACTOR times its residual,
    within COMPLETE_FIT_FLOOR_M."""
    perf, model, R, points, ankle = _right_foot([-0.07, 0.0, -0.04], [0.12, 0.035, -0.045], [0.12, -0.035, -0.045])
    m = len(perf.marker_names)
    heel, toe, mt5 = foot = [perf.marker_names.index(n) for n in ("RHEE", "RTOE", "RMT5")]
    back = points[heel] - points[[toe, mt5]].mean(0)
    points[heel] += heel_off_m * back / np.linalg.norm(back)  # the foot 7 mm longer
    misfit = tracker._kabsch_rms(model.layout_offsets_m[foot][None], points[foot][None], np.ones((1, 3), bool))[0]
    assert misfit < tracker.COMPLETE_FIT_FLOOR_M
    assert (misfit > tracker.COMPLETE_FIT_FACTOR * 0.001) == (heel_off_m > 0)
    points = np.vstack([points, ankle + [0.0, 0.0, 1.5]])  # a stray free point, far from the foot
    st = tracker.new_state(model, points[:m], t_ns(0))
    st.t_root_m, st.R_parent_segment = perf.root_position_m[0], R
    st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
    right = np.arange(m)
    right[heel] = -1  # the heel hidden from the labels; its point is free
    swapped = right.copy()
    swapped[toe], swapped[mt5] = mt5, toe

    def check(point_index, free=True):
        cand = np.ones(len(points), bool)
        cand[point_index[point_index >= 0]] = False
        cand[heel] = free
        return _checked(lambda idx, cur: tracker._complete_by_free_point(model, st, points, cand, idx, cur), points, point_index)

    idx = right.copy()
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        assert not check(idx).any()
    assert (idx == right).all()
    idx = swapped.copy()
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        assert not check(idx, free=False).any()
    assert (idx == swapped).all()
    for _ in range(tracker.SHAPE_CONFIRM - 1):
        assert not check(idx).any()
    changed = check(idx)
    want = np.arange(m)
    assert (idx == want).all()
    assert set(np.flatnonzero(changed)) == set(foot)
    assert st.provisional[heel] == tracker.PROBATION_FRAMES


@pytest.mark.parametrize("rival", [False, True])
def test_a_label_on_a_hidden_neighbours_point_is_put_back_by_the_free_point_though_the_fit_is_off(rival):
    """A foot's toe label re-acquired on the heel's point (the heel hidden, the toe's own point free beside
    it), as a tennis player's heel label sat on the toe's point for 2.3 s: the fifth metatarsal and the
    point called toe are 3 cm farther apart than the layout's metatarsal and toe, so the pair is wrong. The
    free point then completes the foot even with the fit's ankle 5 cm off (a skeleton fitting at 20-30 mm):
    the heel label takes its point and the toe label the free one, after SHAPE_CONFIRM checks. Correct
    labels are left alone, and so is the pair with the fit's ankle 30 cm off (a far-fetched triangle).
    Also with a ghost where the foot's mirror image puts the toe, so that a wrong labeling of the two points
    fits the layout as well (a rival): the joint, clearly farther off for it, still tells them apart."""
    perf, model, R, points, _ = _right_foot([-0.07, 0.0, -0.04], [0.14, 0.02, -0.045], [0.09, -0.04, -0.045])
    m = len(perf.marker_names)
    heel, toe, mt5 = (perf.marker_names.index(n) for n in ("RHEE", "RTOE", "RMT5"))
    if rival:
        # the half turn about an axis in the foot's plane that swaps the heel's and metatarsal's points takes
        # the toe's point here: heel and metatarsal labels swapped, with this ghost as the toe, fit the layout
        # (the ankle, turned with them, lands below the foot)
        c, a = (points[heel] + points[mt5]) / 2, points[heel] - points[mt5]
        n = np.cross(np.cross(a, points[toe] - points[mt5]), a)
        n /= np.linalg.norm(n)
        ghost = c + 2.0 * n * (n @ (points[toe] - c)) - (points[toe] - c)
        points = np.vstack([points, ghost])
        fits = tracker._kabsch_rms(model.layout_offsets_m[[heel, mt5, toe]][None], points[[mt5, heel, m]][None],
                                   np.ones((1, 3), bool))[0]
        assert fits < 1e-6
    right = np.arange(m)
    right[heel] = -1  # the heel hidden from the labels; its point is free
    wrong = right.copy()
    wrong[toe], wrong[heel] = heel, -1  # the toe label on the heel's point, the toe's point free

    def run(point_index, shift_m):
        st = tracker.new_state(model, points[:m], t_ns(0))
        st.t_root_m, st.R_parent_segment = perf.root_position_m[0] + [0.0, 0.0, shift_m], R
        st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
        changed = np.zeros(m, bool)
        for _ in range(tracker.SHAPE_CONFIRM + 1):
            cand = np.ones(len(points), bool)
            cand[point_index[point_index >= 0]] = False
            cur = tracker._gather(points, point_index)
            changed |= tracker._complete_by_free_point(model, st, points, cand, point_index, cur)
        return changed

    idx = right.copy()
    assert not run(idx, 0.05).any() and (idx == right).all()
    idx = wrong.copy()
    assert not run(idx, 0.3).any() and (idx == wrong).all()
    idx = wrong.copy()
    changed = run(idx, 0.05)
    want = right.copy()
    want[heel] = heel
    assert (idx == want).all()
    assert set(np.flatnonzero(changed)) == {heel, toe}


@pytest.mark.parametrize("renumbered", [False, True])
@pytest.mark.parametrize("label", ["wrong", "right"])
def test_a_foots_lone_label_is_put_back_and_its_hidden_markers_labeled_by_two_free_points_and_its_joint(label, renumbered):
    """A foot whose heel and fifth metatarsal labels are lost, and whose one label left, the toe's, sits on
    the heel's point (a tennis player's ankle label on the toe's point stayed there 6.5 s, the other two
    points free beside it) or on its own. The two free points and the ankle where the fit puts it complete
    the foot: after SHAPE_CONFIRM checks every label is on its own point, the labels the two free points
    took on probation, also when the two free points trade numbers from frame to frame (a capture system
    numbers its points anew every frame). Left alone: with the fit's ankle 30 cm off (a far-fetched
    triangle), and with one free point only (nothing to register)."""
    perf, model, R, points, _ = _right_foot([-0.07, 0.0, -0.04], [0.14, 0.02, -0.045], [0.09, -0.04, -0.045])
    m = len(perf.marker_names)
    heel, toe, mt5 = (perf.marker_names.index(n) for n in ("RHEE", "RTOE", "RMT5"))
    points = np.vstack([points, points[heel] + [0.0, 0.0, 1.5]])  # a stray free point, far from the foot
    start = np.arange(m)
    start[[heel, mt5]] = -1
    if label == "wrong":
        start[toe] = heel

    def run(shift_m, hidden=()):
        st = tracker.new_state(model, points[:m], t_ns(0))
        st.t_root_m, st.R_parent_segment = perf.root_position_m[0] + [0.0, 0.0, shift_m], R
        st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
        idx, changed, pts = start.copy(), np.zeros(m, bool), points.copy()
        free = [p for p in range(m) if p not in start]
        for k in range(tracker.SHAPE_CONFIRM + 1):
            if renumbered and k:  # the two free points (of the first frame) trade numbers
                perm = np.arange(len(pts))
                perm[free] = perm[free[::-1]]
                pts, idx = pts[perm], np.where(idx >= 0, perm[np.maximum(idx, 0)], -1)
            cand = np.ones(len(pts), bool)
            cand[idx[idx >= 0]] = False
            cand[list(hidden)] = False
            changed |= _checked(lambda i, cur: tracker._complete_lone_label(model, st, pts, cand, i, cur), pts, idx)
        if renumbered and tracker.SHAPE_CONFIRM % 2 == 1:  # (back to the first frame's numbering)
            perm = np.arange(len(pts))
            perm[free] = perm[free[::-1]]
            idx = np.where(idx >= 0, perm[np.maximum(idx, 0)], -1)
        return idx, changed, st

    idx, changed, _ = run(0.3)
    assert not changed.any() and (idx == start).all()
    idx, changed, _ = run(0.0, hidden=[mt5])
    assert not changed.any() and (idx == start).all()
    idx, changed, st = run(0.0)
    assert (idx == np.arange(m)).all()
    assert set(np.flatnonzero(changed)) == ({heel, toe, mt5} if label == "wrong" else {heel, mt5})
    on_free_points = [toe, mt5] if label == "wrong" else [heel, mt5]
    assert (st.provisional[on_free_points] == tracker.PROBATION_FRAMES).all()


@pytest.mark.parametrize("fit_off_m", [0.0, 0.2])
def test_a_pair_misfitting_its_layout_by_skin_motion_is_kept_where_the_joint_fits_it(fit_off_m):
    """A forearm's RWRA and RFIN labels on their own points, the finger's point 16 mm farther from the wrist
    than in the layout (skin and joint motion: a pair misfits by 10-15 mm under pronation), RFRM and RWRB
    unlabeled, RWRB's point free, and a ghost where the pair, read as RWRB and RFIN, puts RWRA. That
    relabelling fits the layout and the misfit pair does not, but the elbow, where the fit puts it, fits
    the pair as labeled within COMPLETE_JOINT_RMS_M and clearly better: left alone (on 135_02 at L3 the
    relabelling swapped the right wrist labels for 3 s). With the fit's elbow 20 cm off, the joint cannot
    vouch for the pair, and the relabelling is taken as before (a wrong pair's misfit)."""
    from protocol.skeleton import SEGMENTS

    perf, model, points, st, _ = _with_layouts("r_forearm")
    m, layout = len(perf.marker_names), model.layout_offsets_m
    frm, wra, wrb, fin = (perf.marker_names.index(n) for n in ("RFRM", "RWRA", "RWRB", "RFIN"))
    assert set(np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))) == {frm, wra, wrb, fin}
    points = points.copy()
    away = points[fin] - points[wra]
    points[fin] += 0.016 * away / np.linalg.norm(away)
    R, t = tracker.rigid_motion(layout[[wrb, fin]], points[[wra, fin]])
    points = np.vstack([points, R @ layout[wra] + t])  # the ghost
    st.t_root_m = perf.root_position_m[0] + [0.0, 0.0, fit_off_m]
    st.R_parent_segment = Rotation.from_quat(perf.rotations_xyzw[0]).as_matrix()
    idx = np.arange(m)
    idx[[frm, wrb]] = -1
    before = idx.copy()
    changed = np.zeros(m, bool)
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        cand = np.ones(len(points), bool)
        cand[idx[idx >= 0]] = False
        cand[frm] = False  # hidden
        changed |= _checked(lambda i, cur: tracker._complete_by_free_point(model, st, points, cand, i, cur), points, idx)
    if fit_off_m == 0.0:
        assert not changed.any() and (idx == before).all()
    else:
        assert idx[wrb] == wra and idx[wra] == m  # RWRB on RWRA's point, RWRA on the ghost


def test_two_labels_tied_with_their_swap_take_the_least_change_unless_a_stale_position_blocks_it():
    """A foot's fifth metatarsal label on its point and the heel label re-acquired on the toe's point (heel
    and toe hidden a while; the toe's place last seen 25 cm from its point now). Two labels match one
    distance: handing the heel label's point to the toe fits the layout, and so does its swap, the
    metatarsal's point to the toe and the metatarsal label onto the toe's point. The stale place blocks the
    first, which used to let the second through (a tennis player's toe and ankle labels so swapped, 4 s).
    With no fit to say where the ankle is, neither is taken. Where the toe was last seen by its point, so
    that neither is blocked, the least change is taken: the heel label's point handed to the toe, the
    metatarsal label left on its point."""
    perf, model, R, points, _ = _right_foot([-0.07, 0.0, -0.04], [0.14, 0.02, -0.045], [0.09, -0.04, -0.045])
    m = len(perf.marker_names)
    heel, toe, mt5 = (perf.marker_names.index(n) for n in ("RHEE", "RTOE", "RMT5"))
    st = tracker.new_state(model, points, t_ns(0))
    st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
    away = points[mt5] - points[toe]
    st.pos_m[toe] = points[mt5] + 0.18 * away / np.linalg.norm(away)  # where the toe was last seen
    assert np.linalg.norm(st.pos_m[toe] - points[toe]) > tracker.SHAPE_MAX_HANDOVER_M
    st.provisional[[heel, mt5]] = tracker.PROBATION_FRAMES  # both just re-acquired
    idx = np.arange(m)
    idx[heel], idx[toe] = toe, -1
    wrong = idx.copy()
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        cur = tracker._gather(points, idx)
        assert not tracker._relabel_by_shape(model, st, points, idx, cur).any()
    assert (idx == wrong).all()
    st.pos_m[toe] = points[toe] + [0.0, 0.0, 0.02]
    for _ in range(tracker.SHAPE_CONFIRM):
        cur = tracker._gather(points, idx)
        changed = tracker._relabel_by_shape(model, st, points, idx, cur)
    want = np.arange(m)
    want[heel] = -1
    assert (idx == want).all() and set(np.flatnonzero(changed)) == {heel, toe}


@pytest.mark.parametrize("toes", ["curled", "level"])
def test_a_foots_label_is_handed_over_only_where_that_fits_its_layout(toes):
    """A foot's heel label and its toe label, just re-acquired, on their own points, the fifth metatarsal
    hidden, and the toes curled under (the toe marker turned 90 degrees about the metatarsal heads): the
    heel and toe points are 6 cm closer than in the layout, 2.6 cm farther than the heel and the fifth
    metatarsal. Handing the toe label's point to the metatarsal fits the layout's distance twice as well as
    the labels do, 13 mm against 30, but not as right labels fit it: the labels are left be
    (BENDING_SEGMENTS; 135_02 at L2, a toe label's point so handed to the metatarsal for 1-1.7 s). The toe
    label re-acquired on the metatarsal's point of a level foot fits it exactly once handed over, and is."""
    perf, model, R, points, _ = _right_foot([-0.07, 0.0, -0.04], [0.18, 0.02, -0.045], [0.09, -0.04, -0.045])
    m = len(perf.marker_names)
    heel, toe, mt5 = (perf.marker_names.index(n) for n in ("RHEE", "RTOE", "RMT5"))
    assert model.marker_segment[heel] in tracker.BENDING_SEGMENTS
    assert set(np.flatnonzero(model.marker_segment == model.marker_segment[heel])) == {heel, toe, mt5}
    idx = np.arange(m)
    idx[mt5] = -1
    points = points.copy()
    if toes == "curled":
        mtp = points[heel] + (points[toe] - points[heel]) * 0.7  # the metatarsal heads, 7.5 cm behind the toe marker
        side = np.cross([0.0, 0.0, 1.0], points[toe] - points[heel])
        points[toe] = mtp + Rotation.from_rotvec(np.radians(90) * side / np.linalg.norm(side)).apply(points[toe] - mtp)
        fits = tracker._kabsch_rms(model.layout_offsets_m[[[heel, toe], [heel, mt5]]],
                                   np.broadcast_to(points[[heel, toe]], (2, 2, 3)), np.ones((2, 2), bool))
        assert 0.025 < fits[0] and tracker.SHAPE_MIN_RMS_M < fits[1] < tracker.SHAPE_GAIN * fits[0]
        want = idx.copy()
    else:
        idx[toe] = mt5  # the toe label on the metatarsal's point; the toe's point out of view
        want = idx.copy()
        want[toe], want[mt5] = -1, mt5
    st = tracker.new_state(model, points, t_ns(0))
    st.t_root_m, st.R_parent_segment = perf.root_position_m[0], R
    st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
    st.provisional[toe] = tracker.PROBATION_FRAMES  # just re-acquired
    st.pos_m[[mt5, toe]] = points[[mt5, toe]]  # where they were last seen: nothing blocked
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        _checked(lambda i, cur: tracker._relabel_by_shape(model, st, points, i, cur), points, idx)
    assert (idx == want).all()


def test_a_wrist_label_on_the_waist_markers_point_is_reseated_where_its_forearm_puts_it():
    """A hand resting on the hip: the wrist marker's label on the waist marker's point and the waist's on
    the wrist's, 4 cm apart. No permutation within either segment undoes it, but the forearm's other labels
    still fit its layout and put the wrist label back on its own point; the waist's label takes the point
    the wrist's left. After SHAPE_CONFIRM checks, not before; correct labels are left alone, and so is a
    forearm whose every label misfits alike (nothing to tell which is off)."""
    from protocol.skeleton import SEGMENTS

    perf = perform(3, duration_s=0.1)
    m = len(perf.marker_names)
    model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                 perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                 layout_rms_m=np.full(m, 0.001))
    fore = np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))
    pelvis = np.flatnonzero(perf.marker_segment == SEGMENTS.index("pelvis"))
    assert len(fore) >= tracker.RESEAT_MIN_LABELS and len(pelvis) >= 3
    wrist, waist = int(fore[0]), int(pelvis[0])
    points = perf.recording.points_m[0].copy()
    points[waist] = points[wrist] + [0.04, 0.0, 0.0]  # the hand at the hip
    st = tracker.new_state(model, points, t_ns(0))
    st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
    right = np.arange(m)
    swapped = right.copy()
    swapped[wrist], swapped[waist] = waist, wrist

    def check(point_index):
        cand = np.zeros(len(points), bool)
        return _checked(lambda idx, cur: tracker._reseat_outliers(model, st, points, cand, idx, cur), points, point_index)

    idx = right.copy()
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        assert not check(idx).any()
    assert (idx == right).all()
    idx = swapped.copy()
    for _ in range(tracker.SHAPE_CONFIRM - 1):
        assert not check(idx).any()
    changed = check(idx)
    assert (idx == right).all()
    assert set(np.flatnonzero(changed)) == {wrist, waist}
    # every forearm label 3 cm off along a different direction: leaving out one fits no better than another
    idx = right.copy()
    moved = points.copy()
    rng = np.random.default_rng(0)
    for i in fore:
        v = rng.normal(size=3)
        moved[i] += 0.03 * v / np.linalg.norm(v)
    st.reseat_votes.clear()
    for _ in range(tracker.SHAPE_CONFIRM + 1):
        cur = tracker._gather(moved, idx)
        assert not tracker._reseat_outliers(model, st, moved, np.ones(len(moved), bool), idx, cur).any()


def test_a_re_acquired_label_on_a_hidden_neighbours_point_is_handed_to_it():
    """A forearm marker re-acquired on the point of another forearm marker, which is unlabeled (both were
    hidden; it came back first): the layout says the point is the other's, so it is handed over once
    SHAPE_CONFIRM checks agree, and the re-acquired marker is unlabeled again. A settled label (confirmed
    by the whole layout and tracked since) is left. (One tracked all along, not settled: only on
    overwhelming evidence, `test_a_tracked_wrist_label_on_a_neighbours_point_is_handed_over_only_on_...`.)"""
    perf, model, points, st, fore = _with_layouts("r_forearm")
    m = len(perf.marker_names)
    a, b = fore[1], fore[0]  # a wrist marker on the point of the forearm marker 15 cm up
    wrong = np.arange(m)
    wrong[a], wrong[b] = b, -1  # a sits on b's point; b unlabeled

    def checks(provisional: int, settled: bool = False):
        idx = wrong.copy()
        st.provisional[:] = 0
        st.provisional[a] = provisional
        st.settled[a] = settled
        for _ in range(tracker.SHAPE_CONFIRM):
            cur = np.where(idx[:, None] >= 0, points[np.maximum(idx, 0)], np.nan)
            changed = tracker._relabel_by_shape(model, st, points, idx, cur)
        return idx, changed

    idx, changed = checks(provisional=0, settled=True)
    assert (idx == wrong).all() and not changed.any()
    idx, changed = checks(provisional=tracker.PROBATION_FRAMES)
    assert idx[b] == b and idx[a] == -1 and set(np.flatnonzero(changed)) == {a, b}
    assert (np.delete(idx, [a, b]) == np.delete(np.arange(m), [a, b])).all()


def test_with_one_other_label_in_view_a_re_acquired_label_is_handed_by_their_distance():
    """Two of a forearm's four markers in view: the forearm marker, and a wrist label re-acquired on the
    finger marker's point. Two labeled points still tell their distance (22 cm, where the layout has 15 cm
    for these labels and 22 cm to the finger), so the point is handed to the finger marker. Segments with
    two labels were never checked: a toe label on a tennis player's ankle point stayed 270 frames."""
    perf, model, points, st, fore = _with_layouts("r_forearm")
    m = len(perf.marker_names)
    assert [perf.marker_names[i] for i in fore] == ["RFRM", "RWRA", "RWRB", "RFIN"]
    a, b = fore[1], fore[3]  # RWRA on RFIN's point; RWRB and RFIN unlabeled
    idx = np.arange(m)
    idx[a], idx[b], idx[fore[2]] = b, -1, -1
    st.provisional[a] = tracker.PROBATION_FRAMES
    for _ in range(tracker.SHAPE_CONFIRM):
        cur = np.where(idx[:, None] >= 0, points[np.maximum(idx, 0)], np.nan)
        changed = tracker._relabel_by_shape(model, st, points, idx, cur)
    assert idx[b] == b and idx[a] == -1 and idx[fore[2]] == -1 and set(np.flatnonzero(changed)) == {a, b}


def test_a_label_on_a_near_neighbours_point_is_handed_over_on_clear_evidence():
    """A foot of four markers (53-marker set), three labeled: heel, fifth metatarsal, and the first
    metatarsal's label re-acquired on the toe marker's point, 5.6 cm away. Registered, the two layouts differ
    by less than SHAPE_DISTINCT_M, which used to rule the handover out (a toe label sat 1.6 s on the fifth
    metatarsal's point: 85_12 at L2); the labels misfit by about that difference and the handed-over ones
    fit exactly, so the point goes to the toe marker; also from a foot whose layout held to 4 mm in
    calibration (a toe label sat 1.5 s on the fifth metatarsal's point of such a foot: 85_02 at L2), or to
    5 mm (a forearm's, 135_02 at L3). Not with a layout that was looser."""
    from protocol.skeleton import SEGMENTS

    perf = perform(3, marker_set="gt53", duration_s=0.1)
    m = len(perf.marker_names)
    foot = {perf.marker_names[i]: i for i in np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_foot"))}
    heel, mt5, mt1, toe = foot["RHEL"], foot["RMT5"], foot["RMT1"], foot["RTOE"]
    off = perf.marker_offsets_m
    now, moved = off[[heel, mt5, mt1]], off[[heel, mt5, toe]]
    symmetric = tracker._kabsch_rms(moved[None], now[None], np.ones((1, 3), bool))[0]
    assert tracker.SHAPE_CLEAR_MIN_M <= symmetric < tracker.SHAPE_DISTINCT_M

    def handed(layout_rms_m: float):
        model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, off, perf.joint_offsets_m, True,
                                     layout_offsets_m=off, layout_rms_m=np.full(m, layout_rms_m))
        points = perf.recording.points_m[0]
        st = tracker.new_state(model, points, t_ns(0))
        st.shape_fit[:], st.shape_checks[:] = 1.0, 10
        idx = np.arange(m)
        idx[mt1], idx[toe] = toe, -1
        st.provisional[mt1] = tracker.PROBATION_FRAMES
        for _ in range(tracker.SHAPE_CONFIRM):
            cur = np.where(idx[:, None] >= 0, points[np.maximum(idx, 0)], np.nan)
            tracker._relabel_by_shape(model, st, points, idx, cur)
        return idx[toe] == toe and idx[mt1] == -1

    assert handed(0.002) and handed(0.004) and handed(0.005)
    assert not handed(0.007)


def run_tracker(points_m: np.ndarray, seed_frames: int, shuffle_seed: int = 0, ghosts_m=None):
    """Seed, then step every later frame with the points shuffled; returns per frame the true marker each
    marker slot was given (-1 = none, -2 = a ghost)."""
    rng = np.random.default_rng(shuffle_seed)
    model, st = seeded_state(points_m, seed_frames)
    got = np.full(points_m.shape[:2], -1)
    for f in range(seed_frames, len(points_m)):
        seen = np.flatnonzero(np.isfinite(points_m[f, :, 0]))
        cloud, truth = points_m[f, seen], seen
        if ghosts_m is not None:
            cloud = np.concatenate([cloud, ghosts_m[f]])
            truth = np.concatenate([truth, np.full(len(ghosts_m[f]), -2)])
        order = rng.permutation(len(cloud))
        cloud, truth = cloud[order], truth[order]
        st, res = tracker.step(model, st, cloud, np.ones(len(cloud), bool), t_ns(f), CONFIG)
        idx = res.point_index
        got[f] = np.where(idx >= 0, truth[np.maximum(idx, 0)], -1)
    return got


@pytest.mark.parametrize("m", [0, 1, 2])
def test_a_subject_of_fewer_markers_than_a_partner_set_steps_without_error(m):
    """Degenerate subjects (no marker, one, two: fewer than three partners) step through random clouds,
    their partner lists rebuilt on the way, and label nothing they cannot tell."""
    model = tracker.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)),
                                 np.zeros((14, 3)))
    st = tracker.new_state(model, np.zeros((m, 3)), t_ns(0))
    rng = np.random.default_rng(m)
    for f in range(1, 70):  # past the partner update (every 30 frames)
        st, res = tracker.step(model, st, rng.normal(size=(5, 3)), np.ones(5, bool), t_ns(f), CONFIG)
        assert res.point_index.shape == (m,)
    assert st.partners.shape == (m, tracker.N_PARTNERS)


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


def test_a_reacquired_marker_keeps_its_measured_velocity():
    """A velocity needs two observations: a marker found again where its (wrong) prediction was not gets
    the velocity it was last measured with, not (point - prediction) / dt, which turned prediction errors
    into speed and walked fast arms onto their neighbours (tennis serve at 50 Hz)."""
    m = 6
    st = tracker.new_state(
        tracker.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)), np.zeros((14, 3))),
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
    """A marker swinging on a tight circle at 50 Hz (3.6 m/s, 108 m/s^2: a serving hand) curves 4 cm off a
    straight line each frame. Predicted with its measured acceleration it is tracked every frame; the
    control, a constant-velocity prediction (acceleration capped at 0), loses it."""
    rate, r, w = 50.0, 0.12, 30.0
    t = np.arange(100) / rate
    P = np.stack([r * np.cos(w * t), r * np.sin(w * t), np.ones_like(t)], axis=1)[:, None]
    model = tracker.SubjectModel("P", ("M0",), np.zeros(1, int), np.zeros((1, 3)), np.zeros((14, 3)))

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
        model = tracker.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)),
                                     np.zeros((14, 3)), has_skeleton=True)
        ns = [int(round(f * 1e9 / rate)) for f in range(len(P))]
        st = tracker.new_state(model, P[0], ns[0], P[:1])
        solver = _CountingSolver()
        n = 66
        for f in range(1, n + 1):
            st, res = tracker.step(model, st, P[f], np.ones(m, bool), ns[f], CONFIG, solver)
        assert solver.launches == n // every, rate


@pytest.mark.parametrize("long_memory", [True, False])
def test_a_swap_the_running_distance_statistics_absorbed_is_swapped_back(monkeypatch, long_memory):
    """Two rigid bodies move apart after one marker of each was tracked through a crossing swapped (a wrist
    passing 1.3 cm from a waist marker, 135_02 at L2). Within ten updates the running statistics widen
    enough for the swapped labels to look normal; the long-memory ones do not, and the repair swaps back."""
    if not long_memory:
        monkeypatch.setattr(tracker, "SLOW_ALPHA", 0.02)  # the long memory as short as the running one
    rng = np.random.default_rng(3)
    plate = rng.uniform(-0.05, 0.05, (4, 3))
    hist = []
    for f in range(300):  # body B wanders about body A, each turning on its own
        ra = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        rb = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        hist.append(np.vstack([plate @ ra.T, plate @ rb.T + [0.3, 0, 0] + rng.normal(0, 0.1, 3)]))
    hist = np.array(hist)
    model = tracker.SubjectModel("P", tuple(f"M{i}" for i in range(8)), np.zeros(8, int), np.zeros((8, 3)), np.zeros((14, 3)))
    st = tracker.new_state(model, hist[-1], 0, hist)
    # A's marker 0 and B's marker 4 met 1.3 cm apart and their labels crossed; B then moves off 15 cm over
    # ten updates of the statistics (20 frames), the labels still crossed
    a, b = plate.copy(), plate.copy()
    b += a[0] - b[0] + [0.013, 0, 0]
    for k in range(10):
        now = np.vstack([a, b + [0.015 * k, 0, 0]])
        crossed = now.copy()
        crossed[[0, 4]] = now[[4, 0]]
        tracker._update_distances(st, crossed, np.ones(8, bool))
    point_index = np.array([4, 1, 2, 3, 0, 5, 6, 7])  # point 0 is A's marker 0 ...
    cur = now[point_index]
    assert tracker.distance_misfit(st, cur, np.ones(8, bool))[[0, 4]].max() < tracker.Z_SUSPECT  # absorbed
    tracker._repair_by_distances(st, point_index, cur, now, np.zeros(8, bool))
    assert (point_index == np.arange(8)).all() == long_memory


def _limb(angle: float, layout: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """A rigid cluster `layout` (offsets from the pivot) swung by `angle` [rad] about the vertical at `pivot`."""
    return layout @ Rotation.from_rotvec([0.0, 0.0, angle]).as_matrix().T + pivot


def test_with_no_skeleton_a_cluster_hidden_whole_is_found_by_its_layout():
    """A subject with no skeleton (a seed taken lying down): a limb's cluster of four hides whole and swings a
    quarter turn meanwhile, so the partners across the joint place it 40-70 cm off. Once back it is found by
    its own layout among the free points (`_search_rigid_groups`), with a ghost beside it, and never given
    to the wrong marker. Fails without the search: the cluster stays unlabeled."""
    rng = np.random.default_rng(11)
    trunk = rng.uniform(-0.15, 0.15, (5, 3)) + [0.0, 0.0, 0.3]
    layout = np.array([[0.30, 0.02, 0.0], [0.38, -0.05, 0.03], [0.45, 0.06, -0.02], [0.52, -0.01, 0.05]])
    other = np.array([[-0.25, 0.1, 0.0], [-0.33, 0.0, 0.04], [-0.42, 0.12, 0.0], [-0.5, 0.03, -0.03]])
    pivot_a, pivot_b = np.array([0.1, 0.0, 0.3]), np.array([-0.1, 0.0, 0.3])
    n, seed, hide = 480, 240, slice(300, 360)
    angle = 0.3 * np.sin(np.arange(n) / 25.0)  # the limbs move during the seed: their partners are their own
    angle[hide] += np.linspace(0.0, np.pi / 2, hide.stop - hide.start)
    angle[hide.stop:] += np.pi / 2
    P = np.stack([np.concatenate([trunk + [0.001 * f, 0, 0], _limb(angle[f], layout, pivot_a + [0.001 * f, 0, 0]),
                                  _limb(-angle[f], other, pivot_b + [0.001 * f, 0, 0])]) for f in range(n)])
    limb = np.arange(5, 9)
    P[hide, 5:9] = np.nan
    ghosts = (P[:, 6] + [0.0, 0.06, 0.0])[:, None]
    ghosts[: hide.stop] = P[hide.stop, 6] + [0.0, 0.06, 0.0]  # (a point that is never a marker)
    got = run_tracker(P, seed, shuffle_seed=11, ghosts_m=ghosts)
    assert not np.any((got[seed:] >= 0) & (got[seed:] != np.arange(P.shape[1])))  # nothing wrong
    assert not np.any(got[seed:] == -2)
    back = hide.stop + tracker.SEARCH_LOST_FRAMES + tracker.SEARCH_EVERY_FRAMES
    assert np.all(got[back:, limb] == limb)


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
    tracker._update_partners(st)
    rng = np.random.default_rng(6)
    for f in range(seed, n):
        error = np.zeros((7, 3))
        error[6] = fit_error_m * np.array([0.0, 0.0, 1.0])
        st.skel_pred_m, st.skel_vel_m_s, st.skel_t_ns, st.fit_rms_m = P[f] + error, np.zeros((7, 3)), t_ns(f), 0.005
        seen = np.arange(6) if hide[0] <= f < hide[1] else np.arange(7)
        order = rng.permutation(len(seen))
        if f == hide[1]:  # where the partners put it as it comes back
            rpred, _, _ = tracker.rigid_predictions(st, np.where(np.arange(7)[:, None] < 6, P[f], np.nan),
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
    tracker._update_partners(st)
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
    monkeypatch.setattr(tracker, "Z_SUSPECT", np.inf)
    perf = perform(3, duration_s=2.0)
    P = perf.recording.points_m
    m, seed = len(perf.marker_names), 120
    model = tracker.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
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
    model = tracker.SubjectModel("P", tuple(f"M{i}" for i in range(m)), seg, np.zeros((m, 3)), np.zeros((14, 3)),
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


def test_agreeing_pairs_place_three_markers_only_as_one_unrivalled_set():
    pairs = [(2, 0.006, {0: 10, 1: 11}), (2, 0.007, {0: 10, 2: 12}), (2, 0.01, {1: 11, 2: 12})]
    assert tracker._agreeing_pairs(list(pairs)) == {0: 10, 1: 11, 2: 12}
    assert tracker._agreeing_pairs(pairs[:2]) is None  # markers 1 and 2 never placed together
    rival = [(2, 0.006, {0: 20, 1: 21}), (2, 0.007, {0: 20, 2: 22}), (2, 0.01, {1: 21, 2: 22})]
    assert tracker._agreeing_pairs(pairs + rival) is None
    assert tracker._agreeing_pairs(pairs + rival[:2]) == {0: 10, 1: 11, 2: 12}


@pytest.mark.parametrize("off_mm", [0, 25])
def test_a_lost_forearm_one_of_whose_markers_left_its_layout_is_found_by_its_agreeing_pairs(off_mm):
    """A forearm turned 80 degrees at the elbow while unlabeled comes back with three of its four markers
    in view, one moved 25 mm off the layout (on its sphere about the elbow: skin, or a hand flexed at the
    wrist): the three no longer fit the layout at once (they were not found before `_agreeing_pairs`),
    but every two of them do, alike, and they are found."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    rng = np.random.default_rng(3)
    perf, model, st, old, now, _ = _turned_unseen(rng, {"r_forearm": ("y", 80)})
    k = SEGMENTS.index("r_forearm")
    forearm = np.flatnonzero(perf.marker_segment == k)
    hidden, moved = forearm[1], forearm[0]
    _, pw = world_transforms(st.t_root_m, st.R_parent_segment, perf.joint_offsets_m)
    radial = now[moved] - pw[k]
    side = np.cross(radial, [0.0, 0.0, 1.0])
    points = now.copy()
    points[moved] += off_mm * 1e-3 * side / np.linalg.norm(side)
    in_view = np.arange(len(now)) != hidden
    labeled = ~np.isin(np.arange(len(now)), forearm)
    cur = np.where(labeled[:, None], points, np.nan)
    free = np.isin(np.arange(len(now)), forearm) & in_view
    found = tracker._search_segments(model, st, points, free, labeled, cur, ~labeled & (perf.marker_segment == k))
    assert found == {int(i): int(i) for i in forearm if i != hidden}
