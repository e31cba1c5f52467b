"""Rigid partners, learned online, and what they say about a label (`tracker.step`, 2. and 3.).

Rigid partners are learned online: running statistics of every pairwise marker distance (only over
labeled frames) rank, for each marker, the partners whose distance varies least. They are kept with two
memories, ~100 frames and ~1000 (SLOW_ALPHA): the long one still sees a swap the short one has absorbed.

From them: where a marker is now (its partners' positions when it was last seen, carried onto where they
are now: `rigid_predictions`), how loosely they hold it (`_partner_sigma`), and how far its distances to
them stray from their long-run means (`distance_misfit`), which repairs swaps the rigid checks miss
(`_repair_by_distances`) and vetoes relabellings the layout checks propose (`_partners_object`).
"""

from __future__ import annotations

import numpy as np

from service import kernels
from service.track_state import TrackState, _gather

N_PARTNERS = 8
PARTNER_MIN_SAMPLES = 20  # a pair distance sampled fewer times cannot make two markers partners: its
# spread is not known yet (a sternum marker hidden through the seed took two arm markers seen with it in
# 3 frames as its most rigid partners, and was never placed again: squat)
Z_SUSPECT = 4.0  # a label whose distances to its most rigid partners stray more sigmas than this is suspect
#: ... and a re-acquisition beyond the re-acquisition gate's base from its prediction, whose three most rigid
#: partners' z, each capped at this, average more than Z_SUSPECT (`far_reacquisitions_misfit`). (Dev
#: suite, 18 realizations: L2 99.334 -> 99.338 %, precision 99.410 -> 99.415 %; L3 98.641 -> 98.640 %,
#: precision 99.081 -> 99.101 %; the tennis player's L2 precision 99.893 -> 99.903 %, accuracy +0.014. On
#: every re-acquisition, near its prediction too, the tennis files' accuracy fell: L2 -0.025, L3 -0.095.
#: T-pose mode, squat and HDM_mm, seeds 0-5: L3 -0.079, L2 unchanged; see benchmarks/CHANGES.md.)
FAR_Z_CAP = 2.0 * Z_SUSPECT
#: The partner distances are kept twice: a running mean/variance that follows the body within ~100 frames
#: (partners, weights, checks), and one with this smaller weight per update (~1000 frames), which a fresh
#: swap cannot absorb. A wrist label swapped onto a waist marker's point 1.3 cm away had widened the fast
#: statistics' spread enough to look normal within 10 frames, and stayed for 4 s (135_02 at L2); the slow
#: ones still called it 7 sigmas off, and the repair swaps it back.
SLOW_ALPHA = 0.002
_BIG = kernels.BIG  # a cost or score that must never be chosen


def _update_distances(st: TrackState, pos: np.ndarray, labeled: np.ndarray, alpha_min: float = 0.02) -> None:
    """Running mean/variance of pairwise distances among labeled markers (count-based, then EMA with weight
    alpha_min, and with SLOW_ALPHA for the long-memory pair), in place. (A compiled loop: `kernels`.)"""
    if np.count_nonzero(labeled) >= 2:
        kernels.update_distances(st.dist_n, st.dist_mean_m, st.dist_var_m2, st.dist_slow_mean_m, st.dist_slow_var_m2,
                                 pos, labeled, alpha_min, min(alpha_min, SLOW_ALPHA))


def _update_partners(st: TrackState) -> None:
    """For every marker, the K partners whose distance to it varies least (ties broken by nearness)."""
    m = len(st.pos_m)
    score = np.sqrt(st.dist_var_m2) + 0.02 * st.dist_mean_m
    score = np.where(st.dist_n >= PARTNER_MIN_SAMPLES, score, _BIG)
    np.fill_diagonal(score, _BIG)
    k = max(min(N_PARTNERS, m - 1), 0)  # (a subject of one marker has no partner)
    order = np.argsort(score, axis=1)[:, :k]
    ok = np.take_along_axis(score, order, axis=1) < _BIG
    partners = np.full((m, N_PARTNERS), -1)
    partners[:, :k] = np.where(ok, order, -1)
    st.partners = partners


def _snapshot(st: TrackState, pos: np.ndarray, labeled: np.ndarray) -> None:
    """Remember, for each labeled marker, where every labeled marker is now. Keeping all of them (not only
    the current partners) lets the partner lists change while a marker is hidden."""
    kernels.snapshot(st.snap_m, pos, labeled)


def rigid_predictions(st: TrackState, pos: np.ndarray, labeled: np.ndarray, which: np.ndarray):
    """Predict markers `which` from their rigid partners labeled now (`pos`, NaN elsewhere).

    For each marker, the partners' positions when it was last seen are carried onto their positions now by
    the best rigid transform (weighted Kabsch), and so is the marker. Partners are weighted by how rigidly
    they keep their distance to it (sigma + 3 mm of skin). Returns (pred (M, 3), spread (M,) = weighted
    RMS misfit of the partners [m], swing (M,) = how far [m] their skin wobble could turn it about their long
    axis); NaN where fewer than 3 usable partners. (A compiled loop: `kernels`.)
    """
    return kernels.rigid_predict(st.partners, st.snap_m, st.dist_var_m2, pos, labeled, which)


def _partner_sigma(st: TrackState, labeled: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """How loosely the labeled partners of markers `rows` hold them (R,) [m]: the spread of their distances to
    it, averaged with `rigid_predict`'s weights (1 / (sigma + 3 mm)^2, so the tightest partners count most).
    Three partners always fit their own snapshot closely, whatever the spread of their distances to the
    marker (`spread` says nothing then); this says how far from their prediction the marker may be."""
    part = st.partners[rows]
    ok = (part >= 0) & labeled[np.maximum(part, 0)]
    sd = np.sqrt(st.dist_var_m2[rows[:, None], np.maximum(part, 0)])
    w = np.where(ok, 1.0 / (sd + kernels.SKIN_M) ** 2, 0.0)
    return np.sqrt(np.sum(w * sd**2, axis=1) / np.maximum(np.sum(w, axis=1), 1e-12))


def _distance_stats(st: TrackState, slow: bool) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) (M, M) of the partner distances: the long-memory pair if `slow`, else the running one."""
    return (st.dist_slow_mean_m, st.dist_slow_var_m2) if slow else (st.dist_mean_m, st.dist_var_m2)


def distance_misfit(st: TrackState, cur: np.ndarray, labeled: np.ndarray, rows: np.ndarray | None = None,
                    slow: bool = False, cap: float = np.inf) -> np.ndarray:
    """How many standard deviations each labeled marker's distances to its most rigid labeled partners
    stray from their long-run means: the median z = |d - mean| / (sigma + 3 mm) over (up to) the 3
    partners with the smallest sigma that are labeled now. Unlike the rigid prediction, which follows the
    last frames, this remembers the body, so a wrong label cannot become its own reference; `slow` takes
    the long-memory statistics. With a finite `cap`, the mean of the three z each capped at `cap` where
    that is larger (`far_reacquisitions_misfit`). NaN for markers with fewer than 2 such partners."""
    mean, var = _distance_stats(st, slow)
    idx = np.arange(len(cur)) if rows is None else np.asarray(rows, dtype=np.int64)
    return kernels.distance_misfit(st.partners, st.dist_n, mean, var, cur, labeled, idx, float(cap))


def far_reacquisitions_misfit(st: TrackState, cur: np.ndarray, labeled: np.ndarray, rows: np.ndarray,
                              pred: np.ndarray, near_m: float) -> np.ndarray:
    """(len(rows),) which re-acquisitions (markers `rows`, labeled now at cur[rows]) lie farther than `near_m`
    from where they were predicted (`pred`, (M, 3)) and misfit their partners' distances by the capped mean
    (FAR_Z_CAP): a point taken in a gate widened by loose partners or time hidden needs more than a median
    of its three most rigid partners to agree. A serving right wrist's point, 10 cm from where a hidden left
    forearm marker was predicted (135 mm gate), had z 0.8, 9.0 and 3.7 against the forearm's three markers:
    the median 3.7 passed, the label held 16 frames (tennis at L2). The median alone stays the rule near the
    prediction, where one wrong partner label must not refuse a right re-acquisition."""
    far = np.linalg.norm(cur[rows] - pred[rows], axis=1) > near_m
    out = np.zeros(len(rows), bool)
    if far.any():
        out[far] = distance_misfit(st, cur, labeled, rows[far], cap=FAR_Z_CAP)[rows[far]] > Z_SUSPECT
    return out


def _misfit_at(st: TrackState, i: int, x: np.ndarray, cur: np.ndarray, labeled: np.ndarray, exclude: int = -1,
               slow: bool = False) -> float:
    """distance_misfit of marker i if it were at x (NaN with fewer than 2 usable partners)."""
    part = st.partners[i]
    part = part[(part >= 0) & (part != exclude)]
    part = part[labeled[part] & (st.dist_n[i, part] >= 10)]
    if len(part) < 2:
        return float("nan")
    mean, var = _distance_stats(st, slow)
    sigma = np.sqrt(var[i, part]) + 0.003
    best = np.argsort(sigma)[:3]
    z = np.abs(np.linalg.norm(cur[part[best]] - x, axis=1) - mean[i, part[best]]) / sigma[best]
    return float(np.median(z))


def _repair_by_distances(
    st: TrackState, point_index: np.ndarray, cur: np.ndarray, points: np.ndarray, free: np.ndarray
) -> None:
    """Where the long-run partner distances say a label is wrong (z > Z_SUSPECT), move it: swap two close
    suspects when each fits where the other is, or take a free point nearby that fits far better (the
    freed point's own marker can then re-acquire it). Catches swaps that rigid checks miss because both
    markers moved together since. Judged on the long-memory statistics first (a swap the running ones
    have absorbed), then on the running ones. In place."""
    for slow in (True, False):
        labeled = point_index >= 0
        z = distance_misfit(st, cur, labeled, slow=slow)
        sus = np.flatnonzero(z > Z_SUSPECT)  # (labeled ones: NaN for the others, and NaN compares False)
        if len(sus) == 0:
            continue
        free_idx = np.flatnonzero(free)
        for a, i in enumerate(sus):
            if point_index[i] < 0 or _swap_back(st, point_index, cur, labeled, z, i, sus[a + 1 :], slow):
                continue
            near = free_idx[np.linalg.norm(points[free_idx] - cur[i], axis=1) < 0.15] if len(free_idx) else free_idx
            if len(near):
                z_near = np.array([_misfit_at(st, i, points[p], cur, labeled, slow=slow) for p in near])
                j = int(np.nanargmin(z_near)) if np.isfinite(z_near).any() else -1
                if j >= 0 and z_near[j] < Z_SUSPECT and z_near[j] < 0.3 * z[i]:
                    free[point_index[i]] = True
                    free[near[j]] = False
                    free_idx = np.flatnonzero(free)
                    point_index[i] = near[j]
                    cur[i] = points[near[j]]


def _swap_back(st: TrackState, point_index: np.ndarray, cur: np.ndarray, labeled: np.ndarray, z: np.ndarray, i: int,
               others: np.ndarray, slow: bool) -> bool:
    """Swap suspect i's label with the first of the suspects `others` within 25 cm such that each fits
    where the other is (their misfits, z, fall under 0.3 of the sum); in place. Whether it swapped."""
    for k in others:
        if point_index[k] < 0 or np.linalg.norm(cur[i] - cur[k]) > 0.25:
            continue
        swapped = _misfit_at(st, i, cur[k], cur, labeled, exclude=k, slow=slow) + _misfit_at(st, k, cur[i], cur, labeled, exclude=i, slow=slow)
        if swapped < 0.3 * (z[i] + z[k]):
            point_index[i], point_index[k] = point_index[k], point_index[i]
            cur[[i, k]] = cur[[k, i]]
            z[i] = z[k] = 0.0
            return True
    return False


def _partners_object(st: TrackState, points: np.ndarray, cur: np.ndarray, labeled: np.ndarray,
                     proposed: np.ndarray, moved: np.ndarray) -> bool:
    """Whether the long-run partner distances object to moving the `moved` markers' labels to the points
    `proposed` gives them: they have taken a long-standing permutation in (what the layout checks undo)
    but refuse a fresh one (a layout near-symmetric under it, a skin-moved segment)."""
    z_now = distance_misfit(st, cur, labeled, moved)[moved]
    z_new = distance_misfit(st, _gather(points, proposed), proposed >= 0, moved)[moved]
    z_now, z_new = z_now[np.isfinite(z_now)], z_new[np.isfinite(z_new)]
    return bool(len(z_new) and np.median(z_new) > max(Z_SUSPECT, 2.0 * (np.median(z_now) if len(z_now) else 0.0)))
