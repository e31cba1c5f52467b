"""service/segment_search.py: finding the markers of a segment none or few of whose markers are labeled,
around its joint, with its child down the chain, by its own layout as a free rigid body, and (with no
skeleton) a cluster hidden whole by its layout; points a mirror segment fits as well go to neither; and where
the model's joint lies in a layout refinement reshaped (`SubjectModel.layout_joints_m`: the searches by
layout hang the layout there)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service import segment_search, track_state, tracker
from tests.tracker_fixtures import run_tracker, turned_unseen


@pytest.mark.parametrize("off_mm, found", [(18, True), (40, False)])
def test_a_lost_marker_is_found_where_three_labeled_markers_of_its_segment_put_it_despite_skin_motion(off_mm, found):
    """A forearm's three other markers labeled, its fourth unlabeled in view: its point sits 18 mm from where
    their layout puts it (skin and joint motion: a serving forearm's marker, 12-21 mm) and is found
    (SEARCH_PLACED_INLIER_M); 40 mm away, it is not theirs to place."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf, model, st, old, _, _ = turned_unseen(np.random.default_rng(5), {})
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
    assert segment_search._search_segments(model, st, points, free, labeled, cur, lost) == want


@pytest.mark.parametrize("upper_arm_deg", [0.0, 20.0])
def test_a_lost_marker_three_labeled_markers_of_its_segment_place_is_found_wherever_the_fit_left_the_joint(upper_arm_deg):
    """A forearm's three other markers labeled, its fourth unlabeled in view where they put it, and the fit
    (a serving arm, 35-45 mm RMS) holding the elbow 10 cm off: the three place it without the joint (its
    distance from the joint would rule its point out: a serving wrist marker stayed unlabeled in view for
    20 frames, two players at L2)."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf, model, st, old, _, _ = turned_unseen(np.random.default_rng(5), {})
    forearm = np.flatnonzero(perf.marker_segment == SEGMENTS.index("r_forearm"))
    lost_one, k = forearm[1], SEGMENTS.index("r_forearm")
    _, before = world_transforms(st.t_root_m, st.R_parent_segment, perf.joint_offsets_m)
    upper = SEGMENTS.index("r_upperarm")
    st.R_parent_segment[upper] = Rotation.from_euler("x", upper_arm_deg, degrees=True).as_matrix() @ st.R_parent_segment[upper]
    _, after = world_transforms(st.t_root_m, st.R_parent_segment, perf.joint_offsets_m)
    assert np.linalg.norm(after[k] - before[k]) > (0.08 if upper_arm_deg else -1.0)
    labeled = np.arange(len(old)) != lost_one
    cur = np.where(labeled[:, None], old, np.nan)
    assert segment_search._search_segments(model, st, old, ~labeled, labeled, cur, ~labeled) == {int(lost_one): int(lost_one)}


def test_a_segment_the_fit_lost_is_found_around_its_joint():
    """A forearm turned 80 degrees at the elbow while its markers went unlabeled: the fit (which had no
    word on it) still holds it where it was, its wrist 12 cm from its markers. Registered around the
    elbow, every forearm marker gets its own point, not a ghost beside it; with the forearm's points gone,
    nothing is found."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(3)
    perf, model, st, old, now, _ = turned_unseen(rng, {"r_forearm": ("y", 80)})
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    assert on_forearm.sum() >= 3 and np.linalg.norm(now - old, axis=1)[on_forearm].max() > 0.1
    labeled = ~on_forearm
    cur = np.where(labeled[:, None], now, np.nan)
    ghosts = now[on_forearm] + rng.normal(0.0, 0.04, (on_forearm.sum(), 3))
    order = rng.permutation(len(now) + len(ghosts))
    points = np.concatenate([now, ghosts])[order]
    truth = np.concatenate([np.arange(len(now)), np.full(len(ghosts), -2)])[order]
    free = np.isin(truth, np.flatnonzero(on_forearm)) | (truth == -2)

    found = segment_search._search_segments(model, st, points, free, labeled, cur, on_forearm)
    assert found == {int(i): int(np.flatnonzero(truth == i)[0]) for i in np.flatnonzero(on_forearm)}
    assert segment_search._search_segments(model, st, points, truth == -2, labeled, cur, on_forearm) == {}


def test_a_forearm_whose_upper_arm_swung_too_is_found_by_its_layout():
    """The whole arm swung while unlabeled (70 degrees at the shoulder, 60 at the elbow): the fit holds
    the elbow where it was, so no search around it can work. The forearm's markers are found by their
    layout, with the elbow at the upper arm's length from the shoulder; not with their layouts unmeasured,
    and not among points whose layout matches but that lie out of the arm's reach."""
    import dataclasses

    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(4)
    turns = {"r_upperarm": ("x", 70), "r_forearm": ("y", 60)}
    perf, model, st, old, now, turned_at = turned_unseen(rng, turns, measured_layouts=True)
    arm = np.isin(perf.marker_segment, [SEGMENTS.index(name) for name in turns])
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    assert on_forearm.sum() >= 4 and np.linalg.norm(now - old, axis=1)[on_forearm].min() > 0.1
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)
    ghosts = now[arm] + rng.normal(0.0, 0.05, (arm.sum(), 3))
    points = np.concatenate([now, ghosts])
    free = np.concatenate([arm, np.ones(len(ghosts), bool)])

    found = segment_search._search_segments(model, st, points, free, labeled, cur, arm)
    assert {i: p for i, p in found.items() if on_forearm[i]} == {int(i): int(i) for i in np.flatnonzero(on_forearm)}
    assert all(p == i for i, p in found.items())
    unmeasured = dataclasses.replace(model, layout_rms_m=None)
    assert not any(on_forearm[i] for i in segment_search._search_segments(unmeasured, st, points, free, labeled, cur, arm))
    away = turned_at(st.t_root_m + [0.0, 1.5, 0.0])  # the same arm 1.5 m to the side: out of this one's reach
    far = np.concatenate([now[~arm], away[arm]])
    far_free = np.concatenate([np.zeros((~arm).sum(), bool), np.ones(arm.sum(), bool)])
    assert segment_search._search_segments(model, st, far, far_free, labeled, cur, arm) == {}


def test_a_forearm_found_by_its_layout_is_hung_from_the_elbow_refinement_moved():
    """Refinement moved the elbow (here 6 cm: the calibration's was off, the motion placed it) and the
    forearm's offsets with it, but keeps the calibrated layout, whose origin stays where the calibration
    put the elbow. The search places the layout and asks where the model's elbow is in it
    (`SubjectModel.layout_joints_m`), so the arm swung unseen is found. (At the layout's own origin, the
    elbow lay 6 cm off the upper arm's length from the shoulder: a serving forearm whose elbow refinement
    had moved 66 mm stayed unlabeled in view for 45 frames, two players at L2.)"""
    from protocol.skeleton import SEGMENTS

    perf, model, st, now, arm, forearm = _arm_swung_unseen()
    shoulder = track_state._joints_m(model, st)[SEGMENTS.index("r_upperarm")]
    R, elbow = track_state.rigid_motion(model.marker_offsets_m[forearm], now[forearm])  # the forearm's pose now
    up_the_arm = (shoulder - elbow) / np.linalg.norm(shoulder - elbow)
    layout = model.layout_offsets_m.copy()
    layout[forearm] -= 0.06 * R.T @ up_the_arm  # the calibration's elbow, 6 cm nearer the shoulder
    calibrated = dataclasses.replace(model, layout_offsets_m=layout)
    np.testing.assert_allclose(calibrated.layout_joints_m[SEGMENTS.index("r_forearm")],
                               -0.06 * R.T @ up_the_arm, atol=1e-12)
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)

    found = segment_search._search_segments(calibrated, st, now, arm.copy(), labeled, cur, arm)
    assert {i: p for i, p in found.items() if i in forearm} == {int(i): int(i) for i in forearm}


@pytest.mark.parametrize("raised_m, skin_m, found", [(0.065, 0.004, True), (0.12, 0.0, True), (0.12, 0.004, False),
                                                     (0.25, 0.0, False)])
def test_a_forearm_found_by_its_layout_may_hang_from_a_shoulder_the_shoulder_blade_raised(raised_m, skin_m, found):
    """The arm swung unseen and the shoulder blade carried it up along itself (an arm raised to serve); the
    upper arm's markers are labeled again, the forearm's not. The fit holds the shoulder where the trunk
    puts it and the elbow where it was, so the elbow the forearm's layout places lies beyond the upper
    arm's length from that shoulder. 6.5 cm beyond, it is taken (SEARCH_BONE_TOL_M; two players at L3, a
    serving forearm unlabeled in view for 0.4 s), its markers a few millimetres off their layout; 12 cm
    beyond, only by a triangle that fits the layout tightly, alone in reach (TIGHT_BONE_TOL_M: a serving
    forearm's wrist pair and finger fitted theirs to 1 mm, 9-16 cm beyond, two players at L2); 25 cm
    beyond, it is no arm of this shoulder's."""
    from protocol.skeleton import SEGMENTS

    perf, model, st, now, arm, forearm = _arm_swung_unseen()
    shoulder = track_state._joints_m(model, st)[SEGMENTS.index("r_upperarm")]
    _, elbow = track_state.rigid_motion(model.marker_offsets_m[forearm], now[forearm])
    along = (elbow - shoulder) / np.linalg.norm(elbow - shoulder)
    points = now.copy()
    points[arm] += raised_m * along
    # skin: each forearm marker off its layout by skin_m, each its own way (every triangle misfits)
    points[forearm] += skin_m * np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-0.6, -0.6, -0.5]])
    lost = np.zeros(len(points), bool)
    lost[forearm] = True
    cur = np.where(~lost[:, None], points, np.nan)

    got = segment_search._search_segments(model, st, points, lost.copy(), ~lost, cur, lost)
    assert got == ({int(i): int(i) for i in forearm} if found else {})


def test_a_tight_triangle_beyond_the_bone_is_refused_where_its_elbow_is_nearer_the_other_shoulder():
    """A forearm's triangle fits its mirror image (the other hand's) by a turn, so one found beyond its
    bone's length (`TIGHT_BONE_TOL_M`) must place its elbow nearer its own shoulder than the other one:
    12 cm beyond the upper arm's length from the right shoulder, out to the side, the right forearm is
    found; as far across the chest, past the left shoulder, it is not."""
    from protocol.skeleton import SEGMENTS

    perf, model, st, now, arm, forearm = _arm_swung_unseen()
    pw = track_state._joints_m(model, st)
    right, left = pw[SEGMENTS.index("r_upperarm")], pw[SEGMENTS.index("l_upperarm")]
    reach = np.linalg.norm(model.joint_offsets_m[SEGMENTS.index("r_forearm")])
    _, elbow = track_state.rigid_motion(model.marker_offsets_m[forearm], now[forearm])
    across = (left - right) / np.linalg.norm(left - right)
    lost = np.zeros(len(now), bool)
    lost[forearm] = True
    for way, found in ((-across, True), (across, False)):
        points = now.copy()
        points[forearm] += right + (reach + 0.12) * way - elbow
        cur = np.where(~arm[:, None], points, np.nan)
        got = segment_search._search_segments(model, st, points, lost.copy(), ~arm, cur, lost)
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
    model = track_state.SubjectModel("P", ("a", "b", "c", "d"), np.full(4, 6), offsets, np.zeros((14, 3)), True,
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
    perf, model, st, _, now, _ = turned_unseen(np.random.default_rng(4), turns, measured_layouts=True)
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
    shoulder = track_state._joints_m(model, st)[SEGMENTS.index("r_upperarm")]
    hidden = forearm[np.argmin(np.linalg.norm(now[forearm] - shoulder, axis=1))]  # the one nearest the elbow
    shown = np.setdiff1d(forearm, [hidden])
    labeled = ~arm
    cur = np.where(labeled[:, None], now, np.nan)
    points = now.copy()
    points[hidden] = [9.0, 9.0, 9.0]  # out of reach: hidden
    free = arm.copy()

    found = segment_search._search_segments(model, st, points, free, labeled, cur, arm)
    assert {i: p for i, p in found.items() if i in forearm} == {int(i): int(i) for i in shown}
    # the same three turned 40 degrees about the shoulder: their elbow at the bone's length too
    turn = Rotation.from_rotvec([0.0, 0.0, np.radians(40)]).as_matrix()
    twin = (now[shown] - shoulder) @ turn.T + shoulder
    both = np.concatenate([points, twin])
    found = segment_search._search_segments(model, st, both, np.concatenate([free, np.ones(3, bool)]), labeled, cur, arm)
    assert not any(i in forearm for i in found)
    trunk_too = labeled & (perf.marker_segment != SEGMENTS.index("torso"))
    found = segment_search._search_segments(model, st, points, free, trunk_too, np.where(trunk_too[:, None], now, np.nan), arm)
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

    found = segment_search._search_segments(model, st, points, arm.copy(), labeled, cur, arm)
    assert {i: p for i, p in found.items() if i in forearm} == {int(i): int(i) for i in forearm}


def test_placements_agree_unless_a_marker_or_a_point_is_given_twice():
    assert segment_search._agrees({1: 10, 2: 20}, {2: 20, 3: 30})
    assert not segment_search._agrees({1: 10, 2: 20}, {2: 30})  # marker 2 on two points
    assert not segment_search._agrees({1: 10, 2: 20}, {3: 20})  # point 20 for two markers
    merged, support = segment_search._consensus({1: 10, 2: 20, 3: 30}, [(3, 0.001, {1: 10, 2: 20, 3: 30}),
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
    perf, model, st, old, now, _ = turned_unseen(rng, turns)  # layouts unmeasured: no layout search
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

    found = segment_search._search_segments(model, st, points, free, labeled, cur, arm)
    expected = {i for i in np.flatnonzero(arm) if in_view[i]}
    assert set(found) == expected and all(truth[p] == i for i, p in found.items())
    upper_only = free & ~np.isin(truth, np.flatnonzero(on_forearm))
    assert segment_search._search_segments(model, st, points, upper_only, labeled, cur, arm) == {}
    # the shoulder slid 4.5 cm against the trunk markers that hold its joint (an arm raised overhead):
    # beyond a search around the joint, not beyond the arm's
    slid = points.copy()
    slid[np.isin(truth, np.flatnonzero(arm))] += [0.0, 0.0, 0.045]
    found = segment_search._search_segments(model, st, slid, free, labeled, cur, arm)
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
    perf, model, st, old, now, _ = turned_unseen(rng, turns)
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

    found = segment_search._search_segments(model, st, points, free, labeled, cur, lost)
    assert set(found) == set(np.flatnonzero(lost)) and all(truth[p] == i for i, p in found.items())
    without_foot = free & ~np.isin(truth, np.flatnonzero(on_foot))
    ankle = names.index("RANK")
    assert segment_search._search_segments(model, st, points, without_foot, labeled, cur, lost) == {ankle: ankle}


def test_a_thigh_held_by_one_marker_is_found_with_its_knee_marker_around_the_hip():
    """A thigh turned 35 degrees at the hip while its knee marker went unlabeled: the fit, held by the thigh
    marker alone, keeps the knee where it was. The knee marker's point is the one at its distances from the
    hip and from the thigh marker; a ghost as far from the hip, but not from the thigh marker, is not it;
    and with a second point at both distances (turned about the hip-thigh-marker axis) neither is taken."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(5)
    perf, model, st, old, now, _ = turned_unseen(rng, {"r_thigh": ("x", 35)})
    names = list(perf.marker_names)
    knee, thigh = names.index("RKNE"), names.index("RTHI")
    assert np.linalg.norm(now[knee] - old[knee]) > 0.1
    lost = np.zeros(len(now), bool)
    lost[knee] = True
    cur = np.where(~lost[:, None], now, np.nan)
    hip = track_state._joints_m(model, st)[SEGMENTS.index("r_thigh")]
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
        return segment_search._search_segments(model, st, points, free, ~lost, cur, lost)

    assert search(ghost) == {knee: knee}
    assert search(ghost, twin) == {}


def test_a_lost_marker_is_found_where_its_segments_labeled_markers_and_joint_put_it():
    """A forearm marker lost while the others stay labeled (its partners place it far off: its last labeled
    point was another marker's): the elbow and two labeled markers fix the forearm, and the one point where
    they put it is it; not a ghost a few centimetres from there, however well it matches its distance from
    the elbow."""
    from protocol.skeleton import SEGMENTS

    rng = np.random.default_rng(3)
    perf, model, st, old, now, _ = turned_unseen(rng, {})
    names = list(perf.marker_names)
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    i = names.index("RWRA")
    lost = np.zeros(len(now), bool)
    lost[i] = True
    labeled = ~lost
    cur = np.where(labeled[:, None], now, np.nan)
    elbow = track_state._joints_m(model, st)[SEGMENTS.index("r_forearm")]
    r = now[i] - elbow
    ghost = elbow + Rotation.from_rotvec(0.2 * np.cross(r, [0.0, 0.0, 1.0]) / np.linalg.norm(r)).apply(r)  # as far from the elbow
    assert 0.03 < np.linalg.norm(ghost - now[i]) < 0.06 and on_forearm.sum() >= 3
    points = np.concatenate([now, ghost[None]])
    free = np.zeros(len(points), bool)
    free[[i, len(now)]] = True

    assert segment_search._search_segments(model, st, points, free, labeled, cur, lost) == {i: i}
    free[i] = False
    assert segment_search._search_segments(model, st, points, free, labeled, cur, lost) == {}


def test_a_forearm_swung_out_of_reach_of_where_the_fit_left_its_elbow_is_found_by_its_layout():
    """The arm swung far while its forearm was unlabeled (a serve), and the fit still holds the elbow where
    it was: not one free point lies within the forearm's reach of that joint, so the search around it has
    nothing to try. The layout search must still run (it did not: a tennis player's serving forearm stayed
    unlabeled for 0.7 s, in view)."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    rng = np.random.default_rng(4)
    turns = {"r_upperarm": ("x", 150), "r_forearm": ("y", 60)}
    perf, model, st, old, now, _ = turned_unseen(rng, turns, measured_layouts=True)
    on_forearm = perf.marker_segment == SEGMENTS.index("r_forearm")
    elbow = world_transforms(st.t_root_m, st.R_parent_segment, model.joint_offsets_m)[1][SEGMENTS.index("r_forearm")]
    reach = np.linalg.norm(model.marker_offsets_m[on_forearm], axis=1).max() + segment_search.SEARCH_JOINT_TOL_M
    assert np.linalg.norm(now[on_forearm] - elbow, axis=1).min() > reach
    labeled = ~on_forearm
    cur = np.where(labeled[:, None], now, np.nan)

    found = segment_search._search_segments(model, st, now, on_forearm, labeled, cur, on_forearm)
    assert found == {int(i): int(i) for i in np.flatnonzero(on_forearm)}
    # the layout is the calibrated one (`layout_offsets_m`), not the offsets refinements on the engine's own
    # labels moved: one marker's refined 3 cm off (labeled on a neighbour's point while it was refined)
    # must not leave the forearm unfound (cmu/85_12 at L3: a foot stayed unlabeled in view for 0.5 s)
    i = int(np.flatnonzero(on_forearm)[0])
    moved = model.marker_offsets_m.copy()
    moved[i] += [0.03, 0.0, 0.0]
    refined = dataclasses.replace(model, marker_offsets_m=moved)
    found = segment_search._search_segments(refined, st, now, on_forearm, labeled, cur, on_forearm)
    assert found == {int(i): int(i) for i in np.flatnonzero(on_forearm)}


def _mirrored_forearms():
    """A model of two forearms of four markers each (segments 5 and 7), the right the left mirrored; a turn
    R and an elbow position for the right: (model, offsets, R, elbow)."""
    seg = np.array([5, 5, 5, 5, 7, 7, 7, 7])
    left = np.array([[0.0, 0.0, -0.25], [0.03, 0.0, -0.26], [-0.03, 0.0, -0.26], [0.0, 0.02, -0.33]])
    off = np.vstack([left, left * [1.0, -1.0, 1.0]])
    model = track_state.SubjectModel("P", tuple("abcdefgh"), seg, off, np.zeros((14, 3)), True)
    return model, off, Rotation.from_rotvec([0.3, -0.5, 1.2]).as_matrix(), np.array([0.2, 0.4, 1.3])


def test_points_that_fit_the_mirror_segment_as_well_are_not_given_to_either():
    """Left and right forearms carry mirror-image marker layouts, and three markers of one fit three of
    the other's by a rotation. Points the left forearm's search took (three of the right hand's) stay
    unassigned while the right forearm, searched for too, fits them as well with its elbow about as near;
    they are the left's when the right is not searched for, or when its elbow is far from them."""
    model, off, R, elbow_r = _mirrored_forearms()
    points = off[4:7] @ R.T + elbow_r  # three of the right forearm's markers
    pw = np.zeros((14, 3))  # both elbows stale, a few centimetres apart
    pw[7] = elbow_r + [0.0, 0.0, 0.03]
    pw[5] = pw[7] + [0.0, 0.02, 0.0]
    left_gets = {0: 0, 1: 2, 2: 1}  # mirrored, the second and third markers trade places
    assert segment_search._joint_residual(off[[0, 2, 1]], pw[5], points)[0] < 0.002
    assert segment_search._rival_fits(model, pw, points, left_gets, 5, np.array([5, 7]))
    assert not segment_search._rival_fits(model, pw, points, left_gets, 5, np.array([5]))
    pw[7] = elbow_r + [0.0, 0.3, 0.0]  # the right elbow held 30 cm away: it cannot be the right forearm
    assert not segment_search._rival_fits(model, pw, points, left_gets, 5, np.array([5, 7]))


def test_two_points_found_beside_a_labeled_marker_are_judged_with_it_against_a_rival_segment():
    """Two points alone leave a segment free to turn about them, its joint anywhere on a circle: the right
    forearm's wrist pair, found around the elbow beside its labeled forearm marker, fitted the other
    forearm's pair as well, and that elbow was "about as near" as the one the pair alone placed, 6 cm off
    (two players at L2: the serving hand stayed unlabeled 20 frames). With the labeled marker the right
    forearm's elbow is where the fit holds it, 1 cm off, and the left's, 7 cm away, is no rival; where the
    left elbow holds the points as well as the right does, it still is."""
    model, off, R, elbow_r = _mirrored_forearms()
    right = off[4:8] @ R.T + elbow_r
    points = right[[1, 2]]  # the pair found; marker 4 (the first of the right's) labeled
    cur = np.full((8, 3), np.nan)
    cur[4] = right[0]
    pw = np.zeros((14, 3))
    pw[7] = elbow_r + [0.0, 0.0, 0.01]
    pw[5] = elbow_r + [0.0, 0.05, 0.05]
    both = np.array([5, 7])
    assert segment_search._rival_fits(model, pw, points, {5: 0, 6: 1}, 7, both)  # the pair alone
    assert not segment_search._rival_fits(model, pw, points, {5: 0, 6: 1}, 7, both, np.array([4]), cur)
    pw[5] = elbow_r
    assert segment_search._rival_fits(model, pw, points, {5: 0, 6: 1}, 7, both, np.array([4]), cur)


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


def test_agreeing_pairs_place_three_markers_only_as_one_unrivalled_set():
    pairs = [(2, 0.006, {0: 10, 1: 11}), (2, 0.007, {0: 10, 2: 12}), (2, 0.01, {1: 11, 2: 12})]
    assert segment_search._agreeing_pairs(list(pairs)) == {0: 10, 1: 11, 2: 12}
    assert segment_search._agreeing_pairs(pairs[:2]) is None  # markers 1 and 2 never placed together
    rival = [(2, 0.006, {0: 20, 1: 21}), (2, 0.007, {0: 20, 2: 22}), (2, 0.01, {1: 21, 2: 22})]
    assert segment_search._agreeing_pairs(pairs + rival) is None
    assert segment_search._agreeing_pairs(pairs + rival[:2]) == {0: 10, 1: 11, 2: 12}


@pytest.mark.parametrize("off_mm", [0, 25])
def test_a_lost_forearm_one_of_whose_markers_left_its_layout_is_found_by_its_agreeing_pairs(off_mm):
    """A forearm turned 80 degrees at the elbow while unlabeled comes back with three of its four markers
    in view, one moved 25 mm off the layout (on its sphere about the elbow: skin, or a hand flexed at the
    wrist): the three no longer fit the layout at once (they were not found before `_agreeing_pairs`),
    but every two of them do, alike, and they are found."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    rng = np.random.default_rng(3)
    perf, model, st, old, now, _ = turned_unseen(rng, {"r_forearm": ("y", 80)})
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
    found = segment_search._search_segments(model, st, points, free, labeled, cur, ~labeled & (perf.marker_segment == k))
    assert found == {int(i): int(i) for i in forearm if i != hidden}


def test_a_head_found_whole_with_left_and_right_swapped_is_refused_by_its_joint():
    """`_mirrored`: a head band's four markers keep their distances under a left-right swap; with the neck
    joint where the trunk holds it as a fifth point, the true assignment fits (the identity, to skin noise)
    and the swap does not: refused. The true one is not, nor a triangle's (three markers) true assignment."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf, model, st, old, _, _ = turned_unseen(np.random.default_rng(3), {})
    head = SEGMENTS.index("head")
    _, pw = world_transforms(st.t_root_m, st.R_parent_segment, perf.joint_offsets_m)
    names = [n.split(":")[-1] for n in perf.marker_names]
    band = {n: names.index(n) for n in ("LFHD", "RFHD", "LBHD", "RBHD")}
    assert all(perf.marker_segment[i] == head for i in band.values())
    points = old + np.random.default_rng(0).normal(0.0, 0.002, old.shape)
    true = {i: i for i in band.values()}
    swapped = {band["LFHD"]: band["RFHD"], band["RFHD"]: band["LFHD"], band["LBHD"]: band["RBHD"],
               band["RBHD"]: band["LBHD"]}
    assert not segment_search._mirrored(model, true, points, pw[head])
    assert segment_search._mirrored(model, swapped, points, pw[head])
    three = {i: i for i in list(band.values())[:3]}
    assert not segment_search._mirrored(model, three, points, pw[head])
