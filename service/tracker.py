"""Per-subject labeling, the paper's loop made robust: `step(model, state, points, free, t_ns)`.

1. Tracking (NNT): markers labeled in the previous frame are predicted from their measured velocity (and
   acceleration, once labeled three frames running) and matched one-to-one to points with the Hungarian
   method inside a gate that widens with speed x frame time.
2. Checks: a label its rigid partners (`service.partners`) disagree with (a swap of two close markers, a
   ghost caught while the marker hid), by more than their distances to it spread, is withdrawn or swapped
   back; long-run partner distances repair what rigid checks miss; two labels that each sit where a recent
   skeleton fit puts the other are swapped back (a mirror-image pair, such as toe and fifth metatarsal,
   keeps every distance to its partners when crossed).
3. Re-acquisition: every occluded marker is predicted, from its *rigid partners* when three of them are
   labeled now (Kabsch on the partners' positions when the marker was last seen, i.e. a rigid-body fill;
   the most accurate prediction there is and free of calibration error), else from the fitted skeleton,
   else by coasting. Remaining points are assigned to these predictions with the Hungarian method inside a
   gate, so ghosts far from any prediction stay unlabeled, and a point that stood still while the marker's
   limb moved is not taken (a reflection near the body, `_still_on_moving`); labels the skeleton disagrees
   with by more than `reject_residual_m` are withdrawn: a wrong label costs more than a missing one. On a
   segment none of whose markers is labeled (its pose is the fit's guess), markers are taken two or more at
   once, at the model's distances. Markers neither can place, unlabeled a few frames though in view (a hand
   that moved while hidden, where the fit, with nothing to hold it, kept it), and the markers of a segment
   none of whose markers is labeled (a foot back from an occlusion: its partners across the joint place it no
   better than the fit) are first looked for by registering their segment around its joint
   (`service.segment_search`), where a fit at most SEARCH_FIT_AGE_FRAMES old puts it (an older one: a
   solve is launched and the search waits a frame). A marker its partners place where no point is gets a
   second opinion from a well-fitting skeleton (SECOND_OPINION_GATE_M); with no skeleton at all, a cluster
   hidden whole is found by its own layout (`segment_search._search_rigid_groups`). A subject with fewer
   than 4 labels (it left the volume, or was hidden whole) is looked for by registering its last marker
   cloud onto the unclaimed points nearby (rigid ICP, `_relocate`): on every frame at first, then on every
   RELOCATE_EVERY_FRAMES-th.
   The periodic work (every 2nd, 3rd, 4th frame) runs on frames chosen by the subject's frame count,
   which starts at its phase (`new_state`), so subjects do it on different frames.
   Here the frame's labels are final. What follows (`step(defer=True)` leaves it to `finish`, after the
   daemon has published them) changes the state, not this frame's labels:
4. Every SHAPE_EVERY_FRAMES frames, labels permuted within a segment (a wrist triad after a fast pass,
   tracked permuted since, which the partner statistics absorb), or a re-acquired label on the point of
   another marker of its segment, are put back where the segment's calibrated marker layout says
   (`service.layouts`: `_relabel_by_shape`); two labels of a segment whose other markers hide, swapped,
   are put back by a free point and the segment's joint (`_complete_by_free_point`), and a segment's one
   label on another of its markers' points by two free points and the joint (`_complete_lone_label`). The
   state tracks the new labels from the next frame on.
5. The skeleton fit (optimistix Gauss-Newton, `service.solver`) is launched on the frame's final labels when
   a hidden marker is left that rigid partners cannot place, after a relabelling, and at least every
   `max_skip_frames` frames (and `max_skip_s` seconds); otherwise it is skipped. It computes
   asynchronously (XLA's thread) and is collected by the engine for the frame's pose, or at the next frame
   (`collect`), whose skeleton predictions are its markers carried forward at their velocity. The labels
   never wait for a solve; the pose waits only for its own. Markers hidden long are re-acquired inside a
   gate that widens with the time hidden.

This module keeps the loop; each step's machinery lives with its concept: the rigid partners learned
online (`service.partners`), the searches for a segment few of whose markers are labeled
(`service.segment_search`), the segments' calibrated marker layouts and what they correct
(`service.layouts`), and what all of them share, the subject's calibration and its per-frame state
(`service.track_state`). They import one way: track_state <- partners <- segment_search <- layouts <-
tracker.

The loops over markers, partners and relabellings are compiled (`service.kernels`, numba); these modules
keep the decisions, the kernels the arithmetic.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from protocol.skeleton import N_SEGMENTS
from service import kernels
from service.config import EngineConfig
from service.layouts import (
    PROBATION_FRAMES,
    SHAPE_EVERY_FRAMES,
    SLIDE_SHARE,
    _complete_by_free_point,
    _complete_lone_label,
    _relabel_by_shape,
    _reseat_outliers,
    learn_layout_trust,
)
from service.partners import (
    N_PARTNERS,
    Z_SUSPECT,
    _partner_sigma,
    _repair_by_distances,
    _snapshot,
    _update_distances,
    _update_partners,
    distance_misfit,
    far_reacquisitions_misfit,
    rigid_predictions,
)
from service.segment_search import GROUP_MIN_PLACED, _search_rigid_groups, _search_segments
from service.track_state import _PARENTS, SubjectModel, TrackState, _gather, _norm, _observed_segments, rigid_motion

#: Partners nearly in a line place a far marker poorly: a turn about the line is left to their skin wobble
#: (3 mm), which the lever swings (`kernels.rigid_predict`); a prediction that could swing more than this
#: [m] does not withdraw a tracked label. A knee, a thigh and a shoulder marker placed a foot marker 17 cm
#: off in one frame, and its correct track was withdrawn (cmu/135_02 at L3).
RIGID_MAX_SWING_M = 0.05
#: A tracked label is withdrawn when farther from its rigid prediction than rigid_check_m (+ 4 x the partners'
#: misfit) + this many times the spread of its partners' distances to it (`_partner_sigma`): partners across
#: a joint learned still in the seed place a serving arm's elbow 9 cm off in one 50 Hz frame while their own
#: distances to it vary by 2-4 cm, and its correct label was withdrawn; a neighbour took its point for 140
#: frames (two players at L2, seed 3). (Dev suite, 8 files x L2/L3 x seeds 0-17: L3 98.01 -> 98.19 %, L2
#: 99.25 -> 99.29 %, 85 runs up, 23 down; at 2 and at 5 L3 moved by under 0.02 from 3, and 5 cost L2 0.02.)
RIGID_LOOSE_K = 3.0
LOOSE_SPREAD_M = 0.015  # partners misfitting more than this hand the prediction to a well-fitting skeleton
SKELETON_TRUSTED_RMS_M = 0.015  # a skeleton fit with a lower RMS residual may predict markers
SECOND_OPINION_GATE_M = 0.03  # ... and re-acquire, within this, those its rigid partners placed where no point was
CROSS_JOINT_DISAGREE_M = 0.12  # a hidden marker whose labeled partners are all on other segments is placed by a
# well-fitting skeleton when they put it farther than this from it; with partners on its own segment,
# farther than SAME_SEGMENT_DISAGREE_M (and it is searched for). (Dev suite, 8 files x L2/L3: from 0.2 to
# 0.14, L3 +0.06 % over seeds 0-11 and +0.12 % over 12-17, unseen while choosing, precision +0.01 / +0.03 %,
# L2 unchanged; at 0.16 a neck marker taken on a head marker's point cost one run 3 % (85_02 at L2), and
# 0.12 cost 0.02 % at L2 over seeds 0-5.)
SAME_SEGMENT_DISAGREE_M = 0.14
MAX_GATE_FACTOR = 1.5  # re-acquisition gate at most this times reacquire_gate_m
# ... and, once a skeleton is fitted, never more than this, however loose the partners and poor the fit:
# a gate that grew with the partners' misfit to 20 cm around a hidden wrist marker took its neighbour's
# point, and kept it (135_02). Without a skeleton the partners are all there is, and the wide gate the
# only way back for a marker whose limb moved while it hid.
MAX_RIGID_GATE_FACTOR = 3.0
HIDDEN_WIDEN_S = 0.5  # a skeleton-predicted marker's gate grows by reacquire_gate_m per this long hidden ...
MAX_HIDDEN_GATE_FACTOR = 2.0  # ... up to this many times reacquire_gate_m
RELOCATE_RADIUS_M = 2.5  # a lost subject is looked for among the unclaimed points this far (horizontally) ...
RELOCATE_MIN_SHARE = 0.3  # ... and found when this share of its markers has a point after registration
RELOCATE_GATE_FACTOR = 0.5  # ... within this times reacquire_gate_m (the rigid parts; limbs moved meanwhile)
#: With a skeleton, when the whole cloud does not register, the trunk's markers alone are (pelvis, abdomen,
#: torso, head: they keep their layout while the limbs move), and the subject is found when this share of
#: them has a point within reacquire_gate_m. Measured on the synthetic performer lost for 1.25 s mid-walk
#: (seed 3): the trunk was found on every frame checked over the next 4 s (10-15 of its 15 markers, median
#: error 1-2 cm), the whole cloud on 1 of 4 (its limbs had moved: 6 of 41 markers within the gate at the
#: true shift).
RELOCATE_TRUNK_SHARE = 0.5
RELOCATE_EAGER_FRAMES = 12  # a lost subject is looked for on each of its first this many frames lost ...
RELOCATE_EVERY_FRAMES = 4  # ... then on every this many frames
TRUNK_SEGMENTS = (0, 1, 2, 3)  # indices in protocol.skeleton.SEGMENTS
#: A pause in a subject's frames longer than this [s] (a stream paused and resumed, a sender that stalled,
#: a daemon thinning a long backlog never leaves one this long) leaves every track stale: the subject moved
#: on meanwhile, and chaining its labels to whatever points lie near where it was labels them wrong for
#: good. It is looked for as a lost subject instead (`_relocate`).
LOST_AFTER_GAP_S = 0.25
SEGMENT_DISTANCE_TOL_M = 0.015  # markers re-found together on an unobserved segment keep the model's distances
LONE_OWN_M = 0.03  # ... and one alone is taken this close to where the fit puts it ...
LONE_OTHERS_M = 0.08  # ... and this far from where it puts the segment's other hidden markers ...
LONE_MAX_DRIFT_M = 0.1  # ... if it hid slowly enough to coast less than this (speed x time hidden)
SEARCH_LOST_FRAMES = 3  # a marker unlabeled this many frames on a segment the fit cannot place is searched for
SEARCH_EVERY_FRAMES = 3  # ... on every 3rd frame, around its segment's joint (`_search_segments`)
#: ... around a fit at most this many frames old, else it waits a frame for one. At 1.5 (a fit of the last
#: frame) a synthetic foot hidden whole mid-walk came back 77 % labeled instead of 98 % (test_engine's foot
#: test), and since `_complete_by_free_point` the dev suite's L3 is lower too (97.61 -> 97.48 %).
SEARCH_FIT_AGE_FRAMES = 3.5
#: A fit that followed permuted labels takes several solves to turn the segment back once the layout checks
#: have put them right: meanwhile its predictions sit where the old labels were, and the skeleton's unswap
#: would permute them again (a foot's toe and fifth metatarsal, so swapped back, stayed swapped for 12 s:
#: 85_12 at L3). So for this many frames it may not swap them.
SHAPE_HOLD_FRAMES = 8
CHECK_RESIDUAL_M = 0.006  # a tracked label this far [m] (+10 % of the step) from its prediction is checked
CHECK_EVERY_FRAMES = 4  # every tracked label is checked against its rigid partners this often anyway
REPAIR_EVERY_FRAMES = 4  # the long-run distance repair runs on every 4th frame (a swap lives 3 frames more)
#: The tracking gate widens by the way an acceleration the prediction does not model (a change of
#: acceleration over the frame) carries a marker in one frame interval, 0.5 a dt^2: 0.9 mm at 120 Hz, 5 mm at
#: 50 Hz, where serving wrists outran the 30 mm gate. (Dev suite, 18 realizations: L2 +0.006 +- 0.003 points,
#: 29 runs up, 6 down; L3 +0.023 +- 0.018, precision 99.057 -> 99.062 %; the two players L2 99.486 ->
#: 99.535 %, the 120 Hz files within 0.002. A constant gate instead: 35 mm, L3 +0.003 +- 0.021; 40 mm, L2
#: +0.015 but the two players' precision 99.888 -> 99.871 %; 20 mm, L2 -0.109.)
NNT_UNMODELED_ACC_M_S2 = 25.0
MAX_SPEED_M_S = 15.0  # markers never move faster; caps velocities estimated from bad predictions
MAX_ACC_M_S2 = 300.0  # ... nor accelerate faster (a tennis serve's hand reaches ~200 m/s^2)
SKELETON_VELOCITY_GAP_S = 0.05  # two fits at most this far apart give the skeleton markers' velocity
#: A point that stood still while the marker's body moved is no point of that marker (`_still_on_moving`):
#: still, within STILL_SPEED_M_S x the time + STILL_NOISE_M of an unlabeled point on each of the last frames
#: (up to STILL_FRAMES, STILL_MAX_LAG_S back); moving, its rigid partners twice as far (median), and every
#: labeled marker of its own segment (one at least) farther than the point may have. (Dev suite, 18
#: realizations: L2 +0.004 +- 0.001 points, L3 +0.025 +- 0.017, precision 99.403 -> 99.409 % and 99.062 ->
#: 99.086 %; ghosts that last 0.5 s, seeds 0-5: 98.93 -> 99.06 %, the tennis player 98.56 -> 99.22 %. The
#: partners alone: L3 +0.025, but the tennis player L3 -0.11, its planted toe and heel refused; with the own
#: segment checked where it had a marker labeled, lasting ghosts +0.196, dev suite L3 +0.031, but a
#: synthetic walker whose labels were all lost for a frame had its toes refused, their own segment's
#: labels too fresh to have a velocity (98.6 % after, against 99.5 %); the own segment alone, or the
#: skeleton's velocity as a bound, kept a third of the ghost gain; 0.15 m/s over 5 frames: L3 -0.061, a
#: basketball run -8.6 points.)
STILL_SPEED_M_S = 0.3
STILL_NOISE_M = 0.003
STILL_MAX_LAG_S = 0.1


@dataclasses.dataclass(frozen=True)
class StepResult:
    point_index: np.ndarray  # (M,) int32, -1 = not observed
    predicted_m: np.ndarray  # (M, 3)
    solved: bool
    iterations: int
    residual_m: float
    source: np.ndarray | None = None  # (M,) int8 per marker: 0 none, 1 tracked (NNT), 2 re-acquired, 3 given
    positions_m: np.ndarray | None = None  # (M, 3) position of the point each marker is labeled with, NaN = none


def new_state(model: SubjectModel, positions_m: np.ndarray, t_ns: int, history_m: np.ndarray | None = None,
              phase: int = 0) -> TrackState:
    """Start tracking from known marker positions (M, 3; NaN = unseen), with optional labeled history
    (F, M, 3) to seed the rigid-partner statistics. The frame count starts at `phase`: the periodic work
    (layout checks, searches, repairs, full rigid checks) runs on frames chosen by that count, so subjects
    given different phases do it on different frames instead of all on the same one (8 subjects started
    together: a 28 ms frame every 4th, against 9 ms mean)."""
    m = model.n_markers
    seen = np.isfinite(positions_m[:, 0])
    st = TrackState(
        pos_m=np.where(seen[:, None], positions_m, 0.0),
        vel_m_s=np.zeros((m, 3)),
        labeled=seen.copy(),
        ever_seen=seen.copy(),
        last_t_ns=t_ns,
        dist_n=np.zeros((m, m)),
        dist_mean_m=np.zeros((m, m)),
        dist_var_m2=np.zeros((m, m)),
        dist_slow_mean_m=np.zeros((m, m)),
        dist_slow_var_m2=np.zeros((m, m)),
        partners=np.full((m, N_PARTNERS), -1),
        snap_m=np.full((m, m, 3), np.nan),
        snap_kept_m=np.full((m, m, 3), np.nan),
        provisional=np.zeros(m, int),
        t_root_m=np.zeros(3),
        R_parent_segment=np.tile(np.eye(3), (14, 1, 1)),
        last_labeled_t_ns=t_ns,
        acc_m_s2=np.zeros((m, 3)),
        vel_measured=np.zeros(m, bool),
        hidden_frames=np.zeros(m, int),
        layout_hold=np.zeros(m, int),
        settled=np.zeros(m, bool),
        frames=phase,
    )
    if history_m is not None:
        for frame in history_m:
            _update_distances(st, frame, np.isfinite(frame[:, 0]), alpha_min=0.0)
        _update_partners(st)
        # replay the history so every marker remembers where it and the others were when it was last seen
        for frame in history_m:
            ok = np.isfinite(frame[:, 0])
            _snapshot(st, frame, ok)
            st.pos_m[ok] = frame[ok]
            st.ever_seen |= ok
    else:
        _update_partners(st)
    _snapshot(st, np.where(seen[:, None], positions_m, np.nan), seen)
    st.pos_m[seen] = positions_m[seen]
    return st


def _unswap(point_index: np.ndarray, cur: np.ndarray, pred: np.ndarray, err: np.ndarray, tol_m: float) -> bool:
    """Swap the labels of two markers when each sits where the other is predicted (markers that passed
    close to each other and were tracked through crossed): crossed distances under half the straight
    ones, the best pairs first (a poor fit can make a dozen suspects). `err`: each labeled marker's
    distance to its prediction, 0 for the others. In place; True if any pair was swapped. (A compiled
    loop: `kernels.unswap`.)"""
    return kernels.unswap(point_index, cur, pred, err, tol_m)


def _unsure_on_unseen_segment(model: SubjectModel, labeled: np.ndarray, rows: np.ndarray, cur: np.ndarray,
                              use_skel: np.ndarray, seen: np.ndarray, skel_pred: np.ndarray | None,
                              drift: np.ndarray | None = None) -> np.ndarray:
    """Which re-acquisitions (rows, just assigned at positions cur) to hold back: those the skeleton
    predicted on a segment none of whose markers is labeled. Such a segment's pose is the fit's guess (a
    foot hidden while the leg moved), and one point near it could be any of its markers (`seen`: ever
    seen): its markers are taken only two or more at once, at the distances the model puts between them
    (within SEGMENT_DISTANCE_TOL_M), or one alone where the fit puts it within LONE_OWN_M and every other
    hidden marker of the segment farther than LONE_OTHERS_M (dev suite, seeds 0-2: of the lone points so
    held back, 520 such were the marker's and 16 not; 1122 and 159 in all), unless it hid moving: `drift`
    (M,), its speed as the state carries it (decaying while hidden) times the time hidden, at
    LONE_MAX_DRIFT_M or more. The fit holds an unseen segment where it was, so a fast limb is elsewhere by
    then (two players at L3, seed 3: a serving forearm 7 frames hidden, still at 1.4 m/s, predicted 10 cm
    off its point; the other hand's point lay 2 cm from the prediction, and that arm's labels took the
    other's points for 240 frames; dev suite, seeds 0-5, L2 and L3: of 193 lone points so taken, that one
    and 2 right ones moved this far)."""
    hold = np.zeros(len(rows), bool)
    seg = model.marker_segment
    observed = np.zeros(int(seg.max()) + 1, bool)
    observed[seg[labeled]] = True
    guess = use_skel[rows] & ~observed[seg[rows]]
    for k in np.unique(seg[rows[guess]]):
        group = np.flatnonzero(guess & (seg[rows] == k))
        if len(group) < 2:
            # ambiguous only if the segment carries other markers it could be (a lone shin marker is not),
            # and the point is not clearly the one where the fit puts it
            i = rows[group[0]]
            others = np.flatnonzero((seg == k) & seen & ~labeled)
            others = others[others != i]
            clear = (len(others) > 0 and _norm(cur[i] - skel_pred[i]) < LONE_OWN_M
                     and _norm(skel_pred[others] - cur[i]).min() > LONE_OTHERS_M
                     and (drift is None or drift[i] < LONE_MAX_DRIFT_M))
            hold[group] = np.count_nonzero(seen[seg == k]) >= 2 and not clear
            continue
        i = rows[group]
        d_pts = _norm(cur[i][:, None] - cur[i][None])
        off = model.marker_offsets_m[i]
        d_model = _norm(off[:, None] - off[None])
        if np.abs(d_pts - d_model).max() > SEGMENT_DISTANCE_TOL_M:
            hold[group] = True
    return hold


def _relocate(st: TrackState, points: np.ndarray, cand: np.ndarray, gate_m: float, share: float = RELOCATE_MIN_SHARE,
              rows: np.ndarray | None = None) -> np.ndarray | None:
    """Where a lost subject's markers are now (M, 3; NaN = unknown), or None: its last known marker cloud
    (of markers `rows`, default all) registered onto the unclaimed points within RELOCATE_RADIUS_M of it
    by rigid ICP (from four headings, as it may come back turned; at its height: people walk), accepted
    when at least `share` of those markers (and 4) then have a point within `gate_m`. Limbs that moved
    while it was away fit loosely; the torso and head carry the registration, and the skeleton fit finds
    the rest. Runs only while a subject is lost."""
    usable = st.ever_seen & np.isfinite(st.pos_m[:, 0])
    known = np.flatnonzero(usable if rows is None else usable & rows)
    pts = points[cand]
    if len(known) < 4 or len(pts) < 4:
        return None
    src = st.pos_m[known]
    center = src.mean(0)
    for _ in range(3):  # the centre of the unclaimed points around it (mean shift, horizontally)
        near = pts[_norm(pts[:, :2] - center[:2]) < RELOCATE_RADIUS_M]
        if len(near) < 4:
            return None
        center[:2] = near[:, :2].mean(0)
    tree = cKDTree(near)
    need = max(4, int(np.ceil(share * len(known))))
    best, best_n = None, need - 1
    c_src = src.mean(0)
    for yaw in np.arange(4) * (np.pi / 2):
        c, s_ = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        t = center - c_src @ R.T
        pairs = None
        for it in range(12):  # ICP, trimmed: pairs farther than a shrinking radius are left out
            X = src @ R.T + t
            d, j = tree.query(X)
            radius = max(0.3 * 0.7**it, gate_m)
            inl = d < radius
            if inl.sum() < 3:
                break
            if radius == gate_m:  # the radius has stopped shrinking: the same pairs give the same motion again
                now = np.where(inl, j, -1)
                if pairs is not None and np.array_equal(pairs, now):
                    break
                pairs = now
            R, t = rigid_motion(src[inl], near[j[inl]])
        X = src @ R.T + t
        n = int((tree.query(X)[0] < gate_m).sum())
        if n > best_n:
            best, best_n = X, n
    if best is None:
        return None
    out = np.full(st.pos_m.shape, np.nan)
    out[known] = best
    return out


def _trusted_markers(model: SubjectModel, cur: np.ndarray, labeled: np.ndarray, skel_pred: np.ndarray | None,
                     rms: float) -> np.ndarray:
    """(M,) bool: markers the fit may place. All when its RMS residual is under SKELETON_TRUSTED_RMS_M; else
    those of segments with at least three labeled markers this frame, which the fit (carried forward to
    this frame) places within it among themselves. A model that cannot follow part of the body (shoulder
    markers on the torso with the arms overhead, 10-20 cm off in a tennis serve) leaves the fit's RMS at
    20-100 mm while the serving forearm's markers sit within 1-2 cm of their fitted places: its hidden
    wrist marker, 2-3 cm from its fitted place, stayed unlabeled for 38 frames (two players at L2, seed 3).
    Two labeled markers leave the segment's turn about their line free, and a symmetric wrist pair fits
    its swap as well (with two, 135_02 at L3 lost 0.2 % to long wrist swaps).
    (Dev suite, 18 realizations: L2 99.317 -> 99.322 %, L3 98.524 -> 98.533 %; two players at L2 99.41 ->
    99.44 %. A segment held to 10 or 25 mm instead: L2 99.319 / 99.318 %, L3 98.535 / 98.537 %, against
    99.324 / 98.540 % at 15 mm, with the later changes.)"""
    m = model.n_markers
    if rms < SKELETON_TRUSTED_RMS_M:
        return np.ones(m, bool)
    if skel_pred is None:
        return np.zeros(m, bool)
    seg = np.maximum(model.marker_segment, 0)
    err2 = np.sum((cur - skel_pred) ** 2, axis=1)
    seen = labeled & np.isfinite(err2)
    n = np.bincount(seg[seen], minlength=N_SEGMENTS)
    sse = np.bincount(seg[seen], err2[seen], minlength=N_SEGMENTS)
    ok = (n >= 3) & (sse < SKELETON_TRUSTED_RMS_M**2 * np.maximum(n, 1))
    return ok[seg] & (model.marker_segment >= 0)


def _still_on_moving(model: SubjectModel, st: TrackState, rows: np.ndarray, pos: np.ndarray, labeled: np.ndarray,
                     t_ns: int) -> np.ndarray:
    """(len(rows),) bool: which re-acquisitions of markers `rows` onto points at `pos` (len(rows), 3) to
    refuse: the point stood still (an unlabeled point within STILL_SPEED_M_S x lag + STILL_NOISE_M of it on
    each of the last frames, `TrackState.free_history`) while the marker's body moved: its rigid partners
    labeled on this frame and the last (two at least) moved twice that far (the median of their speeds: a
    marker near a joint moves less than the limb), and the markers of its own segment so labeled (one at
    least) each farther than the point may have: partners across a joint move while a foot stays planted.
    Markers ride on their segments: a point that keeps still beside a moving limb is a reflection (ghosts
    drift ~1 mm a frame) or another thing's marker, and taken, the partners' running statistics soon follow
    it (85_12 with ghosts that last 0.5 s: a shoulder's label on one for 76 frames, re-acquired while its
    partners moved at 0.3-1.6 m/s). Only once the subject has a skeleton and a fit: before, its segments are
    not known (a knee marker, still over a planted foot while the thigh's and shank's markers moved, was
    refused)."""
    out = np.zeros(len(rows), bool)
    if not len(rows) or not st.free_history or not model.has_skeleton or st.skel_vel_m_s is None:
        return out
    # first where the points stood still (most re-acquired points had none before them: a marker back in
    # view), then how fast the markers moved, for those only
    still, looks = np.ones(len(rows), bool), []
    for t_prev, pts in reversed(st.free_history):  # newest first
        lag = (t_ns - t_prev) * 1e-9
        if not len(pts) or lag > STILL_MAX_LAG_S:
            break
        reach = STILL_SPEED_M_S * lag + STILL_NOISE_M
        still &= np.min(_norm(pos[:, None] - pts[None]), axis=1) < reach
        if not still.any():
            break
        looks.append((lag, reach, still.copy()))
    if not looks:
        return out
    part = st.partners[rows]
    idx = np.maximum(part, 0)
    ok = (part >= 0) & labeled[idx] & st.labeled[idx] & st.vel_measured[idx]
    n = ok.sum(axis=1)
    # the median of the partners' speeds (np.nanmedian costs ~50 us: sorted, the missing last)
    speeds = np.sort(np.where(ok, _norm(st.vel_m_s[idx]), np.inf), axis=1)
    r = np.arange(len(rows))
    speed = np.where(n >= 2, 0.5 * (speeds[r, np.maximum(n - 1, 0) // 2] + speeds[r, n // 2]), 0.0)  # (n // 2 < K)
    own = np.full(len(rows), np.nan)  # the slowest labeled marker of its own segment (NaN: none)
    for i in np.flatnonzero(looks[0][2] & (n >= 2)):  # (a few re-acquisitions a frame at most: a loop)
        k = rows[i]
        w = (model.marker_segment == model.marker_segment[k]) & labeled & st.labeled & st.vel_measured
        w[k] = False
        if w.any():
            own[i] = _norm(st.vel_m_s[w]).min()
    for lag, reach, s_ in looks:
        out |= s_ & (speed * lag > 2 * reach) & (own * lag > reach)
    return out


def _assign(pred: np.ndarray, gates: np.ndarray, points: np.ndarray, cand: np.ndarray):
    """Hungarian assignment of markers (rows of pred, gated) to candidate points.

    Returns (rows, point_idx, contested): contested[k] is True when pair k was a choice — its marker had
    another point in its gate, or its point was in another marker's gate — which is where swaps and
    ghosts slip in, so only those need the (costlier) rigid check."""
    rows, cols, cost, n_row, n_col = kernels.gated_pairs(pred, gates, points, cand)
    if cost.shape[0] == 0:  # no choice to make: no Hungarian solve
        return rows, cols, np.zeros(len(rows), bool)
    r, c = linear_sum_assignment(cost)  # (only markers and points with a pair in the gates: a small problem)
    return kernels.assigned(rows, cols, cost, n_row, n_col, r, c)


def step(
    model: SubjectModel,
    st: TrackState,
    points: np.ndarray,
    free: np.ndarray,
    t_ns: int,
    config: EngineConfig,
    solver=None,
    defer: bool = False,
) -> tuple[TrackState, StepResult]:
    """Label one frame for one subject. `points` (N, 3) finite; `free` (N,) marks points no other subject
    claimed. Mutates and returns `st` (the registry owns it; callers never share a state). With `defer`,
    the labels are returned before the layout check (8.), the state update and the solve launch: `finish`
    does those (the daemon publishes the labels first; timed on 135_02 at L2, they are ~0.13 ms of a
    frame's ~0.4 ms on average, ~0.25 ms more on a layout-check frame)."""
    collect(model, st)
    m = model.n_markers
    dt = min(max((t_ns - st.last_t_ns) * 1e-9, 1e-4), 0.5) if st.frames or st.last_t_ns else 1.0 / 120
    taken = ~free
    if st.last_t_ns and (t_ns - st.last_t_ns) * 1e-9 > LOST_AFTER_GAP_S:
        st.labeled[:] = False  # the frames paused: no track is current, the subject is looked for (step 4)

    # 1. NNT: markers labeled last frame, predicted from their velocity and acceleration (which holds for
    #    a frame step, not across dropped frames), matched inside gates that widen with their speed.
    pred_track, speed, gates = kernels.track_predictions(st.pos_m, st.vel_m_s, st.acc_m_s2, st.labeled, dt,
                                                         dt < 1.5 * st.acc_dt_s,
                                                         config.nnt_gate_m + 0.5 * NNT_UNMODELED_ACC_M_S2 * dt * dt)
    rows, cols, contested = _assign(pred_track, gates, points, free)
    taken[cols] = True
    # a label needs the rigid check when it was a choice, or when its point is not where the marker was
    # heading (a ghost caught in the gate as the marker vanished); a full check every CHECK_EVERY frames
    # (check: the markers step 2 checks)
    point_index, cur, labeled, check = kernels.track_labels(points, rows, cols, contested, pred_track, speed, dt, m,
                                                            CHECK_RESIDUAL_M, st.ever_seen,
                                                            st.frames % CHECK_EVERY_FRAMES, CHECK_EVERY_FRAMES)
    # labels tracking carried on with no other marker's point in their gate, in a step short of half the
    # way to the nearest other label (a serving arm's labels slid one marker down the chain, each taking
    # the next one's point, none with a rival in its gate) (SETTLED_MIN_LABELS)
    carried = kernels.carried_labels(point_index, cur, pred_track, gates, speed, dt, SLIDE_SHARE)

    # 2. Predict every marker from its rigid partners; a tracked label its partners disagree with (a swap
    #    of two close markers, a ghost caught while the marker hid) is withdrawn and re-assigned below.
    # (the full checks are spread over frames by marker index, so no frame carries them all: a flat p99)
    rpred, spread, swing = rigid_predictions(st, cur, labeled, check)
    # (bad: a label its partners' prediction withdraws)
    has_rigid, spread0, err, bad = kernels.rigid_check(cur, rpred, spread, swing, labeled, RIGID_MAX_SWING_M,
                                                       config.rigid_check_m)
    changed = _unswap(point_index, cur, rpred, err, config.rigid_check_m)
    if st.frames % REPAIR_EVERY_FRAMES == REPAIR_EVERY_FRAMES // 2:
        _repair_by_distances(st, point_index, cur, points, ~taken)
        taken = ~free
        taken[point_index[point_index >= 0]] = True
        changed = True
    if changed:  # (else every label and its error stand as computed)
        labeled = point_index >= 0
        _, _, err, bad = kernels.rigid_check(cur, rpred, spread, swing, labeled, RIGID_MAX_SWING_M,
                                             config.rigid_check_m)
    if bad.any():  # (few: computed on those only)
        rows = np.flatnonzero(bad)
        tol = config.rigid_check_m + 4.0 * spread0[rows]
        bad[rows] = err[rows] > tol + RIGID_LOOSE_K * _partner_sigma(st, labeled, rows)
    # A re-acquired label is on probation: its distances to its partners are held to the long-run norm for
    # PROBATION_FRAMES, so a wrong re-acquisition cannot become its own reference and persist.
    # (and the probation and layout-hold counts move on a frame)
    wrong, st.provisional, st.layout_hold = kernels.probation(st.partners, st.dist_n, st.dist_mean_m, st.dist_var_m2, cur,
                                                              labeled, st.provisional, st.layout_hold, Z_SUSPECT)
    bad |= wrong
    if bad.any():
        taken[point_index[bad]] = False
        point_index[bad] = -1
        labeled = point_index >= 0
        cur[bad] = np.nan
    missing = ~labeled & st.ever_seen

    # 3. The skeleton's word on this frame: the latest fit (launched on an earlier frame's final labels and
    #    computed while they were published), carried forward at its markers' velocity, if it is recent.
    skel_pred = _skeleton_now(st, t_ns, dt) if model.has_skeleton else None
    residual = st.fit_rms_m
    if skel_pred is not None and residual < 0.5 * config.reject_residual_m:
        # two labels that crossed where no partners could tell (a mirror-symmetric pair, such as the two
        # wrist markers, keeps every distance): each sits where the skeleton puts the other
        err_s = kernels.label_errors(cur, skel_pred, labeled & (st.layout_hold <= 0))  # (see SHAPE_HOLD_FRAMES)
        _unswap(point_index, cur, skel_pred, err_s, config.rigid_check_m)

    # 4. Re-acquire occluded markers (Hungarian on predictions, gated).
    coast = st.pos_m + st.vel_m_s * dt * 0.5
    # Markers placed by rigid partners that put them far from the skeleton, where the fit has a word on
    # the segment (it is observed, or held between an observed parent and child; a foot back before its
    # leg is where the fit left it, and the segment search finds it). Partners across a joint learned while
    # it held still (an upper-arm marker's torso partners in a standing seed) agree among themselves and
    # place it where the arm was (24 cm off after a tennis serve, for a second); partners on its own
    # segment, when its last labeled point was another marker's (a serving forearm's marker, labeled on the
    # elbow's point as the arm whipped past, was placed 42 cm off for 0.7 s). The latest fit judges, however
    # old (the solve is skipped while partners place every hidden marker): these launch one, and are
    # searched for.
    # (computed on the few hidden markers partners place, not on all: it runs on most frames)
    stale = np.zeros(m, bool)
    ref = skel_pred if skel_pred is not None else st.skel_pred_m
    if ref is not None:
        seg = model.marker_segment
        far = kernels.far_from_fit(rpred, ref, missing & has_rigid, labeled, st.partners, seg,
                                   SAME_SEGMENT_DISAGREE_M, CROSS_JOINT_DISAGREE_M)
        if far.any():
            observed = _observed_segments(seg, labeled)
            child_seen = np.zeros(N_SEGMENTS, bool)
            child_seen[_PARENTS[observed & (_PARENTS >= 0)]] = True
            held = observed | (child_seen & (_PARENTS >= 0) & observed[np.maximum(_PARENTS, 0)])
            stale[far] = held[np.maximum(seg[far], 0)]
    # Rigid partners place a hidden marker, in a gate that widens with their misfit: when a well-fitting
    # skeleton can take over from loose partners (below), not beyond MAX_GATE_FACTOR (loose partners place
    # a marker poorly); with a skeleton, never beyond MAX_RIGID_GATE_FACTOR. The skeleton speaks for
    # markers with no rigid partners in view, and for those whose partners have moved against each other
    # since (spread), or that they place far from it (above), when the skeleton itself fits well. A marker
    # long hidden with its neighbours left its segment unobserved: the fit has kept that segment where it
    # was, so its gate widens with the time hidden (the distance check below and probation keep ghosts out).
    trusted = _trusted_markers(model, cur, labeled, skel_pred, residual)
    cap = np.inf
    if skel_pred is not None and residual < SKELETON_TRUSTED_RMS_M:
        cap = MAX_GATE_FACTOR * config.reacquire_gate_m
    if model.has_skeleton:
        cap = min(cap, MAX_RIGID_GATE_FACTOR * config.reacquire_gate_m)
    pred_missing, gate_missing, use_skel = kernels.reacquire_gates(
        rpred, has_rigid, spread0, stale, missing, rpred if skel_pred is None else skel_pred, skel_pred is not None,
        trusted, st.hidden_frames, dt, config.reacquire_gate_m, cap, LOOSE_SPREAD_M,
        HIDDEN_WIDEN_S, MAX_HIDDEN_GATE_FACTOR)
    subject_lost = np.count_nonzero(labeled) < 4
    st.lost_frames = st.lost_frames + 1 if subject_lost else 0
    if subject_lost:
        # Lost (full occlusion, a restart from saved state, a subject that left the volume): look for the
        # subject's last known marker cloud in the unclaimed points nearby, registered rigidly (it came
        # back walking, elsewhere, turned); failing that, for every marker where it was last, coasting.
        # A search costs 2-8 ms: after RELOCATE_EAGER_FRAMES it runs on every RELOCATE_EVERY_FRAMES-th frame
        # only, so a subject that left the volume does not slow every frame of the others for as long as
        # it stays away.
        searching = st.lost_frames <= RELOCATE_EAGER_FRAMES or st.frames % RELOCATE_EVERY_FRAMES == 0
        found = _relocate(st, points, ~taken, RELOCATE_GATE_FACTOR * config.reacquire_gate_m) if searching else None
        trunk = np.isin(model.marker_segment, TRUNK_SEGMENTS)
        if searching and found is None and model.has_skeleton and (trunk & st.ever_seen).sum() >= 4:
            # the limbs moved too much to carry the whole cloud: the trunk alone
            found = _relocate(st, points, ~taken, config.reacquire_gate_m, RELOCATE_TRUNK_SHARE, trunk)
        if found is not None:  # only what the registration places well: the fit then finds the limbs
            # (from their pose before the subject left: their gates start narrow again, not widened by
            # the time away)
            st.hidden_frames[:] = 0
            use = missing & np.isfinite(found[:, 0])
            pred_missing[use] = found[use]
            gate_missing[use] = RELOCATE_GATE_FACTOR * config.reacquire_gate_m
        else:
            use = missing & ~np.isfinite(pred_missing[:, 0])
            pred_missing[use] = coast[use]
            gate_missing[use] = config.reacquire_gate_m
    reacquired = np.zeros(m, bool)

    def accept(rows, cols, segment_rule: bool, pred: np.ndarray | None = None):
        """Take re-acquisitions (rows -> cols) but those their rigid partners' distances refuse (more
        strictly those far from their prediction `pred`, when given) and, with segment_rule, those
        `_unsure_on_unseen_segment` holds back."""
        point_index[rows] = cols
        cur = _gather(points, point_index)
        wrong = distance_misfit(st, cur, point_index >= 0, rows)[rows] > Z_SUSPECT
        if pred is not None:
            wrong |= far_reacquisitions_misfit(st, cur, point_index >= 0, rows, pred, config.reacquire_gate_m)
        wrong |= _still_on_moving(model, st, rows, cur[rows], point_index >= 0, t_ns)
        if segment_rule:
            wrong |= _unsure_on_unseen_segment(model, labeled, rows, cur, use_skel, st.ever_seen, skel_pred,
                                               _norm(st.vel_m_s) * st.hidden_frames * dt)
        point_index[rows[wrong]] = -1
        rows, cols = rows[~wrong], cols[~wrong]
        reacquired[rows] = True
        fresh = rows[st.provisional[rows] <= 0]  # (one re-acquired again on probation keeps the first's)
        st.snap_kept_m[fresh] = st.snap_m[fresh]
        st.provisional[rows] = PROBATION_FRAMES
        taken[cols] = True
        return point_index >= 0, _gather(points, point_index)

    # Markers neither the fit nor their partners can place, unlabeled a few frames though in view, are
    # looked for first, by registering their segment around its joint: markers the fit cannot place (a
    # hand flicked while hidden is found where the fit never looks), and every marker of a segment none of
    # whose markers is labeled. Such a segment (a foot back from an occlusion) moved unseen: the fit and
    # its partners across the joint both keep it where it was, and the Hungarian, left to itself, took
    # the toe marker's point for the fifth metatarsal and so on (135_02 at L3).
    searched = np.zeros(m, bool)  # found where the fit does not look: the fit's word on them is void
    search_due = st.frames % SEARCH_EVERY_FRAMES == 0 or st.search_waits
    st.search_waits = False
    if model.has_skeleton and st.skel_pred_m is not None and search_due:
        seg = model.marker_segment
        observed = _observed_segments(seg, labeled)
        lost = ~labeled & st.ever_seen & (st.hidden_frames >= SEARCH_LOST_FRAMES) & (seg >= 0)
        lost &= ~has_rigid | (spread0 > LOOSE_SPREAD_M) | ~observed[np.maximum(seg, 0)] | stale
        # the search hangs the segments from their joints where the last fit put them: a fit some frames
        # old (solves skipped) misplaces a fast limb's joint, and a serving arm's forearm searched around it
        # took the other hand's points (tennis at L3). Then a solve is launched on this frame and the search
        # waits for it, one frame; the lost markers wait too.
        if lost.any() and (t_ns - st.skel_t_ns) * 1e-9 > SEARCH_FIT_AGE_FRAMES * dt:
            st.search_waits = True
            gate_missing[lost] = 0.0  # nor are they taken one by one from the stale predictions meanwhile
        elif lost.any():
            found = _search_segments(model, st, points, ~taken, labeled, cur, lost)
            if found:
                labeled, cur = accept(np.array(list(found)), np.array(list(found.values())), segment_rule=False)
                searched[list(found)] = labeled[list(found)]
                gate_missing[labeled] = 0.0
    rows, cols, _ = _assign(pred_missing, gate_missing, points, ~taken)
    if len(rows):
        labeled, cur = accept(rows, cols, segment_rule=model.has_skeleton, pred=pred_missing)
    if skel_pred is not None and trusted.any():
        # A second opinion: a marker its partners placed where no point is (partners across a joint that
        # bent while it hid) is looked for where a well-fitting skeleton puts it, inside a narrower gate.
        # Not on the frame it vanished (hidden_frames 0): a ghost born beside it would be taken.
        # (dev suite, 8 files x L2/L3, seeds 0-5: 135 such labels right, 3 wrong; a 45 mm gate: 178 / 19)
        # Where the fit is trusted (`_trusted_markers`; per marker rather than on the fit's RMS: dev suite,
        # 18 realizations, L2 99.322 -> 99.324 %, L3 98.533 -> 98.536 %).
        second = ~labeled & st.ever_seen & has_rigid & ~use_skel & (st.hidden_frames >= 1) & trusted
        if second.any():
            gate = np.where(second, SECOND_OPINION_GATE_M, 0.0)
            rows, cols, _ = _assign(np.where(second[:, None], skel_pred, np.nan), gate, points, ~taken)
            if len(rows):
                labeled, cur = accept(rows, cols, segment_rule=True)
    if not model.has_skeleton and search_due and not subject_lost:
        # no skeleton (a seed taken lying down): a cluster hidden whole, which its partners across the
        # joint place where it was, is found by its own layout (`_search_rigid_groups`)
        lost = ~labeled & st.ever_seen & (st.hidden_frames >= SEARCH_LOST_FRAMES)
        if lost.sum() >= GROUP_MIN_PLACED:
            found = _search_rigid_groups(st, points, np.flatnonzero(~taken), labeled, cur, lost)
            if found:
                labeled, cur = accept(np.array(list(found)), np.array(list(found.values())), segment_rule=False)

    # 5. Reject labels the model disagrees with.
    if skel_pred is not None and residual < 0.5 * config.reject_residual_m:
        # the model's word counts only where no rigid partners can speak for a marker
        err = kernels.label_errors(cur, skel_pred, labeled)
        bad = labeled & check & ~has_rigid & (err > config.reject_residual_m) & ~searched
        if bad.any():
            point_index[bad] = -1
            labeled = point_index >= 0
            cur[bad] = np.nan

    # 6. Where the state will put hidden markers (the bookkeeping below: their partners' prediction, else the
    #    fit's, else coasting), and this frame's predictions (the fit's where there is one, for all markers).
    # 7. Launch (below) the skeleton fit on the final labels when a hidden marker is left that its rigid
    #    partners cannot place (the fit will place it from the next frame on), or when the skip budget is spent.
    #    (Loose partners ask for a fit only when the whole fit is trusted, not where `_trusted_markers` trusts
    #    it per segment: that launched solves on 45 % of 135_02's frames at L2 instead of 39 %, and scored
    #    less, dev suite L3 98.540 against 98.554 %, L2 99.324 against 99.323 %.)
    source, fallback, predicted, unplaced = kernels.frame_outcome(
        point_index, reacquired, cur, has_rigid, rpred, coast, rpred if skel_pred is None else skel_pred,
        skel_pred is not None, st.ever_seen, spread0, stale, LOOSE_SPREAD_M,
        np.full(m, residual < SKELETON_TRUSTED_RMS_M))
    launch = False
    if model.has_skeleton and solver is not None:
        if unplaced or st.search_waits or st.skipped >= min(config.max_skip_frames, config.max_skip_s / dt - 1e-6):
            launch = True
            st.skipped = 0
        else:
            st.skipped += 1
    solved = launch and _launchable(labeled)

    def bookkeeping():
        # 8. Labels permuted within a segment (a wrist triad after a fast pass or a re-acquisition) are put
        #    back in the order the segment's marker layout says. Not before publishing: a relabelling waits
        #    for SHAPE_CONFIRM checks anyway (four frames apart), so one frame more costs little, and these
        #    checks are the costliest step of a frame (~0.25 ms on every SHAPE_EVERY_FRAMES-th). The state
        #    takes the new labels; this frame's published ones stay as they were. Points claimed meanwhile
        #    by subjects stepped after this one (`free` is the engine's, updated in place) are not free.
        idx, now = point_index.copy(), cur.copy()
        relabeled = np.zeros(m, bool)
        st.settled &= (idx >= 0) & (idx == carried)  # a label any other step moved, or none: unsettled
        if model.has_skeleton and st.frames % SHAPE_EVERY_FRAMES == 0:
            relabeled = _relabel_by_shape(model, st, points, idx, now)
            relabeled |= _complete_by_free_point(model, st, points, ~taken & free, idx, now)
            relabeled |= _complete_lone_label(model, st, points, ~taken & free, idx, now)
            relabeled |= _reseat_outliers(model, st, points, ~taken & free, idx, now)
            if relabeled.any():
                # the last fit followed the permuted labels (it turned the forearm half a turn to match):
                # its word on these markers is void until a fit on the new labels (launched here) comes back,
                # and its swaps of them for a while after (SHAPE_HOLD_FRAMES)
                st.skel_pred_m = None
                st.layout_hold[relabeled] = SHAPE_HOLD_FRAMES
        st.labeled &= ~relabeled  # a relabelled marker's velocity is its old one, not the jump between tracks
        # A re-acquired label the checks took off its point (another marker's) has had its partners'
        # snapshot retaken there on every frame since: it would place the marker on that point from now on,
        # 8-10 cm from where it is (a serving wrist label carried onto the finger's point, handed to the
        # finger marker: the wrist, back in view, stayed unlabeled for 30 frames, two players at L2). It
        # gets back the snapshot from before its re-acquisition. (Dev suite, 18 realizations: L3 98.380 ->
        # 98.405 %, precision 98.954 -> 98.969 %, L2 99.314 -> 99.316 %; dropping the snapshot instead, L3
        # 98.400 %; the same for labels the partners' or the model's check withdraws on probation, 98.387 %:
        # those are as often right labels on a fast limb, whose latest snapshot is the better one.)
        undone = relabeled & (idx < 0) & (st.provisional > 0)
        st.snap_m[undone] = st.snap_kept_m[undone]
        final = idx >= 0
        _commit(st, now, final, fallback, t_ns, dt)
        if launch or (relabeled.any() and model.has_skeleton and solver is not None):
            _launch(model, st, solver, now, final, t_ns)
            st.skipped = 0

    st.free_history.append((t_ns, points[~taken]))
    st.unfinished = bookkeeping
    if not defer:
        finish(st)
    return st, StepResult(
        source=source,
        point_index=point_index.astype(np.int32),
        predicted_m=predicted,
        solved=solved,
        iterations=st.fit_iterations,
        residual_m=st.fit_rms_m,
        positions_m=cur,
    )


def observe(
    model: SubjectModel, st: TrackState, cur: np.ndarray, t_ns: int, config: EngineConfig, solver=None
) -> tuple[TrackState, StepResult]:
    """Take given labels as truth (a capture system's own labels, an operator's corrections): `cur` (M, 3)
    holds the labeled positions, NaN where a marker has no label. Keeps every statistic `step` keeps."""
    collect(model, st)
    dt = min(max((t_ns - st.last_t_ns) * 1e-9, 1e-4), 0.5)
    labeled = np.isfinite(cur[:, 0])
    st.settled = labeled.copy()
    missing = ~labeled & st.ever_seen
    rpred, _, _ = rigid_predictions(st, cur, labeled, missing)
    skel_pred = _skeleton_now(st, t_ns, dt) if model.has_skeleton else None
    fallback = np.where(np.isfinite(rpred[:, :1]), rpred, st.pos_m if skel_pred is None else skel_pred)
    if model.has_skeleton and st.frames % SHAPE_EVERY_FRAMES == 0:
        learn_layout_trust(model, st, cur[None])
    _commit(st, cur, labeled, fallback, t_ns, dt)
    solved = False
    if model.has_skeleton and solver is not None and st.skipped >= min(config.max_skip_frames, 2):
        solved = _launch(model, st, solver, cur, labeled, t_ns)
        st.skipped = 0
    else:
        st.skipped += 1
    source = np.where(labeled, 3, 0).astype(np.int8)
    return st, StepResult(np.full(model.n_markers, -1, np.int32), st.pos_m.copy(), solved, st.fit_iterations, st.fit_rms_m, source, cur)


def _commit(st: TrackState, cur: np.ndarray, labeled: np.ndarray, fallback: np.ndarray, t_ns: int, dt: float) -> None:
    """Fold one frame's labels into the state: positions, velocities, partner statistics, snapshots."""
    # A velocity needs two observations. A re-acquired marker's last position is only a prediction (from
    # partners that may have been hidden too, or coasting): (cur - prediction) / dt would turn the
    # prediction's error into speed, and the next frame's NNT would follow it, through a gate it also
    # widens, onto a neighbour. So a re-acquired marker keeps its last measured velocity (decayed while
    # hidden). Velocities are smoothed lightly against noise, not so much that fast markers lag; an
    # acceleration comes from two measured velocities: at 50 Hz a serving arm's hand turns 4 cm off its
    # constant-velocity path in one frame, onto its neighbour. (A compiled loop: `kernels.commit_motion`.)
    st.pos_m, st.vel_m_s, st.acc_m_s2, st.vel_measured, st.hidden_frames = kernels.commit_motion(
        st.pos_m, st.vel_m_s, st.acc_m_s2, st.vel_measured, st.hidden_frames, st.labeled, cur, labeled, fallback,
        dt, MAX_SPEED_M_S, MAX_ACC_M_S2)
    st.acc_dt_s = dt
    st.labeled = labeled
    st.ever_seen |= labeled
    st.last_t_ns = t_ns
    st.frames += 1
    if labeled.any():
        st.last_labeled_t_ns = t_ns
    if st.frames % 2 == 0:  # the statistics move slowly: every other frame halves their O(M^2) cost
        _update_distances(st, cur, labeled)
    if st.frames % 30 == 0:
        _update_partners(st)
    _snapshot(st, cur, labeled)


def resume(st: TrackState, rows: np.ndarray, positions_m: np.ndarray) -> None:
    """Markers found outside the step (`rows`, at `positions_m` this frame: an automatic subject's trial) are
    tracked from there on the next frame, at rest."""
    st.labeled[rows] = True
    st.ever_seen[rows] = True
    st.pos_m[rows] = positions_m
    st.vel_m_s[rows] = 0.0
    st.acc_m_s2[rows] = 0.0
    st.vel_measured[rows] = False
    st.hidden_frames[rows] = 0


def finish(st: TrackState) -> None:
    """Run the bookkeeping a deferred `step` left (idempotent)."""
    if st.unfinished is not None:
        bookkeeping, st.unfinished = st.unfinished, None
        bookkeeping()


def _launchable(labeled: np.ndarray) -> bool:
    return int(np.count_nonzero(labeled)) >= 4  # fewer cannot hold a pose


def _launch(model: SubjectModel, st: TrackState, solver, cur: np.ndarray, labeled: np.ndarray, t_ns: int) -> bool:
    """Start a Gauss-Newton solve from the current pose on this frame's labels; `collect` takes its result."""
    if not _launchable(labeled):
        return False
    st.pending = (solver.launch(st.t_root_m, st.R_parent_segment, model.joint_offsets_m, model.marker_segment,
                                model.marker_offsets_m, cur, labeled), t_ns)
    return True


def collect(model: SubjectModel, st: TrackState):
    """Finish the fit launched on an earlier frame (waiting for it if need be) and take its pose, its marker
    predictions and their velocity (from the previous fit when it was recent). A failed solve keeps the
    pose: never a frozen or exploding skeleton. Returns the FitResult, or None (nothing pending, failed).
    Idempotent; in place. A deferred step's bookkeeping is done first."""
    finish(st)
    if st.pending is None:
        return None
    pending, t_ns = st.pending
    st.pending = None
    fit = pending.result()
    if not fit.ok or not np.isfinite(fit.residual_rms_m) or len(fit.predicted_m) != model.n_markers:
        st.skel_pred_m = None
        return None
    vel = np.zeros_like(fit.predicted_m)
    gap_s = (t_ns - st.skel_t_ns) * 1e-9
    if st.skel_pred_m is not None and len(st.skel_pred_m) == model.n_markers and 0 < gap_s <= SKELETON_VELOCITY_GAP_S:
        vel = (fit.predicted_m - st.skel_pred_m) / gap_s
        speed = np.linalg.norm(vel, axis=1, keepdims=True)
        vel *= np.minimum(1.0, MAX_SPEED_M_S / np.maximum(speed, 1e-9))
    st.t_root_m, st.R_parent_segment = fit.t_world_root_m, fit.R_parent_segment
    st.fit_rms_m, st.fit_iterations = fit.residual_rms_m, fit.iterations
    st.skel_pred_m, st.skel_vel_m_s, st.skel_t_ns = fit.predicted_m, vel, t_ns
    return fit


def _skeleton_now(st: TrackState, t_ns: int, dt: float) -> np.ndarray | None:
    """The latest fit's marker positions carried forward to t_ns, if that fit is at most ~2 frames old."""
    if st.skel_pred_m is None or st.skel_vel_m_s is None:
        return None
    age_s = (t_ns - st.skel_t_ns) * 1e-9
    if not 0 <= age_s <= 2.5 * dt:
        return None
    return st.skel_pred_m + st.skel_vel_m_s * age_s


def _fit(model: SubjectModel, st: TrackState, solver, cur: np.ndarray, labeled: np.ndarray):
    """One blocking Gauss-Newton solve from the current pose (calibration, refinement); on failure keep
    the pose. Any launched fit is collected first, so it cannot overwrite this one."""
    collect(model, st)
    if labeled.sum() < 4:
        return None
    fit = solver.fit(
        st.t_root_m, st.R_parent_segment, model.joint_offsets_m, model.marker_segment, model.marker_offsets_m, cur, labeled
    )
    if not fit.ok or not np.isfinite(fit.residual_rms_m):
        return None
    st.t_root_m = fit.t_world_root_m
    st.R_parent_segment = fit.R_parent_segment
    st.fit_rms_m, st.fit_iterations = fit.residual_rms_m, fit.iterations
    st.skel_pred_m = None  # a fit of another frame than the last: nothing to carry forward
    return fit
