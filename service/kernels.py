"""Compiled inner loops of the per-frame tracker (numba).

Why hand-written loops: a subject has ~40 markers, so every numpy call in the tracker (`tracker`,
`partners`, `segment_search`, `layouts`) works on arrays of a few hundred numbers and costs its ~1-3 us of
call overhead, not arithmetic. A frame made ~150 such calls (~0.5 ms of the ~1 ms a 41-marker frame took,
profiled on 135_02 at L2). The loops below do the same arithmetic in one compiled call each. Each mirrors
the numpy formulation it replaced, which its docstring names, and `tests/test_kernels.py` checks it against
that formulation.

With them a 41-marker frame (135_02 at L2, paced at 120 Hz: `python3 -m benchmarks.speed engine-cost`)
went from 1.03 to ~0.5 ms mean, measured back to back on one machine. Paced, a numpy call costs more: the
first run of a computation after the 8 ms between frames takes 1.5-3x as long on this virtual machine
(the benchmark's idle_penalty), ~5-15 us for a comparison or an `any` on a 41-element array. Folding the
rest of the labels' path into loops here (the rigid check, the un-crossing of swapped labels, probation,
the re-acquisition gates, the frame's outcome, the Hungarian pairs: ~60 calls) took the labels of a
paced frame from 0.83-0.92 to 0.64-0.66 ms mean, back to back from 0.39-0.43 to 0.24 ms (two runs each
of the same engine-cost measure, alternated, on one machine).

Compiled once per machine: `cache=True` keeps the machine code in NUMBA_CACHE_DIR (the daemon and `label`
point it at their --cache-dir/numba), else beside this file; `warm_up` loads or compiles every kernel
(~6 s cold, ~0.2 s from the cache) before a daemon says it is ready. Fixed types, as for the jitted solve:
the tracker passes the arrays in one layout and dtype, so each kernel compiles once (a test checks it).
"""

from __future__ import annotations

import math
import time

import numba
import numpy as np
from scipy.optimize import linear_sum_assignment

_jit = numba.njit(cache=True, nogil=True, fastmath=False)

SKIN_M = 0.003  # added to a pair distance's sigma: skin and marker wobble no statistic catches
BIG = 1e9  # the cost of a pair the Hungarian method must not take
#: A pair's Hungarian cost is d^2/g^2 + GATE_LOG_WEIGHT * ln g: 2/9 of the negative log-likelihood of the
#: point under a 3-D Gaussian prediction of sigma g/3, less a constant. The ln g term matters only where
#: markers compete for fewer points: at the same d/g, a marker its predictors place sharply (a waist marker
#: held by the pelvis, g = 7 cm) takes the point before one placed loosely (a hand hidden for a while,
#: g = 13 cm). With d^2/g^2 alone, the hand took the waist point on 135_02 (L3, seed 7) and the left arm's
#: labels slid along it for 20 s. Over 18 corruption seeds of the 8 dev files it lifted L3 accuracy 97.80
#: -> 97.89 % (135_02: 97.70 -> 98.13 %), L2 unchanged (99.21 %).
GATE_LOG_WEIGHT = 2.0 / 3.0


@_jit
def _dist2(P, i, Q, j):
    """|P[i] - Q[j]|^2 for rows of two (N, 3) arrays."""
    return (P[i, 0] - Q[j, 0]) ** 2 + (P[i, 1] - Q[j, 1]) ** 2 + (P[i, 2] - Q[j, 2]) ** 2


@_jit
def track_predictions(pos, vel, acc, labeled, dt, use_acc, gate_m):
    """Where each marker labeled last frame should be now (constant velocity, plus the acceleration when
    `use_acc`), its speed, and its tracking gate (gate_m + 35 % of its step; 0 for the others): returns
    pred (M, 3), speed (M,), gates (M,). (tracker.step, 1.)"""
    m = pos.shape[0]
    pred = np.empty((m, 3))
    speed = np.empty(m)
    gates = np.zeros(m)
    for i in range(m):
        v2 = 0.0
        for c in range(3):
            pred[i, c] = pos[i, c] + vel[i, c] * dt
            if use_acc:
                pred[i, c] += 0.5 * dt * dt * acc[i, c]
            v2 += vel[i, c] * vel[i, c]
        speed[i] = math.sqrt(v2)
        if labeled[i]:
            gates[i] = gate_m + 0.35 * speed[i] * dt
    return pred, speed, gates


@_jit
def track_labels(points, rows, cols, contested, pred, speed, dt, m, check_m, ever_seen, check_phase, check_every):
    """The tracked labels (marker rows[k] on point cols[k]) as point_index (M,) (-1: none), positions cur
    (M, 3) (NaN: none) and labeled (M,), and which markers (ever seen) the rigid check looks at: the
    unlabeled ones, a label that was a choice (`contested`) or whose point is more than check_m + 10 % of
    the marker's step from where it was heading (a ghost caught in the gate as the marker vanished), and
    every check_every-th marker from check_phase. (tracker.step, 1.)"""
    point_index = np.full(m, -1)
    cur = np.full((m, 3), np.nan)
    labeled = np.zeros(m, np.bool_)
    check = np.zeros(m, np.bool_)
    for k in range(rows.shape[0]):
        i, j = rows[k], cols[k]
        point_index[i] = j
        labeled[i] = True
        for c in range(3):
            cur[i, c] = points[j, c]
        check[i] = contested[k] or math.sqrt(_dist2(points, j, pred, i)) > check_m + 0.1 * speed[i] * dt
    for i in range(m):
        check[i] = ever_seen[i] and (check[i] or not labeled[i] or i % check_every == check_phase)
    return point_index, cur, labeled, check


@_jit
def carried_labels(point_index, cur, pred, gates, speed, dt, slide_share):
    """The tracked labels (point_index, cur from `track_labels`) carried on with no choice: no other
    labeled marker's point inside the marker's gate around its prediction, and a step (speed * dt) no longer
    than slide_share of the way to the nearest other labeled point; -1 elsewhere. Replaces the numpy
    formulation `rival = norm(cur[None] - pred[:, None]) < gates[:, None]` (diagonal off), `slid = speed * dt
    > slide_share * min over others of norm(cur[None] - cur[:, None])`, `where(rival.any(1) | slid, -1,
    point_index)`. (tracker.step, 1.: `TrackState.settled`)"""
    m = point_index.shape[0]
    out = point_index.copy()
    for i in range(m):
        if point_index[i] < 0:
            continue
        g2 = gates[i] * gates[i]
        near2 = math.inf
        for j in range(m):
            if j == i or point_index[j] < 0:
                continue
            if _dist2(cur, j, pred, i) < g2:
                out[i] = -1
                break
            near2 = min(near2, _dist2(cur, j, cur, i))
        if out[i] >= 0 and speed[i] * dt > slide_share * math.sqrt(near2):
            out[i] = -1
    return out


@_jit
def rigid_check(cur, rpred, spread, swing, labeled, max_swing, check_m):
    """The rigid check of the tracked labels against their partners' predictions (`rigid_predict`): returns
    has_rigid (M,) (a prediction exists), spread0 (M,) (its spread, 0 where none), err (M,) (a labeled
    marker's distance to a steady prediction, one whose swing is at most max_swing and so may withdraw a
    label; else 0) and bad (M,) (err over check_m + 4 spread0). Replaces the numpy formulation `has_rigid
    = isfinite(rpred[:, 0])`, `spread0 = where(has_rigid, spread, 0)`, `steady = has_rigid & (swing <=
    max_swing)`, `err = where(labeled & steady, norm(cur - rpred), 0)`, `bad = labeled & steady & (err >
    check_m + 4 spread0)`. (tracker.step, 2.)"""
    m = cur.shape[0]
    has_rigid = np.zeros(m, np.bool_)
    spread0 = np.zeros(m)
    err = np.zeros(m)
    bad = np.zeros(m, np.bool_)
    for i in range(m):
        if not math.isfinite(rpred[i, 0]):
            continue
        has_rigid[i] = True
        spread0[i] = spread[i]
        if labeled[i] and swing[i] <= max_swing:
            err[i] = math.sqrt(_dist2(cur, i, rpred, i))
            bad[i] = err[i] > check_m + 4.0 * spread0[i]
    return has_rigid, spread0, err, bad


@_jit
def unswap(point_index, cur, pred, err, tol_m):
    """Swap the labels of two markers when each sits where the other is predicted: among the markers whose
    err (distance to their prediction; 0 for unlabeled ones) is over tol_m, pairs whose crossed distances
    (|cur[b] - pred[a]| + |cur[a] - pred[b]|) are under half their straight ones (err[a] + err[b]), the
    best (lowest crossed / straight) first, each marker once. point_index, cur and err (0 for a swapped
    marker) in place; True if any pair was swapped. Replaces the numpy formulation that scored all pairs
    at once and took them greedily in `argsort` order (tracker._unswap)."""
    m = cur.shape[0]
    sus = np.empty(m, np.int64)
    n = 0
    for i in range(m):
        if err[i] > tol_m:
            sus[n] = i
            n += 1
    if n < 2:
        return False
    score = np.full((n, n), np.inf)
    for a in range(n):
        for b in range(a + 1, n):
            i, k = sus[a], sus[b]
            crossed = math.sqrt(_dist2(cur, k, pred, i)) + math.sqrt(_dist2(cur, i, pred, k))
            straight = err[i] + err[k]
            if crossed < 0.5 * straight:
                score[a, b] = crossed / straight
    swapped = False
    while True:  # greedy: the best pair left whose markers are both unswapped
        best, ba, bb = np.inf, -1, -1
        for a in range(n):
            if err[sus[a]] == 0.0:
                continue
            for b in range(a + 1, n):
                if score[a, b] < best and err[sus[b]] != 0.0:
                    best, ba, bb = score[a, b], a, b
        if ba < 0:
            return swapped
        i, k = sus[ba], sus[bb]
        point_index[i], point_index[k] = point_index[k], point_index[i]
        for c in range(3):
            cur[i, c], cur[k, c] = cur[k, c], cur[i, c]
        err[i] = err[k] = 0.0
        swapped = True


@_jit
def far_from_fit(rpred, ref, placed, labeled, partners, segment, same_m, cross_m):
    """Markers `placed` (hidden, with a rigid prediction) whose partners place them farther from the
    skeleton fit's `ref` than same_m when a labeled partner is on their own segment, else cross_m (NaN in
    ref: not far). Replaces the numpy formulation, over `placed` rows: `same = ((part >= 0) & labeled[part]
    & (segment[part] == segment[:, None])).any(1)`, `norm(rpred - ref) > where(same, same_m, cross_m)`.
    (tracker.step, 4.: stale predictions)"""
    m = rpred.shape[0]
    far = np.zeros(m, np.bool_)
    for i in range(m):
        if not placed[i]:
            continue
        same = False
        for k in range(partners.shape[1]):
            p = partners[i, k]
            if p >= 0 and labeled[p] and segment[p] == segment[i]:
                same = True
                break
        far[i] = math.sqrt(_dist2(rpred, i, ref, i)) > (same_m if same else cross_m)
    return far


@_jit
def reacquire_gates(rpred, has_rigid, spread0, stale, missing, skel, use_fit, fit_trusted, hidden, dt, gate_m, cap_m,
                    loose_m, widen_s, max_widen):
    """Where to look for each hidden marker (`missing`), and how far: returns pred (M, 3) (NaN: nowhere),
    gate (M,) (0 for markers not missing) and use_skel (M,) (placed by the fit). Rigid partners place a
    marker, gate 0.8 gate_m + 3 spread0 (at most cap_m); with `use_fit`, the fit's `skel` places those
    partners cannot, and, where the fit is trusted (`fit_trusted` (M,)), those whose partners are loose
    (spread0 over loose_m) or `stale`, gate gate_m widened by the time hidden (1 + hidden dt / widen_s, at
    most max_widen).
    Replaces the numpy formulation `pred = where(has_rigid, rpred, nan)`, `gate = where(has_rigid,
    minimum(0.8 gate_m + 3 spread0, cap_m), 0)`, `loose = has_rigid & ((spread0 > loose_m) | stale) &
    fit_trusted`, `use_skel = missing & (~has_rigid | loose)` (with `use_fit`), `pred[use_skel] =
    skel[use_skel]`, `gate[use_skel] = gate_m widen[use_skel]`, `gate = where(missing, gate, 0)`.
    (tracker.step, 4.)"""
    m = rpred.shape[0]
    pred = np.full((m, 3), np.nan)
    gate = np.zeros(m)
    use_skel = np.zeros(m, np.bool_)
    for i in range(m):
        if not missing[i]:
            if has_rigid[i]:
                for c in range(3):
                    pred[i, c] = rpred[i, c]
            continue
        loose = has_rigid[i] and (spread0[i] > loose_m or stale[i]) and fit_trusted[i]
        if use_fit and (not has_rigid[i] or loose):
            use_skel[i] = True
            for c in range(3):
                pred[i, c] = skel[i, c]
            gate[i] = gate_m * (1.0 + min(hidden[i] * dt / widen_s, max_widen - 1.0))
        elif has_rigid[i]:
            for c in range(3):
                pred[i, c] = rpred[i, c]
            gate[i] = min(0.8 * gate_m + 3.0 * spread0[i], cap_m)
    return pred, gate, use_skel


@_jit
def frame_outcome(point_index, reacquired, cur, has_rigid, rpred, coast, skel, use_fit, ever_seen, spread0, stale,
                  loose_m, fit_trusted):
    """The frame's outcome for a subject (labeled: point_index >= 0): source (M,) int8 (0 none, 1 tracked, 2
    re-acquired), fallback (M, 3) (where the state puts an unlabeled marker: its partners' prediction, else the
    fit's with `use_fit`, else `coast`), predicted (M, 3) (a labeled marker at its fit position with `use_fit`,
    else at its point; the others at fallback), and whether the fit is wanted (a hidden marker no partners place,
    or whose partners are loose where the fit is trusted (`fit_trusted` (M,)), or stale). Replaces the numpy
    formulation `fallback = where(has_rigid, rpred, coast)`, `fallback = where(~has_rigid, skel, fallback)`
    (use_fit), `predicted = where(labeled, skel if use_fit else cur, fallback)`, `source = where(labeled,
    where(reacquired, 2, 1), 0)`, `(~labeled & ever_seen & (~has_rigid | (spread0 > loose_m) & fit_trusted |
    stale)).any()`. (tracker.step, 6. and 7.)"""
    m = cur.shape[0]
    source = np.zeros(m, np.int8)
    fallback = np.empty((m, 3))
    predicted = np.empty((m, 3))
    unplaced = False
    for i in range(m):
        labeled = point_index[i] >= 0
        if labeled:
            source[i] = 2 if reacquired[i] else 1
        elif ever_seen[i] and (not has_rigid[i] or (spread0[i] > loose_m and fit_trusted[i]) or stale[i]):
            unplaced = True
        for c in range(3):
            if has_rigid[i]:
                fallback[i, c] = rpred[i, c]
            elif use_fit:
                fallback[i, c] = skel[i, c]
            else:
                fallback[i, c] = coast[i, c]
            if labeled:
                predicted[i, c] = skel[i, c] if use_fit else cur[i, c]
            else:
                predicted[i, c] = fallback[i, c]
    return source, fallback, predicted, unplaced


@_jit
def rigid_predict(partners, snap, dist_var, pos, labeled, which):
    """For each marker i where `which[i]`, carry its partners' positions when it was last seen
    (`snap[i, j]`) onto their positions now (`pos`, labeled ones) by the weighted best rigid motion
    (Kabsch, weights 1 / (sigma + 3 mm)^2), and the marker with them. Returns pred (M, 3) and spread (M,),
    the partners' weighted RMS misfit, and swing (M,), how far [m] skin wobble (SKIN_M) could turn the
    marker about the partners' long axis (large when they lie nearly in a line); NaN where fewer than 3
    partners are usable.
    (partners.rigid_predictions)"""
    m = pos.shape[0]
    n_part = partners.shape[1]
    pred = np.full((m, 3), np.nan)
    spread = np.full(m, np.nan)
    swing = np.full(m, np.nan)
    src = np.empty((n_part, 3))
    dst = np.empty((n_part, 3))
    wt = np.empty(n_part)
    H = np.empty((3, 3))
    for i in range(m):
        if not which[i] or np.isnan(snap[i, i, 0]):
            continue
        n = 0
        for k in range(n_part):
            j = partners[i, k]
            if j < 0 or not labeled[j] or np.isnan(snap[i, j, 0]):
                continue
            for c in range(3):
                src[n, c] = snap[i, j, c]
                dst[n, c] = pos[j, c]
            wt[n] = 1.0 / (math.sqrt(dist_var[i, j]) + SKIN_M) ** 2
            n += 1
        if n < 3:
            continue
        wsum = 0.0
        cs = np.zeros(3)
        cd = np.zeros(3)
        for k in range(n):
            wsum += wt[k]
            for c in range(3):
                cs[c] += wt[k] * src[k, c]
                cd[c] += wt[k] * dst[k, c]
        cs /= wsum
        cd /= wsum
        H[:] = 0.0
        sq = 0.0
        for k in range(n):
            for a in range(3):
                da = src[k, a] - cs[a]
                sq += wt[k] * (da * da + (dst[k, a] - cd[a]) ** 2)
                for b in range(3):
                    H[a, b] += wt[k] * da * (dst[k, b] - cd[b])
        # A partner set that is nearly a line (a knee, a thigh and a shoulder marker placing a foot) leaves the
        # turn about that line to its markers' skin wobble, and a far marker swings with it: the wobble
        # times the lever, over the set's extent about its long axis (sqrt of its two lesser variances).
        S = np.zeros((3, 3))
        for k in range(n):
            for a in range(3):
                for b in range(3):
                    S[a, b] += wt[k] * (src[k, a] - cs[a]) * (src[k, b] - cs[b]) / wsum
        lever = math.sqrt((snap[i, i, 0] - cs[0]) ** 2 + (snap[i, i, 1] - cs[1]) ** 2 + (snap[i, i, 2] - cs[2]) ** 2)
        e1 = _extreme_eigenvalues(S[0, 0], S[1, 1], S[2, 2], S[0, 1], S[0, 2], S[1, 2])[0]
        swing[i] = SKIN_M * lever / math.sqrt(max(S[0, 0] + S[1, 1] + S[2, 2] - e1, 1e-12))
        R = _rotation_of(H)
        trace = 0.0
        for a in range(3):
            for b in range(3):
                trace += R[a, b] * H[b, a]
        spread[i] = math.sqrt(max(sq - 2.0 * trace, 0.0) / wsum)
        for a in range(3):
            acc = cd[a]
            for b in range(3):
                acc += R[a, b] * (snap[i, i, b] - cs[b])
            pred[i, a] = acc
    return pred, spread, swing


@_jit
def _extreme_eigenvalues(m00, m11, m22, m01, m02, m12):
    """(largest, smallest) eigenvalue of the symmetric 3 x 3 matrix with these entries, in closed form
    (the trigonometric solution of the characteristic cubic)."""
    q = (m00 + m11 + m22) / 3.0
    d0, d1, d2 = m00 - q, m11 - q, m22 - q
    p6 = math.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (m01 * m01 + m02 * m02 + m12 * m12)) / 6.0)
    if p6 <= 0:
        return q, q
    det_shifted = d0 * (d1 * d2 - m12 * m12) - m01 * (m01 * d2 - m12 * m02) + m02 * (m01 * m12 - d1 * m02)
    phi = math.acos(min(max(det_shifted / (2.0 * p6**3), -1.0), 1.0)) / 3.0
    return q + 2.0 * p6 * math.cos(phi), q + 2.0 * p6 * math.cos(phi + 2.0 * math.pi / 3.0)


@_jit
def _det(X):
    return (X[0, 0] * (X[1, 1] * X[2, 2] - X[1, 2] * X[2, 1]) - X[0, 1] * (X[1, 0] * X[2, 2] - X[1, 2] * X[2, 0])
            + X[0, 2] * (X[1, 0] * X[2, 1] - X[1, 1] * X[2, 0]))


@_jit
def _rotation_of(H):
    """The rotation R maximising trace(R H) (Kabsch): V U^T for H = U S V^T, the orthogonal polar factor
    of H^T. By scaled Newton iteration X <- (g X + X^-T / g) / 2, g = |det X|^(-1/3), which converges
    quadratically in ~6 steps of 3 x 3 arithmetic: ~10x cheaper than LAPACK's SVD of a 3 x 3 matrix. A
    reflection (det H <= 0, the partners nearly collinear or mirrored) goes to the SVD, which flips the
    least significant axis."""
    X = H.T.copy()
    d = _det(X)
    # (only where H is well conditioned: near-degenerate partners, collinear or coplanar, leave the
    # rotation ill-determined, and there the SVD's choice is the reference)
    if d > 1e-30 * (np.abs(X).max() ** 3 + 1e-300):
        C = np.empty((3, 3))
        for _ in range(30):
            # X^-T = cofactor(X) / det(X)
            C[0, 0] = X[1, 1] * X[2, 2] - X[1, 2] * X[2, 1]
            C[0, 1] = X[1, 2] * X[2, 0] - X[1, 0] * X[2, 2]
            C[0, 2] = X[1, 0] * X[2, 1] - X[1, 1] * X[2, 0]
            C[1, 0] = X[0, 2] * X[2, 1] - X[0, 1] * X[2, 2]
            C[1, 1] = X[0, 0] * X[2, 2] - X[0, 2] * X[2, 0]
            C[1, 2] = X[0, 1] * X[2, 0] - X[0, 0] * X[2, 1]
            C[2, 0] = X[0, 1] * X[1, 2] - X[0, 2] * X[1, 1]
            C[2, 1] = X[0, 2] * X[1, 0] - X[0, 0] * X[1, 2]
            C[2, 2] = X[0, 0] * X[1, 1] - X[0, 1] * X[1, 0]
            d = X[0, 0] * C[0, 0] + X[0, 1] * C[0, 1] + X[0, 2] * C[0, 2]
            if d <= 0.0:
                break
            g = d ** (-1.0 / 3.0)
            change = 0.0
            for a in range(3):
                for b in range(3):
                    new = 0.5 * (g * X[a, b] + C[a, b] / (g * d))
                    change += (new - X[a, b]) ** 2
                    X[a, b] = new
            if change < 1e-24:
                return X
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if _det(R) < 0:  # a reflection: flip the least significant axis
        V = Vt.T.copy()
        V[:, 2] *= -1.0
        R = V @ U.T
    return R


@_jit
def rigid_motion(a, b):
    """The rotation R (3, 3) and translation t (3,) that best take points a (N, 3) onto b (N, 3), b ~ R a + t
    (Kabsch; `_rotation_of`). (calibration.rigid_motion, for the tracker's searches: ~2 us a call against
    ~45 us, and a lost subject's search makes hundreds)"""
    n = a.shape[0]
    R = np.eye(3)
    t = np.zeros(3)
    if n == 0:
        return R, t
    ca = np.zeros(3)
    cb = np.zeros(3)
    for j in range(n):
        for k in range(3):
            ca[k] += a[j, k]
            cb[k] += b[j, k]
    ca /= n
    cb /= n
    H = np.zeros((3, 3))
    for j in range(n):
        for x in range(3):
            for y in range(3):
                H[x, y] += (a[j, x] - ca[x]) * (b[j, y] - cb[y])
    R = _rotation_of(H)
    for x in range(3):
        t[x] = cb[x]
        for y in range(3):
            t[x] -= R[x, y] * ca[y]
    return R, t


@_jit
def distance_misfit(partners, dist_n, mean, var, cur, labeled, rows, cap):
    """The median z = |d - mean| / (sigma + 3 mm) of each marker in `rows` over (up to) its 3 partners
    with the smallest sigma among those labeled now and sampled at least 10 times; NaN with fewer than
    2 such partners or when the marker is not labeled. With a finite `cap`, the mean of those z, each
    capped at `cap`, where it is larger. Returns (M,), NaN but at `rows`. (partners.distance_misfit)"""
    n_rows = rows.shape[0]
    n_part = partners.shape[1]
    out = np.full(cur.shape[0], np.nan)
    sig = np.empty(n_part)
    z = np.empty(n_part)
    for r in range(n_rows):
        i = rows[r]
        if not labeled[i]:
            continue
        n = 0
        for k in range(n_part):
            j = partners[i, k]
            if j < 0 or not labeled[j] or dist_n[i, j] < 10:
                continue
            sig[n] = math.sqrt(var[i, j]) + SKIN_M
            d = math.sqrt(_dist2(cur, i, cur, j))
            z[n] = abs(d - mean[i, j]) / sig[n]
            n += 1
        if n < 2:
            continue
        # the 3 smallest sigmas (first found wins a tie), then the median of their z (the lower of two)
        take = min(n, 3)
        best = np.empty(take)
        used = np.zeros(n, np.bool_)
        for t in range(take):
            b = -1
            for k in range(n):
                if not used[k] and (b < 0 or sig[k] < sig[b]):
                    b = k
            used[b] = True
            best[t] = z[b]
        best.sort()
        out[i] = best[(take - 1) // 2]
        if cap < np.inf:
            capped = 0.0
            for t in range(take):
                capped += min(best[t], cap)
            out[i] = max(out[i], capped / take)
    return out


@_jit
def probation(partners, dist_n, mean, var, cur, labeled, provisional, layout_hold, z_max):
    """The labels on probation (labeled, provisional > 0) whose `distance_misfit` is over z_max, and the
    probation and layout-hold counts one frame on (less one, not below 0): returns (wrong (M,),
    provisional, layout_hold). Replaces the numpy formulation `on = labeled & (provisional > 0)`, `wrong =
    on & (distance_misfit(..., flatnonzero(on)) > z_max)`, `maximum(provisional - 1, 0)`,
    `maximum(layout_hold - 1, 0)`. (tracker.step, 2.)"""
    m = cur.shape[0]
    on = np.zeros(m, np.int64)
    n = 0
    for i in range(m):
        if labeled[i] and provisional[i] > 0:
            on[n] = i
            n += 1
    z = distance_misfit(partners, dist_n, mean, var, cur, labeled, on[:n], np.inf)
    wrong = np.zeros(m, np.bool_)
    for r in range(n):
        wrong[on[r]] = z[on[r]] > z_max
    return wrong, np.maximum(provisional - 1, 0), np.maximum(layout_hold - 1, 0)


@_jit
def label_errors(cur, pred, use):
    """|cur - pred| (M,) where `use`, else 0. Replaces the numpy formulation `norm(where(use[:, None], cur -
    pred, 0), axis=1)`. (tracker.step, 3. and 5.)"""
    m = cur.shape[0]
    err = np.zeros(m)
    for i in range(m):
        if use[i]:
            err[i] = math.sqrt(_dist2(cur, i, pred, i))
    return err


@_jit
def update_distances(dist_n, mean, var, slow_mean, slow_var, pos, labeled, alpha_min, slow_alpha):
    """Running mean and variance of the distances between labeled markers, in place: a plain mean over
    the first 1/alpha samples, then an exponential one with weight alpha_min (slow_alpha for the
    long-memory pair). (partners._update_distances)"""
    m = pos.shape[0]
    for i in range(m):
        if not labeled[i]:
            continue
        for j in range(m):
            if not labeled[j]:
                continue
            d = math.sqrt(_dist2(pos, i, pos, j))
            n = dist_n[i, j] + 1
            dist_n[i, j] = n
            first = 1.0 / n
            alpha = max(first, alpha_min)
            delta = d - mean[i, j]
            mean[i, j] += alpha * delta
            var[i, j] = (1.0 - alpha) * (var[i, j] + alpha * delta * delta)
            alpha = max(first, slow_alpha)
            delta = d - slow_mean[i, j]
            slow_mean[i, j] += alpha * delta
            slow_var[i, j] = (1.0 - alpha) * (slow_var[i, j] + alpha * delta * delta)


@_jit
def _misfit(H, sq, cnt):
    """RMS misfit of the best rigid motion from the centred cross-covariance H (3, 3), the centred points'
    summed squares sq and their count: the optimal trace is s1 + s2 + sign(det H) s3 over H's singular
    values, the square roots of H^T H's eigenvalues, solved in closed form (the trigonometric solution of
    the characteristic cubic)."""
    m00 = H[0, 0] ** 2 + H[1, 0] ** 2 + H[2, 0] ** 2  # M = H^T H
    m11 = H[0, 1] ** 2 + H[1, 1] ** 2 + H[2, 1] ** 2
    m22 = H[0, 2] ** 2 + H[1, 2] ** 2 + H[2, 2] ** 2
    m01 = H[0, 0] * H[0, 1] + H[1, 0] * H[1, 1] + H[2, 0] * H[2, 1]
    m02 = H[0, 0] * H[0, 2] + H[1, 0] * H[1, 2] + H[2, 0] * H[2, 2]
    m12 = H[0, 1] * H[0, 2] + H[1, 1] * H[1, 2] + H[2, 1] * H[2, 2]
    q = (m00 + m11 + m22) / 3.0
    e1, e3 = _extreme_eigenvalues(m00, m11, m22, m01, m02, m12)
    s1 = math.sqrt(max(e1, 0.0))
    s2 = math.sqrt(max(3.0 * q - e1 - e3, 0.0))
    s3 = math.sqrt(max(e3, 0.0))
    det = (H[0, 0] * (H[1, 1] * H[2, 2] - H[1, 2] * H[2, 1]) - H[0, 1] * (H[1, 0] * H[2, 2] - H[1, 2] * H[2, 0])
           + H[0, 2] * (H[1, 0] * H[2, 1] - H[1, 1] * H[2, 0]))
    sign = 1.0 if det > 0 else (-1.0 if det < 0 else 0.0)
    return math.sqrt(max(sq - 2.0 * (s1 + s2 + sign * s3), 0.0) / cnt)


@_jit
def kabsch_rms(A, B, w):
    """RMS misfit (C,) of the best rigid motion taking A onto B, both (C, N, 3), over the points where w
    (C, N) is True (`_misfit`). (track_state._kabsch_rms)"""
    n_c, n_p = A.shape[0], A.shape[1]
    out = np.empty(n_c)
    H = np.empty((3, 3))
    for c in range(n_c):
        cnt = 0
        ca = np.zeros(3)
        cb = np.zeros(3)
        for p in range(n_p):
            if w[c, p]:
                cnt += 1
                for k in range(3):
                    ca[k] += A[c, p, k]
                    cb[k] += B[c, p, k]
        if cnt == 0:
            out[c] = np.nan
            continue
        ca /= cnt
        cb /= cnt
        H[:] = 0.0
        sq = 0.0
        for p in range(n_p):
            if not w[c, p]:
                continue
            for a in range(3):
                da = A[c, p, a] - ca[a]
                db = B[c, p, a] - cb[a]
                sq += da * da + db * db
                for b in range(3):
                    H[a, b] += da * (B[c, p, b] - cb[b])
        out[c] = _misfit(H, sq, cnt)
    return out


@_jit
def gated_pairs(pred, gates, points, cand):
    """The (marker, point) pairs within the markers' gates: marker i (finite pred[i], gates[i] > 0) and
    candidate point j (cand[j]) with |pred[i] - points[j]|^2 < gates[i]^2. Returns (rows, cols, cost,
    n_row, n_col): with no choice to make (each marker with a point in its gate has one, and no point is in
    two gates) the pairs themselves, rows (P,) and cols (P,) with cost (0, 0); otherwise the markers and
    points that have any pair, rows (R,) and cols (C,), cost (R, C) = d^2 / gate^2 + GATE_LOG_WEIGHT *
    ln(gate) (BIG outside the gate) for the Hungarian method, and n_row (R,) / n_col (C,) the pairs each takes part in. (tracker._assign)"""
    m, n = pred.shape[0], points.shape[0]
    n_row = np.zeros(m, np.int64)
    n_col = np.zeros(n, np.int64)
    first = np.full(m, -1)
    for i in range(m):
        g = gates[i]
        if not g > 0 or not np.isfinite(pred[i, 0]):
            continue
        g2 = g * g
        for j in range(n):
            if cand[j]:
                d2 = _dist2(pred, i, points, j)
                if d2 < g2:
                    n_row[i] += 1
                    n_col[j] += 1
                    if first[i] < 0:
                        first[i] = j
    rows = np.flatnonzero(n_row)
    cols = np.flatnonzero(n_col)
    if n_row.sum() == len(rows) == len(cols):
        return rows, first[rows], np.empty((0, 0)), n_row[rows], np.ones(len(rows), np.int64)
    cost = np.full((len(rows), len(cols)), BIG)
    col_of = np.full(n, -1)
    col_of[cols] = np.arange(len(cols))
    for r in range(len(rows)):
        i = rows[r]
        g2 = gates[i] * gates[i]
        sharp = GATE_LOG_WEIGHT * math.log(gates[i])
        for j in cols:
            d2 = _dist2(pred, i, points, j)
            if d2 < g2:
                cost[r, col_of[j]] = d2 / g2 + sharp
    return rows, cols, cost, n_row[rows], n_col[cols]


@_jit
def assigned(rows, cols, cost, n_row, n_col, r, c):
    """The Hungarian method's pairs (r, c) of `gated_pairs`' cost matrix as (marker, point, contested)
    arrays: pairs at cost BIG (outside the gates) dropped; contested where the marker had another point in
    its gate or the point was in another marker's gate. Replaces the numpy formulation `keep = cost[r, c] <
    BIG`, `r, c = r[keep], c[keep]`, `rows[r], cols[c], (n_row[r] > 1) | (n_col[c] > 1)`. (tracker._assign)"""
    out_r = np.empty(len(r), np.int64)
    out_c = np.empty(len(r), np.int64)
    contested = np.empty(len(r), np.bool_)
    n = 0
    for k in range(len(r)):
        if cost[r[k], c[k]] < BIG:
            out_r[n], out_c[n] = rows[r[k]], cols[c[k]]
            contested[n] = n_row[r[k]] > 1 or n_col[c[k]] > 1
            n += 1
    return out_r[:n], out_c[:n], contested[:n]


@_jit
def commit_motion(pos, vel, acc, vel_measured, hidden, was_labeled, cur, labeled, fallback, dt, max_speed, max_acc):
    """One frame's labels folded into the markers' motion; returns new (pos, vel, acc, vel_measured,
    hidden). A marker labeled on both frames gets the measured velocity (smoothed 0.7 / 0.3 with the old
    one) and, when its old velocity was measured too, an acceleration; a re-acquired one keeps its last
    velocity, an unlabeled one's decays by 0.8 a frame; speeds and accelerations are capped. Unlabeled
    markers go to `fallback`. (tracker._commit)"""
    m = pos.shape[0]
    pos2, vel2, acc2 = np.empty((m, 3)), np.empty((m, 3)), np.zeros((m, 3))
    measured = np.empty(m, np.bool_)
    hidden2 = np.empty_like(hidden)
    nv = np.empty(3)
    for i in range(m):
        both = labeled[i] and was_labeled[i]
        decay = 1.0 if labeled[i] else 0.8  # (labeled but not before: re-acquired)
        speed = 0.0
        for c in range(3):
            nv[c] = (cur[i, c] - pos[i, c]) / dt if both else vel[i, c] * decay
            speed += nv[c] * nv[c]
        scale = min(1.0, max_speed / max(math.sqrt(speed), 1e-9))
        a2 = 0.0
        for c in range(3):
            v = nv[c] * scale
            vel2[i, c] = 0.7 * v + 0.3 * vel[i, c] if both else v
            if both and vel_measured[i]:
                acc2[i, c] = (vel2[i, c] - vel[i, c]) / dt
                a2 += acc2[i, c] ** 2
            pos2[i, c] = cur[i, c] if labeled[i] else fallback[i, c]
        scale = min(1.0, max_acc / max(math.sqrt(a2), 1e-9))
        for c in range(3):
            acc2[i, c] *= scale
        measured[i] = both
        hidden2[i] = 0 if labeled[i] else hidden[i] + 1
    return pos2, vel2, acc2, measured, hidden2


@_jit
def snapshot(snap, cur, labeled):
    """Row i of snap (M, M, 3), for each labeled marker i, := every labeled marker's position now (NaN for
    the others), in place. (partners._snapshot)"""
    m = cur.shape[0]
    for i in range(m):
        if not labeled[i]:
            continue
        for j in range(m):
            for c in range(3):
                snap[i, j, c] = cur[j, c] if labeled[j] else np.nan


@_jit
def world_transforms(t_root, R_parent_segment, joint_offsets, parents):
    """World rotations (S, 3, 3) and origins (S, 3) of the segments of one pose; parents (S,) lists each
    segment's parent (-1 for the root), parents before children. (calibration.world_transforms, one pose)"""
    n = R_parent_segment.shape[0]
    Rs = np.empty((n, 3, 3))
    ps = np.empty((n, 3))
    for i in range(n):
        p = parents[i]
        if p < 0:
            Rs[i] = R_parent_segment[i]
            ps[i] = t_root
            continue
        for a in range(3):
            ps[i, a] = ps[p, a]
            for b in range(3):
                ps[i, a] += Rs[p, a, b] * joint_offsets[i, b]
                acc = 0.0
                for c in range(3):
                    acc += Rs[p, a, c] * R_parent_segment[i, c, b]
                Rs[i, a, b] = acc
    return Rs, ps


@_jit
def finite_rows(points):
    """Indices of the rows of points (N, 3) with three finite coordinates. Replaces the numpy formulation
    `flatnonzero(all(isfinite(points), axis=1))` (an axis reduction costs ~30 us paced). (engine.Engine._step)"""
    keep = np.empty(points.shape[0], np.int64)
    n = 0
    for j in range(points.shape[0]):
        if math.isfinite(points[j, 0]) and math.isfinite(points[j, 1]) and math.isfinite(points[j, 2]):
            keep[n] = j
            n += 1
    return keep[:n]


@_jit
def repeats(points, radius_m):
    """Indices of the points within radius_m of an earlier point of the frame (of each close pair, the
    later one). All pairs: for the few dozen points of a frame, cheaper than building a k-d tree."""
    n = points.shape[0]
    r2 = radius_m * radius_m
    out = np.zeros(n, np.bool_)
    for j in range(n):
        for i in range(j):
            if _dist2(points, i, points, j) <= r2:
                out[j] = True
                break
    return np.flatnonzero(out)


@_jit
def relabel_candidates(layout, cur, where, provisional, lab, slot, maps, handover_m, jump_m):
    """One segment's relabellings, scored. Its labeled markers `lab` (n,) sit at cur[lab]; relabelling c
    gives the point of lab[j] the label slot[maps[c, j]] (slots beyond n: its unlabeled markers). Returns
    rms (C,), how well the relabelled points fit the layout (Kabsch misfit), and blocked (C,): a label
    would jump farther from where its marker is (`where`: now, or last known) than jump_m, or than
    handover_m when handed to an unlabeled marker, or is handed over from a marker not on probation
    (`provisional` <= 0: tracked all along). (the batch in layouts._relabel_by_shape)"""
    n_c, n = maps.shape
    rms = np.empty(n_c)
    blocked = np.zeros(n_c, np.bool_)
    H = np.empty((3, 3))
    cb = np.zeros(3)
    for j in range(n):
        for k in range(3):
            cb[k] += cur[lab[j], k]
    cb /= n
    for c in range(n_c):
        ca = np.zeros(3)
        spare = False
        far = 0.0
        for j in range(n):
            t = slot[maps[c, j]]
            for k in range(3):
                ca[k] += layout[t, k]
            if maps[c, j] >= n:
                spare = True
                if provisional[lab[j]] <= 0:
                    blocked[c] = True
            far = max(far, math.sqrt(_dist2(cur, lab[j], where, t)))
        if far > (handover_m if spare else jump_m):
            blocked[c] = True
        ca /= n
        H[:] = 0.0
        sq = 0.0
        for j in range(n):
            t = slot[maps[c, j]]
            for a in range(3):
                da = layout[t, a] - ca[a]
                db = cur[lab[j], a] - cb[a]
                sq += da * da + db * db
                for b in range(3):
                    H[a, b] += da * (cur[lab[j], b] - cb[b])
        rms[c] = _misfit(H, sq, n)
    return rms, blocked


@_jit
def segment_fits(off, joint, pts, perms, max_rms):
    """A segment's markers registered onto n points under each labelling: marker perms[c, j] (offset
    off[.], (M, 3)) on point pts[j] (n, 3). Returns rms (C,), the Kabsch misfit of each, and joint (C,), how
    far that registration puts the segment's origin (the offsets' zero) from `joint` (3,); inf for the
    labellings misfitting by max_rms or more (their rotation is never formed).
    (segment_search._rival_fits, which made one numpy Kabsch per labelling: 1680 of them for a torso's eight
    markers against four points, 0.15 s in one frame of eight subjects.)"""
    n_c, n = perms.shape
    rms = np.empty(n_c)
    dist = np.empty(n_c)
    H = np.empty((3, 3))
    cb = np.zeros(3)
    for j in range(n):
        for k in range(3):
            cb[k] += pts[j, k]
    cb /= n
    for c in range(n_c):
        ca = np.zeros(3)
        for j in range(n):
            for k in range(3):
                ca[k] += off[perms[c, j], k]
        ca /= n
        H[:] = 0.0
        sq = 0.0
        for j in range(n):
            for a in range(3):
                da = off[perms[c, j], a] - ca[a]
                sq += da * da + (pts[j, a] - cb[a]) ** 2
                for b in range(3):
                    H[a, b] += da * (pts[j, b] - cb[b])
        rms[c] = _misfit(H, sq, n)
        if rms[c] >= max_rms:
            dist[c] = np.inf
            continue
        R = _rotation_of(H)
        d2 = 0.0
        for a in range(3):  # the origin goes to t = cb - R ca
            t = cb[a]
            for b in range(3):
                t -= R[a, b] * ca[b]
            d2 += (t - joint[a]) ** 2
        dist[c] = math.sqrt(d2)
    return rms, dist


@_jit
def joint_hypotheses(base_a, base_b, off, points, mk, pt, los, pool, near, pinned, tol_m, inlier_m):
    """Every hypothesis of a segment search around its joint registered at once (segment_search._around_joint,
    which made a numpy registration and placement per hypothesis: 5-15 ms on a frame of eight subjects
    whose unclaimed points offered a lost forearm hundreds). Hypothesis h puts marker mk[h, c] (offsets
    `off`) on point pt[h, c] (`points`), c < 2 (-1: none), beside the segment's base rows: its joint and
    labeled markers, offsets `base_a` and positions `base_b` (row 0 the joint). With `pinned`, a one-marker
    hypothesis is registered without the joint. Returns (keep (H,): its residuals pass (every row within
    2 tol_m, unless pinned, and every row but the joint's within 2 inlier_m); rms (H,): the RMS residual
    (without the joint's when pinned); R (H, 3, 3), t (H, 3): its rigid motion; placed (H, L): the point
    of `pool` (pinned) or `near` nearest to where the motion puts marker los[l], if within inlier_m, else
    -1), for the hypotheses kept."""
    n_h, n0, n_l = mk.shape[0], base_a.shape[0], los.shape[0]
    keep = np.zeros(n_h, np.bool_)
    rms = np.full(n_h, np.nan)
    Rs = np.zeros((n_h, 3, 3))
    ts = np.zeros((n_h, 3))
    placed = np.full((n_h, n_l), -1, np.int64)
    A = np.empty((n0 + 2, 3))
    B = np.empty((n0 + 2, 3))
    A[:n0] = base_a
    B[:n0] = base_b
    for h in range(n_h):
        n = n0
        for c in range(2):
            if mk[h, c] >= 0:
                A[n] = off[mk[h, c]]
                B[n] = points[pt[h, c]]
                n += 1
        one = pinned and n == n0 + 1
        first = 1 if one else 0
        R, t = rigid_motion(A[first:n], B[first:n])
        worst, worst_marker, ss = 0.0, 0.0, 0.0
        for j in range(n):
            d2 = 0.0
            for a in range(3):
                x = A[j, 0] * R[a, 0] + A[j, 1] * R[a, 1] + A[j, 2] * R[a, 2] + t[a] - B[j, a]
                d2 += x * x
            d = math.sqrt(d2)
            worst = max(worst, d)
            if j >= 1:
                worst_marker = max(worst_marker, d)
            if j >= first:
                ss += d * d
        if (not one and worst > 2.0 * tol_m) or worst_marker > 2.0 * inlier_m:
            continue
        keep[h] = True
        rms[h] = math.sqrt(ss / (n - first))
        Rs[h] = R
        ts[h] = t
        cands = pool if one else near
        for r in range(n_l):
            o = off[los[r]]
            x0 = o[0] * R[0, 0] + o[1] * R[0, 1] + o[2] * R[0, 2] + t[0]
            x1 = o[0] * R[1, 0] + o[1] * R[1, 1] + o[2] * R[1, 2] + t[1]
            x2 = o[0] * R[2, 0] + o[1] * R[2, 1] + o[2] * R[2, 2] + t[2]
            best, best_d = -1, np.inf
            for c in range(cands.shape[0]):
                q = points[cands[c]]
                d = math.sqrt((x0 - q[0]) ** 2 + (x1 - q[1]) ** 2 + (x2 - q[2]) ** 2)
                if d < best_d:
                    best, best_d = cands[c], d
            if best_d < inlier_m:
                placed[h, r] = best
    return keep, rms, Rs, ts, placed


def warm_up() -> float:
    """Compile (or load from the cache) every kernel with the argument types the tracker passes."""
    t0 = time.perf_counter()
    m, k = 4, 3
    partners = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], np.int64)
    pos = np.random.default_rng(0).normal(size=(m, 3))
    snap = np.broadcast_to(pos, (m, m, 3)).copy()
    stats = np.ones((m, m))
    labeled = np.ones(m, bool)
    rows = np.arange(m, dtype=np.int64)
    pred, spread, swing = rigid_predict(partners, snap, stats, pos, labeled, labeled)
    has_rigid, spread0, err, _ = rigid_check(pos, pred, spread, swing, labeled, 0.01, 0.006)
    unswap(rows.copy(), pos.copy(), pred, err, 0.006)
    far_from_fit(pred, pos, labeled, labeled, partners, rows, 0.1, 0.2)
    distance_misfit(partners, stats, stats, stats, pos, labeled, rows, np.inf)
    probation(partners, stats, stats, stats, pos, labeled, rows, rows, 3.0)
    label_errors(pos, pos, labeled)
    update_distances(stats.copy(), stats.copy(), stats.copy(), stats.copy(), stats.copy(), pos, labeled, 0.02, 0.002)
    kabsch_rms(snap, snap, np.ones((m, k + 1), bool))
    rows_, cols_, cost, n_row, n_col = gated_pairs(pos, np.ones(m), pos, labeled)
    assigned(rows_, cols_, cost, n_row, n_col, *linear_sum_assignment(cost))
    pred, speed, _ = track_predictions(pos, pos, pos, labeled, 0.01, True, 0.03)
    idx, _, _, _ = track_labels(pos, rows, rows, labeled, pred, speed, 0.01, m, 0.006, labeled, 1, 3)
    carried_labels(idx, pos, pred, speed, speed, 0.01, 0.5)
    hidden = np.zeros(m, np.int64)
    reacquire_gates(pred, has_rigid, spread0, labeled, labeled, pos, True, labeled, hidden, 0.01, 0.05, 0.1, 0.02, 0.5, 2.0)
    frame_outcome(rows, labeled, pos, has_rigid, pred, pos, pos, True, labeled, spread0, labeled, 0.02, labeled)
    commit_motion(pos, pos, pos, labeled, hidden, labeled, pos, labeled, pos, 0.01, 15.0, 500.0)
    snapshot(snap, pos, labeled)
    world_transforms(pos[0], np.broadcast_to(np.eye(3), (m, 3, 3)).copy(), pos, np.arange(-1, m - 1))
    repeats(pos, 0.01)
    finite_rows(pos)
    maps = np.array([[0, 1], [1, 0], [2, 1]], np.int64)
    relabel_candidates(pos, pos, pos, hidden, rows[:2], rows[:3], maps, 0.2, 0.3)
    segment_fits(pos, pos[0], pos[:2], maps, 1.0)
    rigid_motion(pos, pos)
    hyps = np.array([[0, -1], [1, 2]], np.int64)
    joint_hypotheses(pos[:2], pos[:2], pos, pos, hyps, hyps, rows[:2], rows, rows, True, 0.03, 0.02)
    return time.perf_counter() - t0
