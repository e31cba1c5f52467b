"""A segment's calibrated marker layout, and the labels it corrects (`tracker.step`, 4.).

Markers of one segment keep their offsets in it, as first calibrated (`SubjectModel.layout_offsets_m`,
and how well each kept it, `layout_rms_m`). Labels permuted within a segment (a wrist triad after a fast
pass, tracked permuted since, which the partner statistics absorb), or a re-acquired label on the point of
another marker of its segment, no longer fit it, and are put back where it says (`_relabel_by_shape`);
two labels of a segment whose other markers hide, swapped, by a free point and the segment's joint
(`_complete_by_free_point`); a segment's one label on another of its markers' points by two free points
and the joint (`_complete_lone_label`); one clear outlier among four or more labels where the others put
it (`_reseat_outliers`). A layout is trusted only once its labels have fitted it on enough checks
(`learn_layout_trust`, `_count_layout_fits`).

Every check changes the frame's labels in place, after they were published; the state tracks the new
labels from the next frame on.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

from protocol.skeleton import N_SEGMENTS, SEGMENTS
from service import kernels
from service.partners import Z_SUSPECT, _partners_object, distance_misfit
from service.segment_search import SEARCH_INLIER_M
from service.track_state import (
    SHAPE_LAYOUT_TOL_M,
    SubjectModel,
    TrackState,
    _gather,
    _kabsch_rms,
    _joints_m,
    _norm,
    rigid_motion,
)

SHAPE_EVERY_FRAMES = 4  # segment layouts are checked on every this many frames
SHAPE_MIN_RMS_M = 0.012  # a segment whose labels fit its calibrated marker layout this well is not re-checked ...
SHAPE_FIT_FACTOR = 4.0  # ... nor one fitting it within this times its markers' own layout residual ...
SHAPE_FIT_FLOOR_M = 0.004  # ... (not under this)
SHAPE_GAIN = 0.5  # labels of a segment are permuted when that fits its layout under this times as badly ...
SHAPE_GOOD_RMS_M = 0.015  # ... and as well as true labels do [m] RMS
SHAPE_DISTINCT_M = 0.03  # ... and only relabellings that move the layout's own markers this far [m] RMS ...
# ... or, on clear evidence, one that moves them at least SHAPE_CLEAR_MIN_M: a segment of SHAPE_CLEAR_MIN_LABELS
# labels or more whose layout held within SHAPE_CLEAR_LAYOUT_M in calibration, its labels misfitting by
# SHAPE_CLEAR_SHARE of that move or more, the relabelled ones fitting within SHAPE_CLEAR_FIT_M (or twice the
# layout's residual), and no other relabelling within twice that + 1 mm
SHAPE_CLEAR_MIN_M = 0.006
SHAPE_CLEAR_MIN_LABELS = 3
SHAPE_CLEAR_LAYOUT_M = 0.0025
# ... or within SHAPE_CLEAR_HANDOVER_LAYOUT_M for a relabelling that hands a label to an unlabeled marker (a
# toe label on the fifth metatarsal's point of a foot calibrated to 4 mm: 12-15 mm misfit, 4 mm handed over,
# 85_02 at L2, for 1.5 s; a wrist label on the other wrist marker's point of a forearm calibrated to 4.7 mm:
# 20 mm misfit, 5 mm handed over, 135_02 at L3, for 4 s; among labeled markers alone, a wrist pair 6-11 mm
# apart in a 4 mm layout was swapped wrongly, 135_02 at L3. Dev suite, 18 realizations: at 4.5 mm L3 97.925 %,
# at 6 or 8 mm 97.932 %, six runs moved.)
SHAPE_CLEAR_HANDOVER_LAYOUT_M = 0.006
SHAPE_CLEAR_SHARE = 0.6
SHAPE_CLEAR_FIT_M = 0.002
#: ... but a label still on probation (re-acquired, PROBATION_FRAMES), handed to an unlabeled marker of its
#: segment, is suspect anyway: that relabelling counts as clear when it fits the layout as right labels do on
#: a check (`_fit_tolerance`), and the labels misfit it by this much. A serving wrist label re-acquired on its
#: neighbour's point: handed back, it fitted the forearm's layout at 2.3-5.9 mm against the labels' 15-19 mm
#: (the finger marker, which the layout carries, off its seed place with the hand's bend). Over twice the
#: 1.1 mm calibration residual, it was refused for 23 frames, until it fitted under 2 mm (tennis at L2, seed
#: 6; now taken 10 frames sooner, where the joint agreed). With labels misfitting by 8-9 mm, a wrist handover
#: that moves the layout 10 mm RMS was wrong (HDM05 at L3). (Dev suite, 18 realizations: 20 runs moved, 17
#: up; L2 99.318 -> 99.322 %, L3 98.585 -> 98.588 %; two players L2 99.452 -> 99.465 %, the tennis player's
#: precision at L2 99.879 -> 99.885 %. Without the misfit's floor the HDM05 run lost 0.5, on every segment or
#: on the forearms alone, where 85_12's five runs up went too.)
REACQUIRED_HANDOVER_MISFIT_M = SHAPE_MIN_RMS_M
#: ... or, on a forearm (TWISTING_SEGMENTS), fits it under this share of the labels' misfit, where a
#: layout that held tightly in calibration makes a check's tolerance 4 mm. The wrist bends in a serve, and
#: the rigid layout carries the finger marker: a serving wrist label re-acquired on its neighbour's point,
#: handed back, fitted at 9.1, 8.2, 7.4, 5.8, 4.6 mm on successive checks against the labels' 12-16 mm (0.9
#: mm residual), and was taken at 2.2 and 1.5 mm, 12 frames later than now (tennis at L2, seed 10). (Dev
#: suite, 18 realizations: 9 runs moved, 7 up; L2 99.333 -> 99.334 %, L3 98.637 -> 98.641 %, the tennis
#: player's L3 +0.014; KneeltoProne, squat and 03_rolling unchanged. On every segment, 03_rolling at L3 fell
#: 64.45 -> 63.96 %, 7 of its 24 runs down, by up to 3.7 points. At 0.6 the tennis runs were those at 0.4:
#: SHAPE_GAIN governs above 0.5.)
REACQUIRED_HANDOVER_SHARE = 0.4
#: A label tracked all along is handed to an unlabeled marker of its segment (which `relabel_candidates`
#: blocks: it is not suspected of sitting on another's point) where the evidence is overwhelming: a segment
#: of SHAPE_CLEAR_MIN_LABELS labels or more misfitting its layout by this much, and fitting it with the label
#: handed over as tightly as right labels do (its check's tolerance). A wrist label that came back on the
#: forearm marker's point stayed there 2.3 s, 40 mm off the layout, 3 mm handed over (85_12 at L2)
SHAPE_SETTLED_HANDOVER_MISFIT_M = 0.025
# `_reseat_outliers`: a segment with this many labels or more whose labels misfit its layout by this times
# the layout's residual (as `_complete_by_free_point` counts it) ...
RESEAT_MIN_LABELS = 4
RESEAT_MISFIT_FACTOR = 3.0
RESEAT_SHARE = 0.35  # ... and fit it within this share of that misfit (or the residual) with one label left out ...
RESEAT_RADIUS_M = 0.02  # ... has that label moved to a point this close to where the others put it
COMPLETE_FIT_FACTOR = 3.0  # (`_complete_by_free_point`) a labeling whose three points fit the layout within this times its markers' residual ...
COMPLETE_FIT_FLOOR_M = 0.005  # ... or this [m] RMS, whichever is more ...
COMPLETE_JOINT_RMS_M = 0.02  # ... and whose markers and joint fit the offsets this well [m] RMS ...
COMPLETE_PAIR_MISFIT_M = 0.01  # ... is taken, rivalled or not, when the labeled pair's distance misfits the layout's by this much [m] ...
COMPLETE_WRONG_PAIR_JOINT_M = 0.1  # ... and the joint fits within this [m] RMS (the pair is wrong: the joint only guards)
SHAPE_CONFIRM = 2  # ... when the same relabelling wins this many checks running
#: A label carried on by tracking alone since its segment's layout last confirmed it (every layout marker of
#: the segment labeled, SETTLED_MIN_LABELS or more, fitting) is settled: no other marker's point was in its
#: gate since, nor did any step but tracking move it, so nothing could have permuted it, and the layout
#: check leaves it where it is. A forearm twisting under pronation moves its wrist markers against its
#: proximal marker by a centimetre: the true labels misfit the layout by 10 mm where their swap fitted it
#: by 3, and the check swapped two wrist labels tracked apart at 0.1 m/s for 5 s (135_02 at L3, four
#: realizations in 18). (Dev suite, 18 realizations: L3 97.977 -> 98.025 %, L2 99.219 -> 99.225 %, no run
#: lower; settling on any fit of its labels instead held permutations the fit could not see: a wrist label
#: re-acquired on its neighbour's point passes a three-marker forearm's check, 97.967 %. Counting a ghost
#: in the gate as an event too left fewer labels settled at L3: 97.994 %.) A tracked step longer than
#: SLIDE_SHARE of the way to the nearest other label is an event too (without it, 98.021 %: a serving arm's
#: labels slid one marker down the chain with no rival point in any gate, and a two-player run lost 0.6).
SETTLED_MIN_LABELS = 3
SLIDE_SHARE = 0.5
#: (`_mirror_by_joint`) a relabelling the layout cannot tell from the identity (three markers and their mirror
#: image) is taken when, with the segment's joint as a fourth point, it fits under JOINT_GAIN times the
#: identity, which misfits by JOINT_MIN_MISFIT_M or more. (Dev suite: at 0.5, L2 99.215 -> 99.193 %, HDM05 lost up
#: to 0.7 points on four runs; at 0.3, L2 99.227 %, L3 97.630 -> 97.646 %, 91 of 96 runs identical; seeds 6-11: L3
#: 97.361 -> 97.371 %.)
JOINT_GAIN = 0.3
JOINT_MIN_MISFIT_M = 0.015
#: Segments that twist along their length: a forearm carries the wrist and hand markers, which pronation
#: turns about the ulna against its proximal marker, so its layout, rigid in a seed that did not show it,
#: misfits its true labels by ~10 mm, and the wrist pair swapped fits it to 3 mm (the pair is near-mirror
#: symmetric about the forearm's axis). On these a relabelling the layout barely tells (taken on clear
#: evidence) must not fit the joint worse than the labels do (`_relabel_by_shape`). (Dev suite, 18
#: realizations: L2 99.225 -> 99.239 %, L3 98.035 -> 98.056 %, 11 runs up, one down by 0.09; five 135_02 runs
#: at L3 had the right wrist labels swapped for 1-2.5 s. On every segment: L3 98.028 %, a head band's
#: near-square layout, which its joint barely tells, stayed permuted on 85_12, -3.3 points.)
TWISTING_SEGMENTS = (SEGMENTS.index("l_forearm"), SEGMENTS.index("r_forearm"))
#: ... unless the relabelling fits under this share of the labels' misfit: the joint is where the latest fit
#: puts it, and the fit follows the labels, so a wrong label pulls the joint its way (a serving wrist label
#: re-acquired on its neighbour's point, the forearm rolled to fit it: the handover back fitted the layout
#: to 0.4-1.4 mm, the labels 15-16 mm, and the joint refused it for 30 frames, two players at L2, seed 2).
#: Pronation's swap fits at 0.17 of the labels' misfit in a test's 135 degree turn, 0.3 on 135_02. (Dev
#: suite, 18 realizations: 2 runs moved, both up: two players L2 99.443 -> 99.452 %, the tennis player L3
#: 98.374 -> 98.386 %; at 0.2 HDM05 lost 0.06 on a run too, and at 0.4 135_02 L3 fell 99.17 -> 99.07 %.)
TWIST_CLEAR_SHARE = 0.1
#: Segments that bend at their far end: a foot's toe marker sits on the toes, which bend at the metatarsal
#: heads (kneeling, on tiptoe), and the rigid layout does not follow them: 135_02's right toe marker came
#: 5.5 cm nearer the heel for seconds: heel and toe labels misfit the layout by 28 mm RMS, and as heel
#: and fifth metatarsal they fit it at 12 mm. Handing the toe label's point to the metatarsal
#: then fit "better" than the true labels and was taken, for 1-1.7 s each time. On these a relabelling that
#: hands a label to an unlabeled marker must leave the labels fitting the layout as right labels do (the
#: tolerance a check counts as fitting; `_relabel_by_shape`). (Dev suite, 18 realizations: 135_02 at L2
#: 99.70 -> 99.79 %, precision 99.87 -> 99.93 %; L2 99.294 -> 99.304 %, L3 98.351 -> 98.353 %, 11 runs up,
#: 3 down by 0.15 points or less. On every segment, L3 fell to 98.341 %: a tennis wrist's right handover
#: fits its layout at 10-15 mm; on every segment but the forearms, where the layout held within 2.5 mm, a
#: waist label handed over at 11.7 mm was the right one, 85_12 at L3.)
BENDING_SEGMENTS = (SEGMENTS.index("l_foot"), SEGMENTS.index("r_foot"))
SHAPE_FIT_ALPHA = SHAPE_EVERY_FRAMES / 200  # the share of checks (over ~200 frames) on which a segment's labels fit its layout, a running mean ...
SHAPE_TRUSTED_SHARE = 0.3  # ... at least this, over more than SHAPE_MIN_CHECKS checks, for its layout to be trusted
SHAPE_MIN_CHECKS = 5
SHAPE_MAX_JUMP_M = 0.3  # ... and only relabellings that move no label farther than this (heel to toe: ~25 cm) ...
SHAPE_MAX_HANDOVER_M = 0.2  # ... nor hand a label to an unlabeled marker farther than this from where it was
SHAPE_MIN_LABELED = 2  # segments with this many labeled markers are checked (two: their distance, against a spare marker's)
SHAPE_ALL_MAPS = 5  # segments with up to this many labels try every permutation of them, larger ones every swap
PROBATION_FRAMES = 60  # frames a re-acquired label is re-checked against the partners' long-run distances


def _layout_fits(model: SubjectModel, cur: np.ndarray, sel: np.ndarray, ks: np.ndarray):
    """Segments ks's markers `sel` (M,) (all on a segment) registered onto their layout in one batch:
    (members, sorted by segment; the index in ks of each one's segment; how many each segment has; each
    segment's RMS misfit [m]; each segment's markers' own layout residual, RMS [m])."""
    seg = model.marker_segment
    wanted = np.zeros(N_SEGMENTS, bool)
    wanted[ks] = True
    members = np.flatnonzero(sel & wanted[seg])
    members = members[np.argsort(seg[members], kind="stable")]
    row = np.searchsorted(ks, seg[members])
    return (members, row) + _registered_rows(model, members, cur[members], row, len(ks))


def _registered_rows(model: SubjectModel, members: np.ndarray, at_m: np.ndarray, row: np.ndarray, n_rows: int):
    """Markers `members` seen at `at_m`, grouped in rows (`row`, ascending), each row registered onto their
    layout: (how many markers each row has, its RMS misfit [m], its markers' own layout residual, RMS
    [m]). The rows are padded rows of one array, built with array operations: a list of per-row lookups
    cost more than the registration itself."""
    n_lab = np.bincount(row, minlength=n_rows)
    col = np.arange(len(members)) - np.concatenate([[0], np.cumsum(n_lab)[:-1]])[row]
    width = int(n_lab.max())
    A = np.zeros((n_rows, width, 3))
    B = np.zeros((n_rows, width, 3))
    w = np.zeros((n_rows, width), bool)
    A[row, col], B[row, col], w[row, col] = model.layout_offsets_m[members], at_m, True
    typical = np.sqrt(np.bincount(row, model.layout_rms_m[members] ** 2, minlength=n_rows) / n_lab)
    return n_lab, _kabsch_rms(A, B, w), typical


def _fit_tolerance(n_lab: np.ndarray, typical: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(whether a relabelling of each segment could be taken on clear evidence, the RMS [m] within which
    its labels fit its layout). A segment fits when its labels sit about as well as they did in
    calibration: a few times its markers' own layout residual (1-2 mm on a foot), and never worse than
    SHAPE_MIN_RMS_M. A fixed 12 mm let a toe label on the fifth metatarsal's point pass (10 mm, 85_12 at
    L2) for 1.6 s. (Only where a relabelling could then be taken on clear evidence: checking the others
    costs time.)"""
    can_clear = (n_lab >= SHAPE_CLEAR_MIN_LABELS) & (typical <= SHAPE_CLEAR_HANDOVER_LAYOUT_M)
    tol = np.where(can_clear, np.minimum(SHAPE_MIN_RMS_M, np.maximum(SHAPE_FIT_FLOOR_M, SHAPE_FIT_FACTOR * typical)), SHAPE_MIN_RMS_M)
    return can_clear, tol


def _layout_slots(model: SubjectModel, st: TrackState) -> np.ndarray | None:
    """(M,) the markers the layout checks judge: ever seen, and their calibrated layout held within
    SHAPE_LAYOUT_TOL_M (NaN compares False); None if the model has no measured layout."""
    if model.layout_rms_m is None or len(model.layout_rms_m) != model.n_markers or model.layout_offsets_m is None:
        return None
    return st.ever_seen & (model.marker_segment >= 0) & (model.layout_rms_m < SHAPE_LAYOUT_TOL_M)


def _trusted_layouts(st: TrackState) -> np.ndarray:
    """(N_SEGMENTS,) segments whose labels fitted their layout on enough checks for it to be trusted."""
    return (st.shape_fit >= SHAPE_TRUSTED_SHARE) & (st.shape_checks > SHAPE_MIN_CHECKS)


def _layout_tolerance(model: SubjectModel, markers: np.ndarray) -> float:
    """[m] RMS within which these markers fit their layout when labeled right (`_tolerance_of`)."""
    return float(_tolerance_of(np.sqrt(np.mean(model.layout_rms_m[markers] ** 2))))


def _tolerance_of(typical):
    """COMPLETE_FIT_FACTOR times a calibration residual `typical` [m] (RMS), at least SHAPE_CLEAR_FIT_M."""
    return np.maximum(SHAPE_CLEAR_FIT_M, COMPLETE_FIT_FACTOR * typical)


def _labelings_fit(model: SubjectModel, slot: np.ndarray, maps: np.ndarray, joint_m: np.ndarray,
                   pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of P point triples `pts` (P, 3, 3) under each of C labelings `maps` (C, 3) of a segment's
    `slot` markers: (C, P) RMS of the points registered onto the calibrated layout, and of the points and
    the segment's joint `joint_m` registered onto the marker offsets and the segment's origin."""
    C, P = len(maps), len(pts)
    B = np.empty((P, 4, 3))
    B[:, 0], B[:, 1:] = joint_m, pts
    B = np.broadcast_to(B[None], (C, P, 4, 3)).reshape(-1, 4, 3)  # labelling-major
    rms3 = _kabsch_rms(np.repeat(model.layout_offsets_m[slot[maps]], P, axis=0), B[:, 1:], np.ones((C * P, 3), bool))
    A = np.concatenate([np.zeros((C * P, 1, 3)), np.repeat(model.marker_offsets_m[slot[maps]], P, axis=0)], axis=1)
    rms4 = _kabsch_rms(A, B, np.ones((C * P, 4), bool))
    return rms3.reshape(C, P), rms4.reshape(C, P)


def _segment_counts(model: SubjectModel, st: TrackState, point_index: np.ndarray):
    """The layout checks' view of the labels: (slots, labeled, n_lab, n_spare), with each segment's
    labeled and unlabeled layout markers counted (N_SEGMENTS,), or None if no layout was measured."""
    slots = _layout_slots(model, st)
    if slots is None:
        return None
    labeled = point_index >= 0
    seg = model.marker_segment
    n_lab = np.bincount(seg[labeled & slots], minlength=N_SEGMENTS)
    n_spare = np.bincount(seg[~labeled & slots], minlength=N_SEGMENTS)
    return slots, labeled, n_lab, n_spare


def _complete_by_free_point(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                            point_index: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Put back two labels of a segment permuted while its other markers hide, using a free point and the
    segment's joint. In place; returns the markers whose point changed.

    Two labels alone match one distance, which a swap keeps: a foot's toe and fifth metatarsal labels
    swapped as the foot came back (the heel hidden) stayed swapped for 13 s, and the heel's point, in
    view, stayed unlabeled, its prediction carried by the swapped pair (HDM05 at L3). For each segment
    with two labeled markers and unlabeled ones, the two points, each free point within the segment's
    reach and the joint where the latest fit puts it are registered onto the segment's markers under
    every way of labeling the points from them. A labeling counts if its three points fit the calibrated
    layout within COMPLETE_FIT_FACTOR times its markers' calibration residual (at least
    COMPLETE_FIT_FLOOR_M: skin and joint motion the seed did not show); the one whose joint then
    fits best is taken if it permutes the two labels, fits within COMPLETE_JOINT_RMS_M, and another
    labeling of the two points fits the layout too but puts the joint clearly farther off: the ambiguity
    the joint resolves (heel, toe and fifth metatarsal make a near-isosceles triangle; its mirror image
    fits it as well). Where no other labeling fits the layout, the free point is as likely a stray one
    completing a wrong triangle (a torso's markers at L2): left alone, unless the two labels themselves
    misfit the layout's distance between them by COMPLETE_PAIR_MISFIT_M (a tennis wrist marker
    re-acquired on its neighbour's point after the serve, 29 mm off, stayed there 40 frames with its own
    point free beside it). The pair is wrong then, rivalled or not: the joint still tells rivals apart,
    but otherwise only guards against a far-fetched triangle (COMPLETE_WRONG_PAIR_JOINT_M). A skeleton
    fitting at 20-30 mm put a tennis player's ankle joint 5-9 cm from a heel label on the toe's point,
    which stayed there 2.3 s; once the floor let a wrong labeling, its joint 12 cm off, fit a forearm's
    layout too, wrist labels on the finger's and forearm's points (joint 44 mm off) stayed there 5 s. But
    a pair can misfit its layout by the skin's doing (a forearm under pronation, 10-15 mm): where the pair
    as labeled, with any free point, fits the joint within COMPLETE_JOINT_RMS_M and by SHAPE_CLEAR_MIN_M
    better than the relabelling, it is kept (a forearm's right wrist labels so swapped onto each other's
    points stayed swapped 3 s, 135_02 at L3; dev suite, 18 realizations: 3 L3 runs up, L3 98.025 ->
    98.035 %, none down, L2 and the off-suite files unchanged). As in `_relabel_by_shape`, the same
    relabelling must win SHAPE_CONFIRM checks running on a trusted layout, and the long-run partner
    distances must not object; the free point's label is on probation."""
    counts = _segment_counts(model, st, point_index)
    if counts is None:
        return np.zeros(len(point_index), bool)
    slots, labeled, n_lab, n_spare = counts
    seg, layout = model.marker_segment, model.layout_offsets_m
    trusted = _trusted_layouts(st)
    pool = np.flatnonzero(cand)
    before = point_index.copy()
    small = n_lab + n_spare <= SHAPE_ALL_MAPS + 1  # every labeling of three of its markers is tried
    checked = np.flatnonzero((n_lab == 2) & (n_spare > 0) & small & trusted)
    if len(checked):
        pw = _joints_m(model, st)
    for k in checked:
        lab = np.flatnonzero(labeled & slots & (seg == k))
        slot = np.concatenate([lab, np.flatnonzero(~labeled & slots & (seg == k))])
        reach = _norm(layout[slot] - layout[slot].mean(0)).max() * 2.0 + SEARCH_INLIER_M
        near = pool[_norm(points[pool] - cur[lab].mean(0)) < reach]
        if len(near) == 0:
            st.complete_votes.pop(int(k), None)
            continue
        maps = _relabellings(3, len(slot))  # (C, 3): slots labeling the two points, then the free one
        # every (labelling, free point) pair: the two points and the free one
        triples = np.concatenate([np.broadcast_to(cur[lab], (len(near), 2, 3)), points[near][:, None]], axis=1)
        rms3, rms4 = _labelings_fit(model, slot, maps, pw[k], triples)
        # (a floor: a foot's layout, measured to 0.9 mm in the seed, fitted its true labels to 3.7 mm once the
        # ankle flexed, and a toe label stayed on the fifth metatarsal's point 1.7 s; 85_12 at L3)
        tight = max(_layout_tolerance(model, slot), COMPLETE_FIT_FLOOR_M)
        score = np.where(rms3 <= tight, rms4, np.inf)
        c, p = np.unravel_index(int(np.argmin(score)), score.shape)
        other = (maps[:, 0] != maps[c, 0]) | (maps[:, 1] != maps[c, 1])  # another labeling of the two points
        rival = score[other].min() if other.any() else np.inf
        pair_misfit = abs(_norm(cur[lab[0]] - cur[lab[1]]) - _norm(layout[lab[0]] - layout[lab[1]]))
        wrong_pair = pair_misfit >= COMPLETE_PAIR_MISFIT_M
        if wrong_pair:
            # the pair as labeled, its misfit and all, with whichever free point: where the joint fits it
            # as a right labeling should and clearly better than the relabelling, the misfit is the skin's
            kept = rms4[(maps[:, 0] == 0) & (maps[:, 1] == 1)].min()
            if kept <= COMPLETE_JOINT_RMS_M and kept + SHAPE_CLEAR_MIN_M <= score[c, p]:
                st.complete_votes.pop(int(k), None)
                continue
        if not ((np.isfinite(rival) or wrong_pair) and (maps[c, 0], maps[c, 1]) != (0, 1) and rival >= 2.0 * score[c, p] + SHAPE_CLEAR_MIN_M
                and score[c, p] <= (COMPLETE_WRONG_PAIR_JOINT_M if wrong_pair else COMPLETE_JOINT_RMS_M)):
            st.complete_votes.pop(int(k), None)
            continue
        new = (int(slot[maps[c, 0]]), int(slot[maps[c, 1]]), int(slot[maps[c, 2]]), int(near[p]))
        votes = st.complete_votes.get(int(k), ((), 0))  # (the points are renumbered every frame: markers only)
        # (the vote is on the pair's labels: with two of its markers hidden, the free point completing the
        # triangle may be either, frame by frame; a tennis wrist and finger, 2026-11-25)
        votes = (new[:2], votes[1] + 1 if votes[0] == new[:2] else 1)
        st.complete_votes[int(k)] = votes
        if votes[1] < SHAPE_CONFIRM:
            continue
        del st.complete_votes[int(k)]
        proposed = point_index.copy()
        proposed[lab] = -1
        proposed[[new[0], new[1]]] = point_index[lab]
        proposed[new[2]] = new[3]
        if _partners_object(st, points, cur, labeled, proposed, np.flatnonzero(proposed != point_index)):
            continue
        point_index[:] = proposed
        st.provisional[new[2]] = PROBATION_FRAMES
        pool = pool[pool != new[3]]
        cur[:] = _gather(points, point_index)
        labeled = point_index >= 0
    return point_index != before


def _complete_lone_label(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                         point_index: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Put back a segment's one label sitting on another of its markers' points, and label its hidden
    markers, from two free points and the segment's joint. In place; returns the markers whose point
    changed.

    A tennis player's whole foot hid as the serve turned it: its markers came back where neither the
    shank's markers nor the fit put them, the Hungarian gave the ankle label the toe's point, and with the
    heel's and the ankle's own points left free (their predictions followed the wrong label) one label
    alone matched nothing to check: it stayed there 6.5 s (L3). As in `_complete_by_free_point`, the
    labeled point with every two free points within the segment's reach, and the joint where the latest fit
    puts it, are registered onto the segment's markers under every way of labeling the three points; the
    labeling whose three points fit the layout (COMPLETE_FIT_FACTOR) and whose joint then fits best is
    taken if it fits within COMPLETE_JOINT_RMS_M and every labeling that gives the labeled point another
    label fits clearly worse (twice, plus SHAPE_CLEAR_MIN_M). The same labeling must win SHAPE_CONFIRM checks
    running on a trusted layout, and the long-run partner distances must not object; the two free points'
    labels are on probation. (Dev suite, 18 realizations: L3 98.018 -> 98.059 %, 9 runs up, none down; L2
    99.238 -> 99.241 %.)"""
    changed = np.zeros(len(point_index), bool)
    counts = _segment_counts(model, st, point_index)
    if counts is None:
        return changed
    slots, labeled, n_lab, n_spare = counts
    seg, layout = model.marker_segment, model.layout_offsets_m
    small = n_lab + n_spare <= SHAPE_ALL_MAPS + 1  # every labeling of three of its markers is tried
    checked = np.flatnonzero((n_lab == 1) & (n_spare >= 2) & small & _trusted_layouts(st))
    if not len(checked):
        return changed
    pool = cand.copy()
    pool[point_index[labeled]] = False  # (points labeled since `cand` was made: `_complete_by_free_point`)
    pool = np.flatnonzero(pool)
    pw = _joints_m(model, st)
    for k in checked:
        key = -1 - int(k)  # (its votes beside `_complete_by_free_point`'s, which are keyed by segment)
        lab = np.flatnonzero(labeled & slots & (seg == k))
        slot = np.concatenate([lab, np.flatnonzero(~labeled & slots & (seg == k))])
        reach = _norm(layout[slot] - layout[slot].mean(0)).max() * 2.0 + SEARCH_INLIER_M
        near = pool[_norm(points[pool] - cur[lab[0]]) < reach]
        if len(near) < 2:
            st.complete_votes.pop(key, None)
            continue
        pairs = np.array(list(itertools.combinations(near, 2)))  # (P, 2): every labeling below orders them
        maps = _relabellings(3, len(slot))  # (C, 3): slots labeling the labeled point, then the two free ones
        triples = np.concatenate([np.broadcast_to(cur[lab], (len(pairs), 1, 3)), points[pairs]], axis=1)
        rms3, rms4 = _labelings_fit(model, slot, maps, pw[k], triples)
        tight = max(_layout_tolerance(model, slot), COMPLETE_FIT_FLOOR_M)
        score = np.where(rms3 <= tight, rms4, np.inf)
        c, p = np.unravel_index(int(np.argmin(score)), score.shape)
        other = maps[:, 0] != maps[c, 0]  # the labeled point under another label
        rival = score[other].min() if other.any() else np.inf
        if not (score[c, p] <= COMPLETE_JOINT_RMS_M and rival >= 2.0 * score[c, p] + SHAPE_CLEAR_MIN_M):
            st.complete_votes.pop(key, None)
            continue
        new = tuple(int(i) for i in slot[maps[c]])  # (the points are renumbered every frame: markers only)
        # (the vote is on the labeled point's label: which of the two free points is which follows their
        # numbering, frame by frame; a vote on all three labels missed a tennis wrist's swap for 26 frames)
        votes = st.complete_votes.get(key, ((), 0))
        votes = (new[:1], votes[1] + 1 if votes[0] == new[:1] else 1)
        st.complete_votes[key] = votes
        if votes[1] < SHAPE_CONFIRM:
            continue
        del st.complete_votes[key]
        proposed = point_index.copy()
        proposed[lab[0]] = -1
        proposed[list(new)] = [point_index[lab[0]], *pairs[p]]
        moved = np.flatnonzero(proposed != point_index)
        if _partners_object(st, points, cur, labeled, proposed, moved):
            continue
        point_index[moved] = proposed[moved]
        changed[moved] = True
        st.provisional[list(new[1:])] = PROBATION_FRAMES
        pool = pool[~np.isin(pool, pairs[p])]
        cur[:] = _gather(points, point_index)
        labeled = point_index >= 0
    return changed


def _reseat_outliers(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                     point_index: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Move a label its segment's layout says is off to the point where the layout puts it. In place;
    returns the markers whose point changed.

    A wrist marker tracked onto the waist marker's point as the hand rested on the hip (and the waist's
    label onto the wrist's) stays there: the two points lie 4-5 cm apart, about as far from every partner,
    so no distance tells, and no permutation within either segment undoes a swap between segments (135_02
    at L2, 0.6 s). The forearm's other labels still fit its layout: registered without the outlier, they
    put it on its own point. For each segment with a trusted layout and RESEAT_MIN_LABELS labels or more
    that misfits it, the one label whose leaving out makes the rest fit (RESEAT_SHARE; leaving out any
    other fits at least twice as badly) is moved to the point nearest where the rest put it, within
    RESEAT_RADIUS_M: a free point, or another segment's label's point, whose label then takes the
    outlier's point if its long-run partner distances do not object. The same move must win SHAPE_CONFIRM
    checks running. (Dev suite, 8 files x L2/L3 x 6 corruption seeds: L2 99.01 -> 99.10 %, L3 97.18 ->
    97.27 %.)"""
    changed = np.zeros(len(point_index), bool)
    slots = _layout_slots(model, st)
    if slots is None:
        return changed
    labeled = point_index >= 0
    seg, layout = model.marker_segment, model.layout_offsets_m
    n_lab = np.bincount(seg[labeled & slots], minlength=N_SEGMENTS)
    trusted = _trusted_layouts(st)
    proposed = set()
    ks = np.flatnonzero((n_lab >= RESEAT_MIN_LABELS) & trusted)
    if not len(ks):
        return changed
    # first every segment's labels at once: most fit, and only those that misfit are looked at one by one
    # (a loop over all of them cost ~0.3 ms on every check)
    *_, rms_all, typical = _layout_fits(model, cur, labeled & slots, ks)
    misfit = rms_all > RESEAT_MISFIT_FACTOR * _tolerance_of(typical)
    for r, k in enumerate(ks):
        if not (misfit[r] or changed.any()):  # (a move below changes the labels the batch judged)
            continue
        lab = np.flatnonzero(labeled & slots & (seg == k))
        n = len(lab)
        tight = _layout_tolerance(model, lab)
        # all labels, then each left out (one batch)
        w = np.ones((n + 1, n), bool)
        w[np.arange(1, n + 1), np.arange(n)] = False
        rms = _kabsch_rms(np.broadcast_to(layout[lab], (n + 1, n, 3)), np.broadcast_to(cur[lab], (n + 1, n, 3)), w)
        if rms[0] <= RESEAT_MISFIT_FACTOR * tight:
            continue
        order = np.argsort(rms[1:])
        j = int(order[0])
        if not (rms[1 + j] <= max(tight, RESEAT_SHARE * rms[0]) and rms[1 + order[1]] >= 2.0 * rms[1 + j]):
            continue
        i = int(lab[j])
        rest = np.delete(lab, j)
        R, t = rigid_motion(layout[rest], cur[rest])
        x = R @ layout[i] + t
        d = _norm(points - x)
        p = int(np.argmin(d))
        if d[p] > RESEAT_RADIUS_M or p == point_index[i]:
            st.reseat_votes.pop(i, None)
            continue
        owner = np.flatnonzero(point_index == p)
        q = int(owner[0]) if len(owner) else -1
        if q < 0 and not cand[p]:
            continue  # another subject's point
        if q >= 0 and seg[q] == k:
            continue  # a permutation within the segment: `_relabel_by_shape`'s
        votes = st.reseat_votes.get(i, (None, 0))
        votes = (q, votes[1] + 1 if votes[0] == q else 1)
        st.reseat_votes[i] = votes
        proposed.add(i)
        if votes[1] < SHAPE_CONFIRM:
            continue
        del st.reseat_votes[i]
        new = point_index.copy()
        new[i] = p
        if q >= 0:
            new[q] = point_index[i]
            z_now = distance_misfit(st, cur, labeled, np.array([q]))[q]
            z_new = distance_misfit(st, _gather(points, new), new >= 0, np.array([q]))[q]
            if np.isfinite(z_new) and z_new > max(Z_SUSPECT, 2.0 * (z_now if np.isfinite(z_now) else 0.0)):
                continue
        moved = np.flatnonzero(new != point_index)
        point_index[:] = new
        changed[moved] = True
        cur[:] = _gather(points, point_index)
        labeled = point_index >= 0
    for i in [i for i in st.reseat_votes if i not in proposed]:
        del st.reseat_votes[i]
    return changed


def _mirror_by_joint(model: SubjectModel, st: TrackState, k: int, lab: np.ndarray, slot: np.ndarray, maps: np.ndarray,
                     cur: np.ndarray, symmetric: np.ndarray) -> int | None:
    """The relabelling (an index into maps) of segment k's labels `lab` that its joint tells from the
    identity though the layout alone cannot, or None. Three markers match their mirror image by a turn (a
    foot whose heel is as far from the toe as from the fifth metatarsal: toe and metatarsal labels
    swapped fit the layout as well, HDM05 at L3, for 3 s); the joint, where the parent holds it, is a
    fourth point off their plane. Taken when, with the joint, the relabelling fits under JOINT_GAIN times
    the identity, the identity misfits by JOINT_MIN_MISFIT_M or more, and no other fits about as well."""
    cands = np.flatnonzero(symmetric[1:]) + 1
    if len(cands) == 0 or len(lab) < 3 or st.skel_pred_m is None:
        return None
    rows = np.concatenate([[0], cands])
    fit = _joint_fits(model, st, k, lab, slot, maps, rows, cur)
    order = np.argsort(fit[1:])
    best = fit[1 + order[0]]
    if fit[0] < JOINT_MIN_MISFIT_M or best > JOINT_GAIN * fit[0]:
        return None
    if len(order) > 1 and fit[1 + order[1]] < 1.5 * best:
        return None
    return int(rows[1 + order[0]])


def _overwhelming_handovers(st: TrackState, lab: np.ndarray, slot: np.ndarray, maps: np.ndarray, rms: np.ndarray,
                            blocked: np.ndarray, tol: float, where: np.ndarray) -> np.ndarray:
    """(C,) the relabellings of a segment misfitting its layout by SHAPE_SETTLED_HANDOVER_MISFIT_M that hand
    a label tracked all along to an unlabeled marker and fit within `tol`, no label jumping farther than
    SHAPE_MAX_HANDOVER_M from where its marker was: `relabel_candidates` blocked them for the tracked label
    alone; the evidence lifts that block (see SHAPE_SETTLED_HANDOVER_MISFIT_M). Not for a settled label
    (confirmed by the whole layout and tracked since), which no relabelling moves: lifted, its block would
    only make the check propose what it will not take, in place of what it would. Nor where a relabelling
    not blocked fits about as well (twice its RMS + 1 mm, as the check counts rivals): the handover would
    only tie with it, and the tie leave the labels be (a head's near-square layout: the tracked label's
    handover and the other two labels mirrored both fitted, 85_12 at L3, and the head stayed wrong 3 s
    longer than with the mirror taken alone)."""
    handed = maps >= len(lab)
    out = (rms <= tol) & (handed & (st.provisional[lab] <= 0)[None]).any(1) & ~(handed & st.settled[lab][None]).any(1)
    for c in np.flatnonzero(out):
        out[c] = _norm(where[lab] - where[slot[maps[c]]]).max() <= SHAPE_MAX_HANDOVER_M
    if out.any():
        others = ~blocked
        others[0] = False  # (the identity)
        if (rms[others] < 2.0 * rms[out].min() + 0.001).any():
            out[:] = False
    return out


def _joint_fits(model: SubjectModel, st: TrackState, k: int, lab: np.ndarray, slot: np.ndarray, maps: np.ndarray,
                rows: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """(len(rows),) [m] RMS of segment k's labeled points `lab` and its joint, where the latest fit puts
    it, registered onto the layout under each relabelling maps[rows]; all infinite with no fit to ask."""
    if st.skel_pred_m is None:
        return np.full(len(rows), np.inf)
    joint = _joints_m(model, st)[k]
    A = np.concatenate([model.layout_offsets_m[slot[maps[rows]]],
                        np.broadcast_to(model.layout_joints_m[k], (len(rows), 1, 3))], axis=1)
    B = np.broadcast_to(np.vstack([cur[lab], joint[None]]), A.shape)
    return _kabsch_rms(A, B, np.ones(A.shape[:2], bool))


@functools.lru_cache(maxsize=None)
def _relabellings(n: int, s: int | None = None) -> np.ndarray:
    """(C, n) ways to give n labeled points (now on slots 0..n-1 of a segment's s >= n marker slots; the
    slots beyond n are its unlabeled markers) labels from those slots, one each, the identity first: every
    assignment for small segments, else every swap of two labels and every label handed to an unlabeled
    marker (a torso of 7: 21 swaps, not 5040 permutations)."""
    s = n if s is None else s
    if n <= SHAPE_ALL_MAPS and s <= SHAPE_ALL_MAPS + 1:
        return np.array(list(itertools.permutations(range(s), n)), dtype=int)
    maps = [list(range(n))]
    for i, j in itertools.combinations(range(n), 2):
        p = list(range(n))
        p[i], p[j] = j, i
        maps.append(p)
    for i in range(n):
        for u in range(n, s):
            p = list(range(n))
            p[i] = u
            maps.append(p)
    return np.array(maps, dtype=int)


def _count_layout_fits(st: TrackState, ks: np.ndarray, fits: np.ndarray) -> np.ndarray:
    """Fold one check of segments `ks` (whether their labels fit their layouts) into the running share of
    checks that fit; returns the share before it."""
    share = st.shape_fit[ks]
    st.shape_checks[ks] += 1
    alpha = np.maximum(1.0 / st.shape_checks[ks], SHAPE_FIT_ALPHA)  # a plain mean first, then a running one
    st.shape_fit[ks] = share + alpha * (fits - share)
    return share


def learn_layout_trust(model: SubjectModel, st: TrackState, history_m: np.ndarray) -> None:
    """Count how often each segment's labels fit its new layout over the labeled frames (F, M, 3) it was
    calibrated from (every SHAPE_EVERY_FRAMES-th), as the checks of `_relabel_by_shape` would have: a
    calibration that lands after a seed (at 50 Hz, 2 s of labels are 100 frames) would otherwise start with
    no layout trusted. `observe` counts each given frame it checks the same way.

    Every frame's segments are registered in one batch, then folded in frame order: one frame at a time
    (~80 us each), the 60 frames of a 240-frame history held up the frame that took a calibration by 4-8
    ms, the largest part of a subject scan's p99 (three subjects' calibrations taken 0.45 s apart)."""
    slots = _layout_slots(model, st)
    if slots is None:
        return
    frames = history_m[::SHAPE_EVERY_FRAMES]
    seg = np.maximum(model.marker_segment, 0)  # (slots exclude segment -1)
    f_of, members = np.nonzero(np.isfinite(frames[:, :, 0]) & slots)  # (frame-major, markers ascending)
    counts = np.zeros((len(frames), N_SEGMENTS), int)
    np.add.at(counts, (f_of, seg[members]), 1)
    checked = counts >= SHAPE_MIN_LABELED
    fr, ks = np.nonzero(checked)  # the rows: each frame's checked segments, ascending
    if len(fr) == 0:
        return
    on = checked[f_of, seg[members]]
    f_of, members = f_of[on], members[on]
    key = f_of * N_SEGMENTS + seg[members]
    order = np.argsort(key, kind="stable")  # (a segment's markers stay ascending, as `_layout_fits` has them)
    f_of, members, key = f_of[order], members[order], key[order]
    row = np.searchsorted(fr * N_SEGMENTS + ks, key)
    n_lab, rms, typical = _registered_rows(model, members, frames[f_of, members], row, len(fr))
    fits = rms <= _fit_tolerance(n_lab, typical)[1]
    bounds = np.flatnonzero(np.diff(fr)) + 1
    for rows in np.split(np.arange(len(fr)), bounds):
        _count_layout_fits(st, ks[rows], fits[rows])


def _relabel_by_shape(model: SubjectModel, st: TrackState, points: np.ndarray, point_index: np.ndarray,
                      cur: np.ndarray) -> np.ndarray:
    """Permute the labels within a segment when its calibrated marker layout says they are permuted.
    In place; returns the markers whose point changed. (Given labels, `observe`, only count how often
    each segment's labels fit its layout, `learn_layout_trust`: a layout trusted by the end of a seed can
    undo a swap right after it; a tennis player's wrist labels swapped in the serve, 0.4 s after the
    seed, and stayed swapped for 40 frames while the layout earned its trust.)

    Markers of one segment keep their offsets; a wrist-and-finger triad or a foot's markers permuted by a
    fast pass or a re-acquisition after occlusion keep being tracked permuted, and the long-run partner
    distances absorb it (their spread grows until nothing looks wrong). The layout does not: on 135_02
    the true labels of a forearm fit it to ~11 mm RMS, any permutation of them to 30-80 mm, every frame.
    So each segment's labeled points are registered (Kabsch) onto the offsets of the markers they carry,
    and, where that fits poorly, onto every permutation of their labels, and every assignment that hands
    a just re-acquired marker's point to one of the segment's unlabeled markers (135_02 at L3: the ankle
    marker came back on the fifth metatarsal's point, both hidden for a second, and stayed there)."""
    m = len(point_index)
    changed = np.zeros(m, bool)
    labeled = point_index >= 0
    seg = model.marker_segment
    slots = _layout_slots(model, st)
    if slots is None:
        return changed
    layout = model.layout_offsets_m
    counts = np.bincount(seg[labeled & slots], minlength=int(seg.max()) + 1)
    ks = np.flatnonzero(counts >= SHAPE_MIN_LABELED)
    if len(ks) == 0:
        return changed
    members, row, n_lab, rms0, typical = _layout_fits(model, cur, labeled & slots, ks)
    can_clear, tol = _fit_tolerance(n_lab, typical)
    tight = typical <= SHAPE_CLEAR_LAYOUT_M
    fits = rms0 <= tol
    whole = np.bincount(seg[slots], minlength=int(seg.max()) + 1)[ks] == n_lab
    confirmed = np.zeros(N_SEGMENTS, bool)  # (a lookup: np.isin cost 70-90 us here, a tenth of the check)
    confirmed[ks[fits & whole & (n_lab >= SETTLED_MIN_LABELS)]] = True
    st.settled |= confirmed[seg] & labeled & slots  # (slots: assigned markers only, no segment -1)
    if st.shape_votes:
        for k in ks[fits]:
            st.shape_votes.pop(int(k), None)
    # every permutation of every misfitting segment's labels, registered in one batch (padded to the
    # widest segment): one call instead of one per segment, which cost more than the arithmetic
    flagged = np.flatnonzero(~fits)
    groups = {r: members[row == r] for r in flagged}
    # each segment's labeled slots, then its unlabeled ones: a marker re-acquired on another's point (the
    # ankle marker on the fifth metatarsal's, which was hidden too) is put back by handing its point to the
    # unlabeled marker whose place in the layout it is
    spare = {r: np.flatnonzero(~labeled & slots & (seg == ks[r])) for r in flagged}
    slot_of = {r: np.concatenate([groups[r], spare[r]]) for r in flagged}
    proposals = {}
    # where each marker is, or was last: a label's jump is measured from there
    where = np.where(np.isfinite(cur), cur, st.pos_m)
    for r in flagged:
        lab, slot = groups[r], slot_of[r]
        maps = _relabellings(len(lab), len(slot))
        # every relabelling of the segment scored at once (a compiled loop, `kernels.relabel_candidates`):
        # its fit to the layout, and whether it is blocked. A relabelling trades labels between neighbours
        # (a wrist triad, a foot's markers): labels that would jump across the body tell of a layout
        # calibrated wrong (a seed lying still), not of a permutation. A permutation moves a label at most
        # across its segment (SHAPE_MAX_JUMP_M: a foot's heel to toe; at 0.2 m a tennis player's left foot
        # stayed permuted for 8 s); a label handed to an unlabeled marker, whose place is only known from
        # where it was last, less far (SHAPE_MAX_HANDOVER_M: at 0.3 m a thigh marker calibrated onto a
        # hanging forearm was handed to the finger marker, 85_12 at L3), and only from a re-acquisition
        # still on probation (a marker tracked all along is not suspected of sitting on another's point,
        # short of overwhelming evidence: `_overwhelming_handovers`).
        rms, blocked = kernels.relabel_candidates(layout, cur, where, st.provisional, lab, slot, maps,
                                                  SHAPE_MAX_HANDOVER_M, SHAPE_MAX_JUMP_M)
        if len(lab) >= SHAPE_CLEAR_MIN_LABELS and rms0[r] >= SHAPE_SETTLED_HANDOVER_MISFIT_M:
            blocked &= ~_overwhelming_handovers(st, lab, slot, maps, rms, blocked, tol[r], where)
        fits[r] = rms.min() < SHAPE_GOOD_RMS_M
        # a relabelling the layout itself is symmetric under (a square cluster plate turned by 90 degrees,
        # two markers equidistant from the rest) cannot be told from the identity: never taken, unless the
        # segment's joint tells them apart (`_mirror_by_joint`)
        key = slot.tobytes() + bytes([len(lab)])  # the layout's own symmetries: once per set of slots
        symmetric_rms = st.shape_symmetry.get(key)
        if symmetric_rms is None:
            if len(st.shape_symmetry) > 256:
                st.shape_symmetry.clear()
            ones = np.ones(maps.shape, bool)
            symmetric_rms = st.shape_symmetry[key] = _kabsch_rms(layout[slot[maps]], np.broadcast_to(layout[lab], maps.shape + (3,)), ones)
        # a relabelling that moves the layout's markers less than SHAPE_DISTINCT_M is taken only on clear
        # evidence: the labels misfit the layout by about that move, and the relabelled ones fit it as tightly
        # as in calibration (a toe label on the fifth metatarsal's point, 11 mm apart in the foot's layout:
        # 10 mm misfit, 0.4 mm relabelled; 85_12 at L2). Not with two labels: they match one distance, and a
        # head band's sides and diagonals offer several. A label on probation handed back to an unlabeled
        # marker (see REACQUIRED_HANDOVER_MISFIT_M) need only fit as right labels do on a check (`tol`), or,
        # on a forearm, well under the labels' misfit (REACQUIRED_HANDOVER_SHARE).
        handed = maps >= len(lab)  # (C, n): which labels each relabelling hands to an unlabeled marker
        handback = (handed & (st.provisional[lab] > 0)[None]).any(1)
        share = REACQUIRED_HANDOVER_SHARE if ks[r] in TWISTING_SEGMENTS else 0.0
        clear = (
            can_clear[r] & (tight[r] | handed.any(1)) & (symmetric_rms >= SHAPE_CLEAR_MIN_M)
            & (rms0[r] >= SHAPE_CLEAR_SHARE * symmetric_rms)
            & ((rms <= max(SHAPE_CLEAR_FIT_M, 2.0 * typical[r]))
               | ((rms <= max(tol[r], share * rms0[r])) & handback & (rms0[r] >= REACQUIRED_HANDOVER_MISFIT_M)))
        )
        unseen = (symmetric_rms < SHAPE_DISTINCT_M) & ~clear  # relabellings the layout cannot tell
        mirror = _mirror_by_joint(model, st, ks[r], lab, slot, maps, cur, unseen & ~blocked & (rms < SHAPE_GOOD_RMS_M))
        if mirror is not None:
            proposals[r] = slot[maps[mirror]]
            continue
        fitting = np.where(unseen, np.inf, rms)  # blocked or not
        fitting[0] = np.inf
        rms = np.where(blocked, np.inf, fitting)
        best = int(np.argmin(rms))
        # (one taken on clear evidence must also stand out: two that fit alike leave it open which)
        rivals = np.count_nonzero(rms < 2.0 * rms[best] + 0.001)
        unique = rivals <= 1 or symmetric_rms[best] >= SHAPE_DISTINCT_M
        # Two labels match one distance, which their swap keeps: every relabelling of them ties with its
        # swap, and a block on one of the two for a label's jump from where a marker was last seen (stale
        # after a long occlusion) used to pick the other (a tennis player's toe label went to the ankle's
        # point and the ankle's to the toe's, for 4 s). Such a tie is told apart by the segment's joint,
        # failing that by the least change (the one relabelling that moves fewest labels, if not blocked),
        # or left alone. (A block for handing over the point of a label tracked all along stands: that label
        # is not suspect.) (Dev suite, 18 realizations: L3 97.932 -> 97.959 %, L2 unchanged, with the joint
        # alone; 97.977 % with the least change, L2 99.219 %, and an HDM05 run whose fifth metatarsal label
        # sat 7 s on the heel's point put back. For segments of any number of labels L3 gained less,
        # 97.946 %, and the head's near-square layout kept a swap twice as long on 85_12.)
        tied = np.flatnonzero(fitting < 2.0 * rms[best] + 0.001) if len(lab) == 2 else np.zeros(0, int)
        tied = tied[~((maps[tied] >= len(lab)) & (st.provisional[lab] <= 0)).any(1)]
        if len(tied) > 1:
            joint_fit = _joint_fits(model, st, ks[r], lab, slot, maps, tied, cur)
            order = np.argsort(joint_fit)
            if joint_fit[order[0]] <= COMPLETE_WRONG_PAIR_JOINT_M and joint_fit[order[1]] >= 2.0 * joint_fit[order[0]] + SHAPE_CLEAR_MIN_M:
                best = int(tied[order[0]])
                unique = not blocked[best]
            else:
                moves = (slot[maps[tied]] != lab).sum(1)
                least = tied[moves == moves.min()]
                if len(least) == 1 and not blocked[least[0]]:
                    best, unique = int(least[0]), True
                elif blocked[tied].any():
                    unique = False
        take = unique and rms[best] < min(SHAPE_GAIN * rms0[r], SHAPE_GOOD_RMS_M) and symmetric_rms[best] > 2.0 * rms[best]
        if take and ks[r] in BENDING_SEGMENTS and (maps[best] >= len(lab)).any():  # (see BENDING_SEGMENTS)
            take = rms[best] <= tol[r]
        if (take and ks[r] in TWISTING_SEGMENTS and symmetric_rms[best] < SHAPE_DISTINCT_M
                and rms[best] > TWIST_CLEAR_SHARE * rms0[r]):  # (see TWISTING_SEGMENTS)
            joint_fit = _joint_fits(model, st, ks[r], lab, slot, maps, np.array([0, best]), cur)
            take = joint_fit[1] <= joint_fit[0]
        if take:
            proposals[r] = slot[maps[best]]
        else:
            st.shape_votes.pop(int(ks[r]), None)
    # A layout to be trusted fits the labels, or a permutation of them, on most checks; one that seldom
    # does was calibrated wrong (from a pose that hid which markers move together): it is left alone.
    share = _count_layout_fits(st, ks, fits)
    trusted = (share >= SHAPE_TRUSTED_SHARE) & (st.shape_checks[ks] > SHAPE_MIN_CHECKS)
    for r, new_labels in proposals.items():
        if not trusted[r]:
            continue
        lab = groups[r]
        # the same relabelling on SHAPE_CONFIRM checks running: one frame's loose marker is no reason. A
        # relabelling that carries the last one's moves and more is the same, seen with a label more (a
        # serving wrist triad's cycle, proposed on two labels, then on three once the finger's label came
        # back on the third point, is taken a check sooner: two players at L2). (Dev suite, 18
        # realizations: 7 runs moved, 6 up; L2 99.322 -> 99.323 %, the two players 99.465 -> 99.470 %;
        # KneeltoProne, squat and 03_rolling, seeds 0-5, unchanged.)
        moves = tuple(sorted((int(a), int(b)) for a, b in zip(lab, new_labels) if a != b))
        n_votes = st.shape_votes.get(int(ks[r]), ((), 0))
        n_votes = n_votes[1] + 1 if n_votes[0] and set(n_votes[0]) <= set(moves) else 1
        st.shape_votes[int(ks[r])] = (moves, n_votes)
        if n_votes < SHAPE_CONFIRM:
            continue
        del st.shape_votes[int(ks[r])]
        proposed = point_index.copy()
        proposed[lab] = -1
        proposed[new_labels] = point_index[lab]
        moved = slot_of[r][proposed[slot_of[r]] != point_index[slot_of[r]]]
        if st.settled[moved].any():
            continue
        if _partners_object(st, points, cur, labeled, proposed, moved):
            continue
        point_index[moved] = proposed[moved]
        changed[moved] = True
    if changed.any():
        cur[changed] = _gather(points, point_index)[changed]
    return changed
