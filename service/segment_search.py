"""Finding the markers of a segment none or few of whose markers are labeled (`tracker.step`, 3.).

A hand that moved while hidden, where the fit, with nothing to hold it, kept it; a foot back from an
occlusion, which its partners across the joint place no better than the fit: such a segment is registered
onto the unclaimed points around its joint, where a recent fit puts it (`_search_segments`,
`_around_joint`); one with too few markers in view to be placed alone, with its child around the joint it
puts the child's at (`_down_the_chain`); one whose joint is misplaced too (its parent moved unseen), by its
own calibrated layout, as a free rigid body at its bone's length from the next joint up
(`_search_free_segment`). Points a rival segment fits about as well go to neither (`_rival_fits`). With no
skeleton at all, a cluster hidden whole is found by its own layout (`_search_rigid_groups`).

Each search proposes labels, {marker: point}; `tracker.step` takes them.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

from protocol.skeleton import MIRRORS, N_SEGMENTS, PARENTS
from service import kernels
from service.partners import PARTNER_MIN_SAMPLES
from service.track_state import (
    SHAPE_LAYOUT_TOL_M,
    _PARENTS,
    SubjectModel,
    TrackState,
    _joints_m,
    _kabsch_rms,
    _norm,
    _observed_segments,
    rigid_motion,
)

SEARCH_JOINT_TOL_M = 0.03  # a point this close to a marker's distance from its joint may be it ...
SEARCH_PAIR_TOL_M = 0.012  # ... two points this close to the model distance between two of its markers ...
SEARCH_INLIER_M = 0.012  # ... and a marker with a point this close to where the registered segment puts it
#: ... or this close, where three labeled markers of its segment put it: they place it by its layout alone,
#: which skin and joint motion bend (a serving forearm's marker sat 12-21 mm from where the two wrist markers
#: and the finger put it, and stayed unlabeled in view for 34 frames: tennis, two players, at L3)
SEARCH_PLACED_INLIER_M = 0.024
#: A segment whose joint is misplaced too (its parent segment moved unseen: a whole arm swung while the
#: subject was lost) is looked for by its own layout, as a free rigid body whose joint lies this close to
#: its bone's length from the grandparent joint (`_search_free_segment`). The grandparent joint is where the
#: trunk's fit puts it, but a shoulder rides on its shoulder blade, which lifts a raised arm several
#: centimetres: serving forearms placed right had their elbows 6.7-7.7 cm beyond the upper arm's length
#: (two players at L3, a run +0.38 with them). At 8 cm rather than 5, dev suite, 18 realizations: L3 98.360 ->
#: 98.380 %, L2 99.312 -> 99.314 % (tennis L3 +0.07, two players L3 +0.03; one two-player run -1.3: a
#: forearm found mid-serve was lost to its neighbours' points on the next frame, its markers' velocities
#: unknown).
SEARCH_BONE_TOL_M = 0.08
#: ... and, when no triangle with a fourth marker places it, by its triangles one by one: the best placement
#: is taken if no disagreeing one fits about as well within this times the search's tolerances ...
RIVAL_TOL_FACTOR = 2.0
#: ... and if its triangle fits their layout within this RMS. Logged against the truth (dev files at L3,
#: 18 seeds each): with the rival rule alone, 64 placements of three taken right and 4 wrong, the wrong ones
#: at 5.1-6.7 mm and 18 right ones beyond. With this RMS and `_consensus`, on all 8 files: 78 placements
#: taken (50 of three markers, 28 of four or five), 263 labels, 1 wrong; 30 held back as ambiguous
SEARCH_THREE_RMS_M = 0.005
#: ... and, when the bone's length misses too (a serving forearm's wrist pair and finger fitted their layout to
#: 1 mm, in view, while its elbow lay 9-16 cm beyond the upper arm's length from where the trunk's fit put the
#: shoulder, and stayed unlabeled 12 frames: the shoulder blade lifts the raised arm, and a calibration on a
#: seed that bent no elbow misplaces the joint), a triangle matched within TIGHT_PAIR_TOL_M a side and
#: fitting within TIGHT_THREE_RMS_M, its joint within TIGHT_BONE_TOL_M of the bone's length and nearer its
#: own anchor than the mirror limb's, with no disagreeing placement in that reach. (Dev suite, 18
#: realizations: L3 98.588 -> 98.597 %, the two players L2 99.470 -> 99.479 %, L3 98.205 -> 98.212 %;
#: KneeltoProne and squat, seeds 0-5, unchanged.)
TIGHT_PAIR_TOL_M = 0.004
TIGHT_THREE_RMS_M = 0.0025
TIGHT_BONE_TOL_M = 0.2
#: With no skeleton (`_search_rigid_groups`), markers whose mutual distances varied less than GROUP_SD_M
#: move as one cluster; its triangle is matched to points at its distances within GROUP_PAIR_TOL_M + 3
#: sigma, its markers are placed on points within GROUP_INLIER_M, and it is taken when GROUP_MIN_PLACED
#: are (a triangle and one more), all within GROUP_REACH_M beyond the reach the distance statistics give
#: from every labeled marker (mean + 4 sigma: a limb swings out of the range it showed)
GROUP_SD_M = 0.005
GROUP_PAIR_TOL_M = 0.004
GROUP_INLIER_M = 0.008
GROUP_MIN_PLACED = 4
GROUP_REACH_M = 0.4
#: A segment with too few markers in view to be placed alone around its joint is placed with its child,
#: unlabeled too, around the joint it puts the child's at: when the two place this many markers
#: (`_down_the_chain`)
CHAIN_MIN_MARKERS = 5  # (counting the segment's labeled markers)
#: ... and so is a segment with this many markers labeled or fewer: one labeled marker and the joint leave
#: it free to turn about them (a shank: its knee marker labeled, its ankle marker lost with the foot)
CHAIN_MAX_LABELED = 1
AGREEING_PAIRS_MAX = 24  # `_agreeing_pairs` weighs at most this many pair hypotheses (typically 1-10)
CHAIN_JOINT_TOL_M = 0.06  # ... the segment's markers within this of their distance from its joint
RIVAL_JOINT_MARGIN_M = 0.05  # a search's points stay unassigned if a rival segment's joint fits within this of its own


def _search_segments(model: SubjectModel, st: TrackState, points: np.ndarray, cand: np.ndarray,
                     labeled: np.ndarray, cur: np.ndarray, lost: np.ndarray) -> dict[int, int]:
    """Which points markers `lost` (labeled on none of the last SEARCH_LOST_FRAMES frames though their segment
    should be in view) are now, {marker: point}. Their segment is registered onto the unclaimed
    points around its joint. The fit has no word on a segment none of whose markers is labeled (it keeps
    it where it was: a wrist flicked while hidden is found tens of centimetres from there), but the joint
    it hangs from is held by the parent. So: a point may be marker i if its distance from the joint matches
    |offset_i| (rotation-invariant); two such points, a pair if their distance matches the model's; the
    segment's rigid motion (Kabsch) from the joint, its labeled markers and the pair places every other
    marker, and the hypothesis placing most markers on points wins, if no other assignment does as well
    (two mirror-image markers alone stay unfound). It must place three markers, labeled ones counted
    (one lost marker of a segment with two labeled is placed where they and the joint put it). A segment
    with too few markers in view to be placed is placed with its child (`_down_the_chain`), failing that,
    if it has two markers, by both (a thigh's knee marker at its distances from the hip and from the thigh
    marker: the fit turns a thigh held by one marker about the hip, and its knee, shank and foot with it);
    one whose joint cannot pin it, by its layout alone (`_search_free_segment`)."""
    found: dict[int, int] = {}
    pw = _joints_m(model, st)
    observed = _observed_segments(model.marker_segment, labeled)
    pool = np.flatnonzero(cand)
    if len(pool) == 0:
        return found
    seg_of = model.marker_segment
    searched = np.flatnonzero(np.bincount(seg_of[lost & (seg_of >= 0)], minlength=N_SEGMENTS))  # (np.unique: 5x the time)
    unfound = lost.copy()
    for k in searched:
        idx = np.flatnonzero((seg_of == k) & st.ever_seen)
        lab, los = idx[labeled[idx]], idx[unfound[idx]]
        if len(los) == 0:
            continue  # found with its parent (`_down_the_chain`)
        scored = _around_joint(model, pw[k], lab, los, cur, points, pool)
        assignment, below = _unambiguous(scored, 0, max(3 - len(lab), 1)), {}
        if assignment is None and len(lab) <= CHAIN_MAX_LABELED:
            assignment, below = _down_the_chain(model, st, k, labeled, lost, cur, points, pool)
        if assignment is None and len(idx) == 2:  # a segment of two: both its markers placed
            assignment = _unambiguous(scored, 0, max(len(idx) - len(lab), 1))
        if assignment is None and len(lab) == 0:
            assignment = _agreeing_pairs(scored)
        if assignment is None and len(lab) == 0:
            # the joint could not pin it (its parent moved unseen too, so the joint is where the fit left
            # it: a serving arm's forearm stayed unfound for 0.7 s): its layout alone
            assignment = _search_free_segment(model, pw, points, pool, los, k, observed)
        if assignment and _rival_fits(model, pw, points, assignment, k, searched, lab, cur):
            assignment = None
        if assignment and len(lab) == 0 and k > 0 and observed[PARENTS[k]] and _mirrored(model, assignment, points, pw[k]):
            assignment = None
        if assignment:
            found.update(assignment)
            found.update(below)
            unfound[list(found)] = False
            pool = pool[~np.isin(pool, list(found.values()))]
    return found


#: (`_mirrored`) a search's assignment is refused when, with the segment's joint, another assignment of its
#: points fits under MIRROR_JOINT_GAIN times its misfit, which is MIRROR_JOINT_MIN_M or more
MIRROR_JOINT_GAIN = 0.3
MIRROR_JOINT_MIN_M = 0.015
MIRROR_MAX_MARKERS = 5  # (every permutation of up to this many markers is tried)


def _mirrored(model: SubjectModel, assignment: dict[int, int], points: np.ndarray, joint_m: np.ndarray) -> bool:
    """Whether a segment's markers found on points (`assignment`, none of them labeled before) fit the
    model, with the segment's joint where its parent holds it (`joint_m`), far better under another
    assignment of the same points. A head band's four markers keep their distances, and nearly their
    distances from the neck, under a left-right swap: a head hidden whole came back with the swap taken (the
    search's best hypotheses fitted alike, 9.3-10.2 mm), and the fit turned the head upside down to follow
    it for the rest of the run (two players at L3, seed 17). The joint is a point off the band's plane:
    registered with it, the swap misfits by centimetres. (The root's joint is no parent's: not judged.)"""
    markers = np.array(list(assignment))
    n = len(markers)
    if n < 3 or n > MIRROR_MAX_MARKERS:
        return False
    maps = np.array(list(itertools.permutations(range(n))))  # the identity first
    A = np.concatenate([np.zeros((len(maps), 1, 3)), model.marker_offsets_m[markers[maps]]], axis=1)
    B = np.broadcast_to(np.vstack([joint_m[None], points[list(assignment.values())]]), A.shape)
    rms = _kabsch_rms(A, B, np.ones(A.shape[:2], bool))
    return bool(rms[0] >= MIRROR_JOINT_MIN_M and rms[1:].min() < MIRROR_JOINT_GAIN * rms[0])


def _agreeing_pairs(scored: list) -> dict[int, int] | None:
    """Markers of a segment none of whose markers is labeled that fit around its joint two at a time but
    not three at once (a serving hand flexed at the wrist moves the finger marker off its forearm layout by
    a few centimetres): three or more points every pair of which is a hypothesis of `scored` (n placed,
    RMS, {marker: point}, ...), if no other such set places as many. {marker: point}, or None. (Two players
    at L2, seed 3: the forearm's finger, wrist and forearm markers were in view 12 frames, each pair
    placed alike, and stayed unfound. Dev suite, 18 realizations: 13 runs moved, 12 up; L3 98.536 ->
    98.540 %, L2 unchanged at 99.324 %.)"""
    # (the search is quadratic in the pairs: the best-fitting few only, as a crowded frame's hundreds
    # would cost milliseconds)
    best_first = sorted((h for h in scored if h[0] == 2 and len(h[2]) == 2), key=lambda h: h[1])
    pairs = [h[2] for h in best_first[:AGREEING_PAIRS_MAX]]
    have = {frozenset(a.items()) for a in pairs}
    sets = set()
    for seed in pairs:
        merged = dict(seed)
        for q in pairs:
            new = [(i, p) for i, p in q.items() if i not in merged]
            if len(new) == 1 and _agrees(merged, q) and all(
                    frozenset({new[0], (j, pj)}) in have for j, pj in merged.items()):
                merged[new[0][0]] = new[0][1]
        if len(merged) >= 3:
            sets.add(frozenset(merged.items()))
    if not sets:
        return None
    most = max(len(x) for x in sets)
    best = [x for x in sets if len(x) == most]
    return dict(best[0]) if len(best) == 1 else None


def _around_joint(model: SubjectModel, o: np.ndarray, lab: np.ndarray, los: np.ndarray, cur: np.ndarray,
                  points: np.ndarray, pool: np.ndarray, refine: bool = False, tol_m: float = SEARCH_JOINT_TOL_M) -> list:
    """Hypotheses (n placed, RMS, {marker: point}, R, t) for a segment whose joint is at `o`, labeled
    markers `lab` (at `cur`) and lost ones `los`, among points `pool`: (R, t) its rigid motion."""
    off = model.marker_offsets_m
    reach = _norm(points[pool] - o)
    within = reach < _norm(off[np.concatenate([lab, los])]).max() + tol_m
    near, r_near = pool[within], reach[within]
    options = {i: near[np.abs(r_near - _norm(off[i])) < tol_m] for i in los}
    base_a = np.vstack([np.zeros((1, 3)), off[lab]])
    base_b = np.vstack([o[None], cur[lab]])
    hyps = []
    if len(lab) >= 2:
        # the joint and two labeled markers fix the segment, three labeled markers alone better (the joint
        # is where the fit puts it, within its residual): one point where they put a lost marker is it
        R, t = rigid_motion(base_a[1:], base_b[1:]) if len(lab) >= 3 else rigid_motion(base_a, base_b)
        at = off[los] @ R.T + t
        gate = SEARCH_PLACED_INLIER_M if len(lab) >= 3 else SEARCH_INLIER_M
        # Three labeled markers place it alone, wherever the fit left the joint: a point's distance from that
        # joint is no test then (a fit at 35-45 mm RMS put a serving elbow 6-15 cm from where the wrist
        # marker's distance from it said, and the marker, 10-14 mm from where its three partners put it,
        # stayed unlabeled in view for 20 frames, two players at L2). Nor is the joint registered with them.
        # (Dev suite, 18 realizations: L2 99.316 -> 99.320 %, L3 98.405 -> 98.410 %, 18 runs up, 3 down by
        # 0.05 points at most.)
        # (each lost marker's candidates at once: point by point, the whole pool with three labeled markers,
        # took 1-2 ms a segment with several subjects' points unclaimed)
        for r, i in enumerate(los):
            cands = pool if len(lab) >= 3 else options[i]
            hyps += [((i, p),) for p in cands[_norm(points[cands] - at[r]) < gate]]
    elif len(lab):  # one point with the joint and a labeled marker already fixes the segment
        hyps += [((i, p),) for i in los for p in options[i]]
    for a, i in enumerate(los):
        for j in los[a + 1 :]:
            d_model = _norm(off[i] - off[j])
            for p in options[i]:
                for q in options[j]:
                    if p != q and abs(_norm(points[p] - points[q]) - d_model) < SEARCH_PAIR_TOL_M:
                        hyps.append(((i, p), (j, q)))
    if not hyps:
        return []
    # (every hypothesis registered and its other markers placed in one compiled call: one by one, each
    # cost ~60 us of numpy calls, and a frame of eight subjects offered a lost forearm hundreds)
    mk = np.full((len(hyps), 2), -1, np.int64)
    pt = np.full((len(hyps), 2), -1, np.int64)
    for r, h in enumerate(hyps):
        for c, (i, p) in enumerate(h):
            mk[r, c], pt[r, c] = i, p
    keep, rms_of, Rs, ts, placed = kernels.joint_hypotheses(
        *(np.require(a, np.float64, "C") for a in (base_a, base_b, off, points)), mk, pt,
        *(np.require(a, np.int64, "C") for a in (los, pool, near)), len(lab) >= 3, float(tol_m), SEARCH_INLIER_M)
    scored = []
    for r in np.flatnonzero(keep):
        assignment = {int(los[c]): int(placed[r, c]) for c in np.flatnonzero(placed[r] >= 0)}
        assignment.update({int(i): int(p) for i, p in hyps[r]})
        if len(set(assignment.values())) < len(assignment):
            continue
        rms, R, t = float(rms_of[r]), Rs[r], ts[r]
        if refine and len(assignment) >= 3:
            # the joint is only roughly where the parent's placement put it: the markers placed, alone, place
            # the segment again
            mk, pt = list(assignment), list(assignment.values())
            R, t = rigid_motion(off[mk], points[pt])
            assignment = _placed(off, los, R, t, points, near)
            if len(assignment) < 3 or len(set(assignment.values())) < len(assignment):
                continue
            mk, pt = list(assignment), list(assignment.values())
            rms = float(np.sqrt(np.mean(np.sum((off[mk] @ R.T + t - points[pt]) ** 2, 1))))
        scored.append((len(assignment), rms, assignment, R, t))
    return scored


def _down_the_chain(model: SubjectModel, st: TrackState, k: int, labeled: np.ndarray,
                    lost: np.ndarray, cur: np.ndarray, points: np.ndarray, pool: np.ndarray
                    ) -> tuple[dict[int, int] | None, dict[int, int]]:
    """Segment k, at most CHAIN_MAX_LABELED of whose markers are labeled, placed with its child: (k's
    {marker: point}, the child's). Its joint is held but too few of its markers are in view to tell one
    placement from another (an upper arm of two markers; a shank whose knee marker alone is labeled);
    each placement puts the child's joint (the elbow, the ankle), around which the child, unlabeled, is
    searched. The combination placing most markers wins if no other does about as well. (After a tennis
    serve a whole arm of six markers stayed unlabeled for 20 frames, in view: both segments unobserved,
    the fit had left the elbow 15-30 cm off. A foot back from an occlusion stayed unlabeled in view under
    a shank with one marker labeled, HDM05 at L3.)"""
    seg_of = model.marker_segment
    mine_idx = np.flatnonzero((seg_of == k) & st.ever_seen)
    mine_lab = mine_idx[labeled[mine_idx]]
    scored = None
    for c in np.flatnonzero(_PARENTS == k):
        idx = np.flatnonzero((seg_of == c) & st.ever_seen)
        los = idx[lost[idx]]
        if len(los) < 2 or labeled[idx].any():
            continue
        if scored is None:
            # the joint may be off by more than a search around it allows (a shoulder raised overhead in a
            # serve slides against the trunk markers that hold it): k is placed within a wider reach, and
            # the child confirms
            scored = _around_joint(model, _joints_m(model, st)[k], mine_lab, mine_idx[lost[mine_idx]], cur,
                                   points, pool, tol_m=CHAIN_JOINT_TOL_M)
        combined = []
        for n, rms, a, R, t in scored:
            rest = pool[~np.isin(pool, list(a.values()))]
            elbow = R @ model.joint_offsets_m[c] + t
            for n2, rms2, a2, *_ in _around_joint(model, elbow, los[:0], los, cur, points, rest, True, CHAIN_JOINT_TOL_M):
                combined.append((n + n2, max(rms, rms2), a, a2))
        # k's placement first, by the best combination each gives; then the child's under it, if it is
        # as clear (its markers may slide: a finger's on a serving forearm)
        combined.sort(key=lambda x: (-x[0], x[1]))
        firsts = {}
        for x in combined:
            firsts.setdefault(tuple(sorted(x[2].items())), x)
        least = CHAIN_MIN_MARKERS - len(mine_lab)
        mine = _unambiguous(list(firsts.values()), 0, least)
        if mine is not None:
            return mine, _unambiguous([(n, r, a2) for n, r, a, a2 in combined if a == mine], 0, least) or {}
    return None, {}


def _joint_residual(off: np.ndarray, o: np.ndarray, pts: np.ndarray) -> tuple[float, float]:
    """Segment markers at offsets `off` (n, 3) registered onto points `pts` (n, 3): (RMS of the markers'
    misfit, distance between where that puts the segment's joint and `o`)."""
    R, t = rigid_motion(off, pts)
    return float(np.sqrt(np.mean(np.sum((off @ R.T + t - pts) ** 2, 1)))), float(_norm(t - o))


def _rival_fits(model: SubjectModel, pw: np.ndarray, points: np.ndarray, assignment: dict[int, int], k: int,
                segments: np.ndarray, lab: np.ndarray | None = None, cur: np.ndarray | None = None) -> bool:
    """Whether the points a search gave segment k fit another segment searched for (`segments`) about as
    well: its markers' layout as well, and its joint not clearly farther. The two hands, hidden together,
    are each other's mirror image; three markers alone cannot tell them apart, and when neither elbow is
    held (the upper arms and trunk hidden too) a stale joint cannot either: the left forearm's search took
    the right hand's three points (tennis serve at L3) and kept them for 140 frames. Two points found
    beside the segment's labeled markers `lab` (at `cur`) are weighed with them. (Dev suite, 18
    realizations, with TIGHT_BONE_TOL_M: L3 98.597 -> 98.606 %, the two players L2 99.479 -> 99.486 %.
    03_rolling, both together, seeds 0-23: L2 70.91 -> 71.10 %, L3 64.60 -> 64.18 %, within its spread:
    one run moves by up to 7 points either way.)"""
    off, seg = model.marker_offsets_m, model.marker_segment
    mk = np.array(list(assignment))
    pts = points[list(assignment.values())]
    if lab is not None and len(lab) and len(mk) == 2:
        # two points alone leave the segment free to turn about them, and its joint anywhere on a circle:
        # its labeled markers (`lab`, at `cur`) pin it (a serving forearm's labeled marker and the wrist and
        # finger points found around the elbow fitted it at 1 mm, the joint 34 cm off when turned about the
        # pair alone: the other forearm's pair was a rival, and the hand stayed unlabeled for 20 frames)
        rms, joint = _joint_residual(off[np.concatenate([mk, lab])], pw[k], np.vstack([pts, cur[lab]]))
    else:
        rms, joint = _joint_residual(off[mk], pw[k], pts)
    for k2 in segments:
        idx = np.flatnonzero(seg == k2)
        if k2 == k or len(idx) < len(mk):
            continue
        # every labelling of the points from segment k2's markers at once (a compiled loop)
        limit = max(SEARCH_INLIER_M, 1.5 * rms)
        rms2, joint2 = kernels.segment_fits(off, pw[k2], pts, idx[_arrangements(len(idx), len(mk))], limit)
        if np.any((rms2 < limit) & (joint2 < joint + RIVAL_JOINT_MARGIN_M)):
            return True
    return False


@functools.lru_cache(maxsize=None)
def _arrangements(n: int, k: int) -> np.ndarray:
    """(C, k) every ordered choice of k of n indices (itertools.permutations), as an array."""
    return np.array(list(itertools.permutations(range(n), k)), dtype=np.int64).reshape(-1, k)


def _placed(off: np.ndarray, los: np.ndarray, R: np.ndarray, t: np.ndarray, points: np.ndarray,
            near: np.ndarray, inlier_m: float = SEARCH_INLIER_M) -> dict[int, int]:
    """{marker: point}: markers `los` (offsets `off`) that the segment's motion (R, t) puts within
    `inlier_m` of a point `near`, each on its nearest."""
    d = _norm((off[los] @ R.T + t)[:, None] - points[near][None])
    best = np.argmin(d, axis=1)
    ok = d[np.arange(len(los)), best] < inlier_m
    return {int(los[r]): int(near[best[r]]) for r in np.flatnonzero(ok)}


def _unambiguous(scored: list, margin: int = 0, least: int = 3) -> dict[int, int] | None:
    """The best of scored (n markers placed, RMS, assignment, ...) hypotheses, if it places `least` markers or
    more and no other assignment places as many (less `margin`) about as well."""
    if not scored:
        return None
    scored.sort(key=lambda x: (-x[0], x[1]))
    n, r, assignment = scored[0][:3]
    if n < least or any(n2 >= n - margin and a2 != assignment and r2 < 1.5 * r + 0.003 for n2, r2, a2, *_ in scored[1:]):
        return None
    return assignment


def _triangle_matches(A: np.ndarray, P: np.ndarray, tol_m: tuple) -> list:
    """Every ordered triple of points P (N, 3) at the mutual distances of the triangle A (3, 3), within
    tol_m (per side: ab, ac, bc) [m], as (R, t, residual (3,) [m]): the rigid motion (Kabsch) taking A onto
    those points, and how far each corner then lies from its point. The searches that place a segment or a
    cluster by its layout alone start here."""
    D = _norm(P[:, None] - P[None])
    ab, ac, bc = (np.abs(D - _norm(A[u] - A[v])) < tol for (u, v), tol in zip(((0, 1), (0, 2), (1, 2)), tol_m))
    matches = []
    for a, b in zip(*np.nonzero(ab)):
        for c in np.flatnonzero(ac[a] & bc[b]):
            if c == a or c == b:
                continue
            R, t = rigid_motion(A, P[[a, b, c]])
            matches.append((R, t, _norm(A @ R.T + t - P[[a, b, c]])))
    return matches


def _search_free_segment(model: SubjectModel, pw: np.ndarray, points: np.ndarray, pool: np.ndarray,
                         los: np.ndarray, k: int, observed: np.ndarray) -> dict[int, int] | None:
    """{marker: point} for segment k, none of whose markers `los` is labeled, when its joint cannot anchor
    the search (its parent moved unseen too), or None: its markers' layout is matched as a free rigid
    body. Three of its markers are matched to unclaimed points at the same mutual distances, within reach
    of the grandparent joint (the shoulder for a forearm, held by the trunk); the rigid motion must put
    the segment's joint at its bone's length from there; it then places the other markers. When the
    grandparent moved unseen too, the anchor is the first joint up the chain that an observed segment
    holds, and the joint must lie within the chain's length of it (a foot whose shank and thigh, one
    marker each, hid while the subject walked on hangs from the hip: 85_12 at L3, where the stale knee and
    ankle were 40-65 cm off and the foot stayed unlabeled). Only markers that keep their layout on the
    segment take part.

    What is taken: from the widest triangle, the hypothesis placing most markers, four or more, if no other
    places as many less one about as well (`_unambiguous`: no joint pins it, so a rival one marker short
    counts too). Failing that, where one bone pins the joint, every triangle of the lost markers is tried
    (a serving forearm's wrist pair and finger were in view for 0.5 s while its fourth marker hid with the
    upper arm, and stayed unlabeled: tennis at L3): the best placement, if its triangle fits within
    SEARCH_THREE_RMS_M, merged with every placement agreeing with it (`_consensus`), unless a disagreeing
    one fits about as well with half its support or more. Three markers are a triangle, which fits its
    mirror image (the other hand's) by a turn: only the bone's length tells the two apart, and a chain's
    reach is too loose for that (a foot's three were once matched to two of them and the shank's marker:
    HDM05 at L3, T-pose mode). Where the bone's length misses (a raised arm's shoulder lifted, a joint the
    calibration misplaced), a triangle that fits its layout tightly is taken within a wider reach, if it
    hangs nearer its own anchor than the mirror limb's and no disagreeing placement fits about as well
    (TIGHT_BONE_TOL_M)."""
    parent = PARENTS[k]
    if model.layout_rms_m is None or len(model.layout_rms_m) != model.n_markers or model.layout_offsets_m is None:
        return None  # layouts unmeasured (a calibration saved before they were kept)
    los = los[model.layout_rms_m[los] < SHAPE_LAYOUT_TOL_M]  # a marker that slides (a finger) misplaces it
    if parent < 0 or len(los) < 3:
        return None
    # the calibrated layout, not the offsets refinements on the engine's own labels may have moved (a foot
    # marker refined while labeled on a neighbour's point left the foot unfound, cmu/85_12 at L3)
    off = model.layout_offsets_m
    top, bones = parent, [_norm(model.joint_offsets_m[k])]  # up the unobserved chain to a held joint
    while PARENTS[top] >= 0 and not observed[top] and not observed[PARENTS[top]]:
        bones.append(_norm(model.joint_offsets_m[top]))
        top = PARENTS[top]
    one_bone = len(bones) == 1
    if not one_bone and len(los) < 4:
        return None
    anchor, reach = pw[top], sum(bones)
    joint = model.layout_joints_m[k]  # (where the layout is placed, the model's joint: see layout_joints_m)
    mirror = MIRRORS[top]
    mirror_anchor = pw[mirror] if mirror != top else None
    # (the joint lies within its bone's tolerance of the reach, and each marker within its offset of the joint)
    span = _norm(points[pool] - anchor)
    near = pool[span < reach + SEARCH_BONE_TOL_M + _norm(off[los]).max()]
    wide = pool[span < reach + TIGHT_BONE_TOL_M + _norm(off[los]).max()] if one_bone else near
    if len(wide) < 3:
        return None

    def area(c):
        return _norm(np.cross(off[c[1]] - off[c[0]], off[c[2]] - off[c[0]]))

    triangles = sorted(itertools.combinations(los, 3), key=area, reverse=True)

    def placements(tris, tol: float, pair_m: float = SEARCH_PAIR_TOL_M, beyond: bool = False) -> list:
        """(n placed, RMS of the triangle's fit, {marker: point}), most placed first, from the triangles
        `tris` matched within `tol` times the search's tolerances (side lengths `pair_m`, corner residuals,
        the joint off its bone's length). `beyond`: the joint within TIGHT_BONE_TOL_M of the bone's length
        instead of SEARCH_BONE_TOL_M, among the points in that reach, and nearer its own anchor than the
        mirror limb's (a triangle fits its mirror image, the other limb's, by a turn)."""
        bone_m, cand = (TIGHT_BONE_TOL_M, wide) if beyond else (SEARCH_BONE_TOL_M, near)
        scored, seen = [], set()
        for tri in tris:
            for R, t, res in _triangle_matches(off[list(tri)], points[cand], (tol * pair_m,) * 3):
                d = _norm(R @ joint + t - anchor)  # one bone: at its length; a chain: within its reach
                if res.max() > tol * 2 * SEARCH_INLIER_M or (abs(d - reach) if one_bone else d - reach) > tol * bone_m:
                    continue
                if beyond and mirror_anchor is not None and _norm(R @ joint + t - mirror_anchor) < d:
                    continue
                assignment = _placed(off, los, R, t, points, cand)
                key = tuple(sorted(assignment.items()))
                if len(set(assignment.values())) < len(assignment) or key in seen:
                    continue  # (another triangle of the same placement)
                seen.add(key)
                if len(assignment) >= 3:  # (its own corners at least: one may miss the inlier gate)
                    scored.append((len(assignment), float(np.sqrt(np.mean(res**2))), assignment))
        return sorted(scored, key=lambda x: (-x[0], x[1]))

    scored = placements(triangles[:1], 1.0) if len(los) >= 4 else []  # the widest, and a fourth marker
    if scored and scored[0][0] >= 4:
        return _unambiguous(scored, 1, 4)
    if not one_bone:
        return None
    scored = placements(triangles, 1.0)
    if not scored or scored[0][1] > SEARCH_THREE_RMS_M:
        # the bone's length missed: a tight triangle alone in reach (`TIGHT_BONE_TOL_M`)
        tight = placements(triangles, 1.0, TIGHT_PAIR_TOL_M, beyond=True)
        if not tight or tight[0][1] > TIGHT_THREE_RMS_M:
            return None
        rivals = placements(triangles, RIVAL_TOL_FACTOR, beyond=True)
        assignment, _ = _consensus(tight[0][2], rivals)
        if any(r2 < 1.5 * tight[0][1] + 0.003 and not _agrees(assignment, a2) for _, r2, a2 in rivals):
            return None
        return assignment
    # Each triangle placed alone: the placement is the best one's consensus, every placement agreeing with
    # it merged in (a forearm of five markers twisting under pronation fits no rigid layout within the
    # inlier gate, but four of its triangles each placed three of them, consistently: two players at L3,
    # the left forearm unlabeled 100 frames in view). A rival is a placement disagreeing with it about as
    # good, within RIVAL_TOL_FACTOR times the tolerances (a foot's ankle, fifth metatarsal and toe are
    # nearly isosceles: with ankle and toe swapped they fitted the search's tolerances, the true labels, 13
    # mm off in two sides, did not, and the swap was taken: cmu/135_02 at L3, the foot wrong for 500
    # frames); it makes the placement ambiguous unless its own consensus has less than half the support.
    loose = placements(triangles, RIVAL_TOL_FACTOR)
    assignment, support = _consensus(scored[0][2], loose)
    for _, r2, a2 in loose:
        if r2 < 1.5 * scored[0][1] + 0.003 and not _agrees(assignment, a2) and 2 * _consensus(a2, loose)[1] >= support:
            return None
    return assignment


def _agrees(a: dict[int, int], b: dict[int, int]) -> bool:
    """Whether two {marker: point} placements agree: no marker on two points, no point for two markers."""
    taken = {p: i for i, p in a.items()}
    return all(a.get(i, p) == p and taken.get(p, i) == i for i, p in b.items())


def _consensus(seed: dict[int, int], placements: list) -> tuple[dict[int, int], int]:
    """`seed` merged with every placement (n, RMS, {marker: point}) agreeing with it so far, best first,
    and how many placements it merged (the seed's own counted)."""
    merged, support = dict(seed), 0
    for _, _, a in placements:
        if _agrees(merged, a):
            merged.update(a)
            support += 1
    return merged, max(support, 1)  # (the seed is among them when it came from the same search)


@functools.lru_cache(maxsize=None)
def _triples(n: int) -> np.ndarray:
    """(C, 3) every choice of 3 of n indices, in itertools.combinations order."""
    return np.array(list(itertools.combinations(range(n), 3)), dtype=np.int64).reshape(-1, 3)


def _search_rigid_groups(st: TrackState, points: np.ndarray, pool: np.ndarray, labeled: np.ndarray,
                         cur: np.ndarray, lost: np.ndarray) -> dict[int, int]:
    """Which points markers `lost` are now, {marker: point}, for a subject with no skeleton (a seed taken lying
    down: numediart/03_rolling rolls on the floor, where a limb's cluster hides whole, and nothing placed it
    again once it did). Without segments, the groups are what the partner statistics say moves rigidly now:
    lost markers whose distances to one another all varied by under GROUP_SD_M. A group's layout is where its
    markers were when its first marker was last labeled (`snap_m`); its widest triangle is matched to
    unclaimed points at the same mutual distances, within the reach the distance statistics allow from every
    labeled marker (the body holds a thigh's cluster within a metre of the head, whatever the pose), and the
    rigid motion places the group's other markers. A group's best hypothesis, GROUP_MIN_PLACED markers placed
    or more (three, the triangle alone, took wrong points: 03_rolling's precision at L0 fell from 98.6 to 90 %
    in a trial), is taken if no other assignment of it does about as well (`_unambiguous`), and no other
    group's fits the same points about as well (the left hand's cluster fits the right hand's points when they
    are mirror images: the two hands stay unfound while both are lost and one is in view)."""
    sd = np.sqrt(st.dist_var_m2)
    known = st.dist_n >= PARTNER_MIN_SAMPLES
    rigid = known & (np.maximum(sd, np.sqrt(st.dist_slow_var_m2)) < GROUP_SD_M)  # now and over the long memory
    seeds = np.flatnonzero(lost & ((rigid & lost).sum(1) >= GROUP_MIN_PLACED - 1))
    if len(seeds) == 0 or len(pool) < 3:
        return {}  # (most frames: no group hidden whole, nothing to compute)
    lab = np.flatnonzero(labeled)
    d_lab = _norm(points[pool][:, None] - cur[lab][None])  # (pool, labeled) for the reach
    grouped = np.zeros(len(lost), bool)
    best = []  # per group: (n placed, RMS, {marker: point})
    for i in seeds:
        if grouped[i]:
            continue
        layout = st.snap_m[i]
        # the lost markers rigid to every member, most rigid to i first (a greedy clique)
        order = np.argsort(sd[i])
        order = order[lost[order] & ~grouped[order] & rigid[order, i] & np.isfinite(layout[order, 0]) & (order != i)]
        group = [i]
        for j in order:
            if rigid[j, group].all():
                group.append(j)
        group = np.array(group)
        if len(group) < GROUP_MIN_PLACED:
            continue
        grouped[group] = True
        off = layout[group]
        # reach: each group marker within its mean distance + 4 sigma (+ GROUP_REACH_M) of every labeled
        # marker whose distance to it is known
        bound = np.where(known[np.ix_(group, lab)], st.dist_mean_m[np.ix_(group, lab)] + 4.0 * sd[np.ix_(group, lab)]
                         + GROUP_REACH_M, np.inf)
        near = pool[(d_lab[:, None, :] <= bound[None]).all(axis=(1, 2))]
        if len(near) < 3:
            continue
        triples = _triples(len(group))  # the widest triangle
        tri = triples[np.argmax(_norm(np.cross(off[triples[:, 1]] - off[triples[:, 0]],
                                               off[triples[:, 2]] - off[triples[:, 0]])))]
        A, tri = off[list(tri)], group[list(tri)]
        tol = tuple(GROUP_PAIR_TOL_M + 3.0 * sd[tri[u], tri[v]] for u, v in ((0, 1), (0, 2), (1, 2)))
        scored = []
        for R, t, res in _triangle_matches(A, points[near], tol):
            if res.max() > GROUP_INLIER_M:
                continue
            placed = _placed(off, np.arange(len(group)), R, t, points, near, GROUP_INLIER_M)
            if len(set(placed.values())) < len(placed):
                continue
            scored.append((len(placed), float(np.sqrt(np.mean(res**2))), {int(group[r]): p for r, p in placed.items()}))
        assignment = _unambiguous(scored, 0, GROUP_MIN_PLACED)
        if assignment:
            n, r = scored[0][:2]
            best.append((n, r, assignment))
    found: dict[int, int] = {}
    for n, r, assignment in best:
        pts = set(assignment.values())
        if not any(n2 >= n - 1 and r2 < 1.5 * r + 0.003 and pts & set(a2.values()) for n2, r2, a2 in best
                   if a2 is not assignment):
            found.update(assignment)
    return found
