"""service/layouts.py: a segment's calibrated marker layout and the labels it corrects. Labels permuted
within a segment put back, labels handed over to hidden neighbours, swaps the layout cannot see told by the
joint, a pair completed by a free point, a lone label by two, an outlier reseated, and how a layout earns
its trust."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol.skeleton import N_SEGMENTS
from recordings.synthetic import perform
from service import layouts, track_state, tracker
from tests.tracker_fixtures import t_ns, turned_unseen


def test_a_swap_the_layout_cannot_see_is_told_by_the_joint():
    """A foot whose heel is as far from the toe as from the fifth metatarsal: the toe and metatarsal labels
    swapped fit the three markers' layout exactly (a turn of the foot about its long axis), so the layout
    check cannot undo the swap (HDM05 at L3: 3 s). The ankle, which the shank holds, is a fourth point off
    their plane: with it the swap shows, and the relabelling that undoes it is found; the true labels are
    left alone."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    rng = np.random.default_rng(6)
    perf, model, st, old, _, _ = turned_unseen(rng, {}, measured_layouts=True)
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
    maps = layouts._relabellings(3, 3)
    symmetric = np.ones(len(maps), bool)
    swapped = cur.copy()
    swapped[lab[[1, 2]]] = cur[lab[[2, 1]]]

    found = layouts._mirror_by_joint(model, st, k, lab, lab, maps, swapped, symmetric)
    assert found is not None and list(lab[maps[found]]) == [lab[0], lab[2], lab[1]]
    assert layouts._mirror_by_joint(model, st, k, lab, lab, maps, cur, symmetric) is None


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
    np.testing.assert_allclose(layouts._kabsch_rms(A, B, w), want, atol=1e-9)


def _checked(layout_check, points: np.ndarray, point_index: np.ndarray) -> np.ndarray:
    """Run one of the tracker's layout checks, `layout_check(point_index, cur)`, which relabels in place;
    the positions it was given must follow the labels it leaves. Returns the markers whose point changed."""
    cur = track_state._gather(points, point_index)
    changed = layout_check(point_index, cur)
    np.testing.assert_array_equal(cur, track_state._gather(points, point_index))
    return changed


def _with_layouts(segment: str):
    """A synthetic performer's first frame, its model with layouts measured (2 mm residuals), a state whose
    layouts have been fitting, and the markers of `segment`: (perf, model, points, st, markers)."""
    from protocol.skeleton import SEGMENTS

    perf = perform(3, duration_s=0.1)
    model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
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
        return _checked(lambda idx, cur: layouts._relabel_by_shape(model, st, points, idx, cur), points, point_index)

    idx = right.copy()
    assert not check(idx).any() and (idx == right).all()
    unmeasured = dataclasses.replace(model, layout_rms_m=None)
    idx = wrong.copy()
    st.settled[fore[:3]] = False  # as the fast pass that permuted them left them (a choice in tracking)
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        assert not check(idx, unmeasured).any()
    assert (idx == wrong).all()
    for _ in range(layouts.SHAPE_CONFIRM - 1):
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
    assert not layouts._relabel_by_shape(model, st, points, idx, track_state._gather(points, idx)).any()
    assert st.settled[fore].all()  # confirmed: the whole forearm labeled, fitting its layout
    # the layout now says three of the forearm's labels sit cycled on each other's points
    three = fore[1:4]
    cycled = perf.marker_offsets_m.copy()
    cycled[three] = perf.marker_offsets_m[three[[1, 2, 0]]]
    twisted = dataclasses.replace(model, layout_offsets_m=cycled)
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        assert not layouts._relabel_by_shape(twisted, st, points, idx, track_state._gather(points, idx)).any()
    assert (idx == right).all()
    st.settled[three] = False  # re-acquired since (a forearm back from an occlusion)
    changed = np.zeros(m, bool)
    for _ in range(layouts.SHAPE_CONFIRM):
        changed |= layouts._relabel_by_shape(twisted, st, points, idx, track_state._gather(points, idx))
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
    cur = track_state._gather(points, idx)
    misfit = layouts._layout_fits(model, cur, idx >= 0, np.array([model.marker_segment[wrist]]))[3][0]
    assert (misfit > 0.045) if taken else (0.01 < misfit < layouts.SHAPE_SETTLED_HANDOVER_MISFIT_M)
    assert st.provisional[wrist] <= 0  # tracked all along
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        _checked(lambda i, c: layouts._relabel_by_shape(model, st, points, i, c), points, idx)
    want = np.arange(m)
    want[wrist] = -1
    if not taken:
        want[wrist], want[other] = other, -1
    np.testing.assert_array_equal(idx, want)


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
    assert k in layouts.TWISTING_SEGMENTS
    R = Rotation.from_quat(perf.rotations_xyzw[0]).as_matrix()
    elbow = world_transforms(perf.root_position_m[0], R, perf.joint_offsets_m)[1][k]
    points = points.copy()
    axis = (points[wra] + points[wrb]) / 2 - elbow
    points[[wra, wrb]] = elbow + Rotation.from_rotvec(np.radians(135) * axis / np.linalg.norm(axis)).apply(points[[wra, wrb]] - elbow)
    labels, swap = [frm, wra, wrb], [frm, wrb, wra]
    misfit = layouts._kabsch_rms(layout[[labels, swap]], np.broadcast_to(points[labels], (2, 3, 3)), np.ones((2, 3), bool))
    assert misfit[0] > 0.015 and misfit[1] < 0.004
    # the fit's elbow where the labels (or their swap), registered on the layout, put the segment's origin
    _, origin = track_state.rigid_motion(layout[labels if elbow_fits == "labels" else swap], points[labels])
    st.t_root_m, st.R_parent_segment = perf.root_position_m[0] + origin - elbow, R
    st.skel_pred_m = points.copy()  # (a fit to ask)
    idx = np.arange(m)
    idx[fin] = -1  # hidden
    changed = np.zeros(m, bool)
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        changed |= _checked(lambda i, cur: layouts._relabel_by_shape(model, st, points, i, cur), points, idx)
    if elbow_fits == "labels":
        assert not changed.any() and (idx[[frm, wra, wrb]] == labels).all()
    else:
        assert set(np.flatnonzero(changed)) == {wra, wrb} and idx[wra] == wrb and idx[wrb] == wra


def test_a_wrist_label_on_its_neighbours_point_is_handed_back_though_the_fit_followed_it():
    """A serving wrist's RWRB label re-acquired on RWRA's point (RWRA unlabeled), and the fit, which follows
    the labels, rolled the forearm so that the elbow sits where the wrong labels put it: the joint test of
    a twisting segment (TWISTING_SEGMENTS) prefers the labels. But the handover back fits the layout under
    TWIST_CLEAR_SHARE of their misfit (here exactly, against the wrist pair's distance), which pronation
    does not reach: it is taken (two players at L2, seed 2: 30 frames refused at 0.4-1.4 against 15-16 mm)."""
    perf, model, points, st, _ = _with_layouts("r_forearm")
    m, layout = len(perf.marker_names), model.layout_offsets_m
    frm, wra, wrb, fin = (perf.marker_names.index(n) for n in ("RFRM", "RWRA", "RWRB", "RFIN"))
    R = Rotation.from_quat(perf.rotations_xyzw[0]).as_matrix()
    idx = np.arange(m)
    idx[wrb], idx[wra] = wra, -1  # RWRB's label on RWRA's point
    st.provisional[wrb] = layouts.PROBATION_FRAMES  # (just re-acquired)
    wrong, right = [frm, wrb, fin], [frm, wra, fin]
    misfit = layouts._kabsch_rms(layout[[wrong, right]], np.broadcast_to(points[[frm, wra, fin]], (2, 3, 3)), np.ones((2, 3), bool))
    assert misfit[1] < layouts.TWIST_CLEAR_SHARE * misfit[0]
    k = perf.marker_segment[frm]
    from service.calibration import world_transforms

    elbow = world_transforms(perf.root_position_m[0], R, perf.joint_offsets_m)[1][k]
    _, origin = track_state.rigid_motion(layout[wrong], points[[frm, wra, fin]])  # where the wrong labels put it
    st.t_root_m, st.R_parent_segment = perf.root_position_m[0] + origin - elbow, R
    st.skel_pred_m = points.copy()  # (a fit to ask)
    rows = np.array([0, 1])
    maps = np.array([[0, 1, 2], [0, 3, 2]])  # the labels, and RWRB's handed to RWRA
    slot = np.array([frm, wrb, fin, wra])
    joint_fit = layouts._joint_fits(model, st, k, np.array(wrong), slot, maps, rows, track_state._gather(points, idx))
    assert joint_fit[1] > joint_fit[0]  # the joint alone would refuse it
    changed = np.zeros(m, bool)
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        changed |= _checked(lambda i, cur: layouts._relabel_by_shape(model, st, points, i, cur), points, idx)
    assert idx[wra] == wra and idx[wrb] == -1 and changed[[wra, wrb]].all()


def _bent_wrist_on_its_neighbours_point(residual_m: float, bend_deg: float = 12.0):
    """A right forearm's layout measured at `residual_m`, the finger marker off its seed place by the wrist's
    bend (`bend_deg` of deviation), and RWRB's label on RWRA's point, RWRA unlabeled; the fit's elbow between
    where the labels and the handover put it, nearer the handover's (the joint agrees with it, though not as
    clearly as a mirror image it would take on its own word, JOINT_GAIN). Returns (model, st, points, idx,
    (RWRA, RWRB), the layout's misfit [m] RMS of the labels as they are and handed back)."""
    from service.calibration import world_transforms

    perf, model, points, st, _ = _with_layouts("r_forearm")
    model = dataclasses.replace(model, layout_rms_m=np.full(len(perf.marker_names), residual_m))
    m, layout = len(perf.marker_names), model.layout_offsets_m
    frm, wra, wrb, fin = (perf.marker_names.index(n) for n in ("RFRM", "RWRA", "RWRB", "RFIN"))
    points = points.copy()
    wrist = (points[wra] + points[wrb]) / 2
    axis = np.cross(points[wra] - points[wrb], points[fin] - wrist)
    points[fin] = wrist + Rotation.from_rotvec(np.radians(bend_deg) * axis / np.linalg.norm(axis)).apply(points[fin] - wrist)
    wrong, right = [frm, wrb, fin], [frm, wra, fin]
    misfit = layouts._kabsch_rms(layout[[wrong, right]], np.broadcast_to(points[[frm, wra, fin]], (2, 3, 3)), np.ones((2, 3), bool))
    R = Rotation.from_quat(perf.rotations_xyzw[0]).as_matrix()
    k = perf.marker_segment[frm]
    elbow = world_transforms(perf.root_position_m[0], R, perf.joint_offsets_m)[1][k]
    _, at_right = track_state.rigid_motion(layout[right], points[[frm, wra, fin]])
    _, at_wrong = track_state.rigid_motion(layout[wrong], points[[frm, wra, fin]])
    origin = 0.6 * at_right + 0.4 * at_wrong
    st.t_root_m, st.R_parent_segment = perf.root_position_m[0] + origin - elbow, R
    st.skel_pred_m = points.copy()  # (a fit to ask)
    idx = np.arange(m)
    idx[wrb], idx[wra] = wra, -1  # RWRB's label on RWRA's point
    return model, st, points, idx, (wra, wrb), misfit


def _shape_checks(model, st, points, idx) -> np.ndarray:
    """SHAPE_CONFIRM + 1 layout checks in a row (`_relabel_by_shape`): the markers whose point changed."""
    changed = np.zeros(len(idx), bool)
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        changed |= _checked(lambda i, cur: layouts._relabel_by_shape(model, st, points, i, cur), points, idx)
    return changed


@pytest.mark.parametrize("reacquired", [True, False])
def test_a_reacquired_wrist_label_is_handed_back_though_the_hand_bent(reacquired):
    """A wrist label re-acquired on its neighbour's point (RWRB's on RWRA's, RWRA unlabeled), the finger
    marker, which the forearm's layout carries, off its seed place by the wrist's bend (12 degrees of
    deviation): handed back, the labels fit the layout at 5-6 mm, beyond what clear evidence has asked
    (twice the 2 mm calibration residual) but within what right labels fit on a check, and against 19 mm
    as they are. A label on probation is suspect: it is handed back (a serving wrist, tennis at L2: refused 0.46 s
    at 2-6 mm against 15-19 mm), the joint agreeing. One tracked all along is not, short of overwhelming
    evidence."""
    model, st, points, idx, (wra, wrb), misfit = _bent_wrist_on_its_neighbours_point(0.002)
    assert misfit[0] > layouts.SHAPE_MIN_RMS_M and 2 * 0.002 < misfit[1] < 4 * 0.002
    st.provisional[wrb] = layouts.PROBATION_FRAMES if reacquired else 0
    changed = _shape_checks(model, st, points, idx)
    if reacquired:
        assert idx[wra] == wra and idx[wrb] == -1 and changed[[wra, wrb]].all()
    else:
        assert not changed.any() and idx[wrb] == wra


@pytest.mark.parametrize("share, forearm", [(layouts.REACQUIRED_HANDOVER_SHARE, True), (0.0, True),
                                            (layouts.REACQUIRED_HANDOVER_SHARE, False)])
def test_a_reacquired_wrist_label_is_handed_back_where_that_fits_well_under_the_labels(monkeypatch, share, forearm):
    """The same bent wrist on a forearm whose layout held to 1 mm in calibration (a check's tolerance 4 mm,
    as the tennis player's): handed back, the labels fit at 5-6 mm, beyond the tolerance, but under
    REACQUIRED_HANDOVER_SHARE of their 19 mm misfit as they are: handed back (a serving wrist, tennis at L2:
    handed back at 4.6-5.8 mm against 15-16 mm, 12 frames sooner). Held to the tolerance alone, they stay;
    and so they do on a segment that is not a forearm (TWISTING_SEGMENTS: on every segment, 03_rolling lost)."""
    model, st, points, idx, (wra, wrb), misfit = _bent_wrist_on_its_neighbours_point(0.001)
    tol = layouts._fit_tolerance(np.array([3]), np.array([0.001]))[1][0]
    assert tol < misfit[1] < layouts.REACQUIRED_HANDOVER_SHARE * misfit[0]
    monkeypatch.setattr(layouts, "REACQUIRED_HANDOVER_SHARE", share)
    if not forearm:
        monkeypatch.setattr(layouts, "TWISTING_SEGMENTS", ())
    st.provisional[wrb] = layouts.PROBATION_FRAMES
    changed = _shape_checks(model, st, points, idx)
    if share and forearm:
        assert idx[wra] == wra and idx[wrb] == -1 and changed[[wra, wrb]].all()
    else:
        assert not changed.any() and idx[wrb] == wra


def test_layouts_are_trusted_from_the_frames_they_were_calibrated_from():
    """A calibration that lands after the seed starts with every segment's layout trusted where the
    labeled history fits it, so a swap right after it can be undone (a tennis serve at 50 Hz swapped the
    wrist labels 0.4 s after the seed, and they stayed swapped 40 frames while the layout earned trust);
    not a segment whose labels in the history misfit it (a layout calibrated wrong)."""
    from protocol.skeleton import SEGMENTS

    perf = perform(3, duration_s=1.0)
    m = len(perf.marker_names)
    model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                     perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                     layout_rms_m=np.full(m, 0.002))
    history = perf.recording.points_m[:80].copy()
    st = tracker.new_state(model, history[-1], t_ns(0))
    assert not layouts._trusted_layouts(st).any()
    fore = np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))
    history[:, fore[:2]] = history[:, fore[[1, 0]]]  # two forearm labels swapped all along
    layouts.learn_layout_trust(model, st, history)
    trusted = layouts._trusted_layouts(st)
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
    model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                     perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                     layout_rms_m=rng.uniform(0.0005, 0.004, m))
    history = perf.recording.points_m[:90] + rng.normal(0.0, 0.004, (90, m, 3))
    history[rng.random((90, m)) < 0.3] = np.nan
    fore = np.flatnonzero(perf.marker_segment == SEGMENTS.index("l_forearm"))
    history[40:70, fore[:2]] = history[40:70, fore[[1, 0]]]
    st, ref = (tracker.new_state(model, perf.recording.points_m[0], t_ns(0)) for _ in range(2))
    for s in (st, ref):  # checked before (a recalibration's): the shares are running means, the order counts
        s.shape_fit[:], s.shape_checks[:] = 0.5, 60
    layouts.learn_layout_trust(model, st, history)

    checked = 0
    for frame in history[:: layouts.SHAPE_EVERY_FRAMES]:
        sel = np.isfinite(frame[:, 0]) & layouts._layout_slots(model, ref)
        counts = np.bincount(model.marker_segment[sel], minlength=N_SEGMENTS)
        ks = np.flatnonzero(counts >= layouts.SHAPE_MIN_LABELED)
        _, _, n_lab, rms, typical = layouts._layout_fits(model, frame, sel, ks)
        layouts._count_layout_fits(ref, ks, rms <= layouts._fit_tolerance(n_lab, typical)[1])
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
    model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, off, perf.joint_offsets_m, True,
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
    misfit = layouts._kabsch_rms(model.layout_offsets_m[foot][None], points[foot][None], np.ones((1, 3), bool))[0]
    assert misfit < layouts.COMPLETE_FIT_FLOOR_M
    assert (misfit > layouts.COMPLETE_FIT_FACTOR * 0.001) == (heel_off_m > 0)
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
        return _checked(lambda idx, cur: layouts._complete_by_free_point(model, st, points, cand, idx, cur), points, point_index)

    idx = right.copy()
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        assert not check(idx).any()
    assert (idx == right).all()
    idx = swapped.copy()
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        assert not check(idx, free=False).any()
    assert (idx == swapped).all()
    for _ in range(layouts.SHAPE_CONFIRM - 1):
        assert not check(idx).any()
    changed = check(idx)
    want = np.arange(m)
    assert (idx == want).all()
    assert set(np.flatnonzero(changed)) == set(foot)
    assert st.provisional[heel] == layouts.PROBATION_FRAMES


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
        fits = layouts._kabsch_rms(model.layout_offsets_m[[heel, mt5, toe]][None], points[[mt5, heel, m]][None],
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
        for _ in range(layouts.SHAPE_CONFIRM + 1):
            cand = np.ones(len(points), bool)
            cand[point_index[point_index >= 0]] = False
            cur = track_state._gather(points, point_index)
            changed |= layouts._complete_by_free_point(model, st, points, cand, point_index, cur)
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
        for k in range(layouts.SHAPE_CONFIRM + 1):
            if renumbered and k:  # the two free points (of the first frame) trade numbers
                perm = np.arange(len(pts))
                perm[free] = perm[free[::-1]]
                pts, idx = pts[perm], np.where(idx >= 0, perm[np.maximum(idx, 0)], -1)
            cand = np.ones(len(pts), bool)
            cand[idx[idx >= 0]] = False
            cand[list(hidden)] = False
            changed |= _checked(lambda i, cur: layouts._complete_lone_label(model, st, pts, cand, i, cur), pts, idx)
        if renumbered and layouts.SHAPE_CONFIRM % 2 == 1:  # (back to the first frame's numbering)
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
    assert (st.provisional[on_free_points] == layouts.PROBATION_FRAMES).all()


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
    R, t = track_state.rigid_motion(layout[[wrb, fin]], points[[wra, fin]])
    points = np.vstack([points, R @ layout[wra] + t])  # the ghost
    st.t_root_m = perf.root_position_m[0] + [0.0, 0.0, fit_off_m]
    st.R_parent_segment = Rotation.from_quat(perf.rotations_xyzw[0]).as_matrix()
    idx = np.arange(m)
    idx[[frm, wrb]] = -1
    before = idx.copy()
    changed = np.zeros(m, bool)
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        cand = np.ones(len(points), bool)
        cand[idx[idx >= 0]] = False
        cand[frm] = False  # hidden
        changed |= _checked(lambda i, cur: layouts._complete_by_free_point(model, st, points, cand, i, cur), points, idx)
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
    assert np.linalg.norm(st.pos_m[toe] - points[toe]) > layouts.SHAPE_MAX_HANDOVER_M
    st.provisional[[heel, mt5]] = layouts.PROBATION_FRAMES  # both just re-acquired
    idx = np.arange(m)
    idx[heel], idx[toe] = toe, -1
    wrong = idx.copy()
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        cur = track_state._gather(points, idx)
        assert not layouts._relabel_by_shape(model, st, points, idx, cur).any()
    assert (idx == wrong).all()
    st.pos_m[toe] = points[toe] + [0.0, 0.0, 0.02]
    for _ in range(layouts.SHAPE_CONFIRM):
        cur = track_state._gather(points, idx)
        changed = layouts._relabel_by_shape(model, st, points, idx, cur)
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
    assert model.marker_segment[heel] in layouts.BENDING_SEGMENTS
    assert set(np.flatnonzero(model.marker_segment == model.marker_segment[heel])) == {heel, toe, mt5}
    idx = np.arange(m)
    idx[mt5] = -1
    points = points.copy()
    if toes == "curled":
        mtp = points[heel] + (points[toe] - points[heel]) * 0.7  # the metatarsal heads, 7.5 cm behind the toe marker
        side = np.cross([0.0, 0.0, 1.0], points[toe] - points[heel])
        points[toe] = mtp + Rotation.from_rotvec(np.radians(90) * side / np.linalg.norm(side)).apply(points[toe] - mtp)
        fits = layouts._kabsch_rms(model.layout_offsets_m[[[heel, toe], [heel, mt5]]],
                                   np.broadcast_to(points[[heel, toe]], (2, 2, 3)), np.ones((2, 2), bool))
        assert 0.025 < fits[0] and layouts.SHAPE_MIN_RMS_M < fits[1] < layouts.SHAPE_GAIN * fits[0]
        want = idx.copy()
    else:
        idx[toe] = mt5  # the toe label on the metatarsal's point; the toe's point out of view
        want = idx.copy()
        want[toe], want[mt5] = -1, mt5
    st = tracker.new_state(model, points, t_ns(0))
    st.t_root_m, st.R_parent_segment = perf.root_position_m[0], R
    st.shape_fit[:], st.shape_checks[:] = 1.0, 10  # layouts that have been fitting
    st.provisional[toe] = layouts.PROBATION_FRAMES  # just re-acquired
    st.pos_m[[mt5, toe]] = points[[mt5, toe]]  # where they were last seen: nothing blocked
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        _checked(lambda i, cur: layouts._relabel_by_shape(model, st, points, i, cur), points, idx)
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
    model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                     perf.joint_offsets_m, True, layout_offsets_m=perf.marker_offsets_m,
                                     layout_rms_m=np.full(m, 0.001))
    fore = np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))
    pelvis = np.flatnonzero(perf.marker_segment == SEGMENTS.index("pelvis"))
    assert len(fore) >= layouts.RESEAT_MIN_LABELS and len(pelvis) >= 3
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
        return _checked(lambda idx, cur: layouts._reseat_outliers(model, st, points, cand, idx, cur), points, point_index)

    idx = right.copy()
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        assert not check(idx).any()
    assert (idx == right).all()
    idx = swapped.copy()
    for _ in range(layouts.SHAPE_CONFIRM - 1):
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
    for _ in range(layouts.SHAPE_CONFIRM + 1):
        cur = track_state._gather(moved, idx)
        assert not layouts._reseat_outliers(model, st, moved, np.ones(len(moved), bool), idx, cur).any()


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
        for _ in range(layouts.SHAPE_CONFIRM):
            cur = np.where(idx[:, None] >= 0, points[np.maximum(idx, 0)], np.nan)
            changed = layouts._relabel_by_shape(model, st, points, idx, cur)
        return idx, changed

    idx, changed = checks(provisional=0, settled=True)
    assert (idx == wrong).all() and not changed.any()
    idx, changed = checks(provisional=layouts.PROBATION_FRAMES)
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
    st.provisional[a] = layouts.PROBATION_FRAMES
    for _ in range(layouts.SHAPE_CONFIRM):
        cur = np.where(idx[:, None] >= 0, points[np.maximum(idx, 0)], np.nan)
        changed = layouts._relabel_by_shape(model, st, points, idx, cur)
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
    symmetric = layouts._kabsch_rms(moved[None], now[None], np.ones((1, 3), bool))[0]
    assert layouts.SHAPE_CLEAR_MIN_M <= symmetric < layouts.SHAPE_DISTINCT_M

    def handed(layout_rms_m: float):
        model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, off, perf.joint_offsets_m, True,
                                         layout_offsets_m=off, layout_rms_m=np.full(m, layout_rms_m))
        points = perf.recording.points_m[0]
        st = tracker.new_state(model, points, t_ns(0))
        st.shape_fit[:], st.shape_checks[:] = 1.0, 10
        idx = np.arange(m)
        idx[mt1], idx[toe] = toe, -1
        st.provisional[mt1] = layouts.PROBATION_FRAMES
        for _ in range(layouts.SHAPE_CONFIRM):
            cur = np.where(idx[:, None] >= 0, points[np.maximum(idx, 0)], np.nan)
            layouts._relabel_by_shape(model, st, points, idx, cur)
        return idx[toe] == toe and idx[mt1] == -1

    assert handed(0.002) and handed(0.004) and handed(0.005)
    assert not handed(0.007)


def test_a_relabelling_seen_again_with_a_label_more_keeps_its_vote():
    """A wrist triad's labels cycled among its points, the finger's label not yet back: the check proposes
    putting the two labels back (one handed to the finger marker). On the next check the finger's label is
    back, on the third point, and the check proposes the whole cycle: the same relabelling, seen with a
    label more, so its vote carries on and it is taken then, not a check later (a serving wrist triad's
    cycle, two players at L2)."""
    perf, model, points, st, fore = _with_layouts("r_forearm")
    m, f = len(perf.marker_names), fore[1:4]
    right = np.arange(m)
    cycled = right.copy()
    cycled[f] = right[f[[1, 2, 0]]]  # each label on the next marker's point
    partial = cycled.copy()
    partial[f[2]] = -1
    st.settled[f] = False
    st.provisional[f] = layouts.PROBATION_FRAMES  # (re-acquired: a label may be handed to a hidden marker)

    def check(point_index):
        return _checked(lambda idx, cur: layouts._relabel_by_shape(model, st, points, idx, cur), points, point_index)

    idx = partial.copy()
    assert not check(idx).any() and (idx == partial).all()
    assert layouts.SHAPE_CONFIRM == 2
    idx = cycled.copy()
    changed = check(idx)
    assert (idx == right).all() and set(np.flatnonzero(changed)) == set(f)
