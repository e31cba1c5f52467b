"""The compiled loops against the plain numpy formulations they replaced (written out here as references),
on random data with the awkward cases: unlabeled markers, missing partners, NaN snapshots, reflections."""

import numpy as np
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
        pred, spread = kernels.rigid_predict(partners, snap, var, cur, labeled, which)
        for i in range(len(cur)):
            want_p, want_s = _rigid_reference(partners, snap, var, cur, labeled, i) if which[i] else (np.full(3, np.nan), np.nan)
            np.testing.assert_allclose(pred[i], want_p, atol=1e-9)
            np.testing.assert_allclose(spread[i], want_s, atol=1e-7)


def test_distance_misfit_is_the_median_z_over_the_three_most_rigid_partners():
    for seed in range(5):
        _, cur, labeled, partners, _, var, n, mean = _random_case(seed)
        rows = np.array([0, 2, 3, 5, 7, 11])
        got = kernels.distance_misfit(partners, n, mean, var, cur, labeled, rows)
        for i in range(len(cur)):
            js = [j for j in partners[i] if j >= 0 and labeled[j] and n[i, j] >= 10] if labeled[i] and i in rows else []
            js = sorted(js, key=lambda j: np.sqrt(var[i, j]))[:3]  # (stable: the first listed wins a tie)
            z = sorted(abs(np.linalg.norm(cur[i] - cur[j]) - mean[i, j]) / (np.sqrt(var[i, j]) + kernels.SKIN_M) for j in js)
            want = z[(len(z) - 1) // 2] if len(z) >= 2 else np.nan
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


def test_kabsch_rms_matches_a_kabsch_by_svd_with_masks_and_reflections():
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
    np.testing.assert_allclose(kernels.kabsch_rms(A, B, w), want, atol=1e-9)


def test_each_kernel_compiles_once_for_the_types_the_tracker_passes():
    """warm_up compiles the signatures the tracker uses: a frame never waits for a compilation."""
    kernels.warm_up()
    before = {name: len(getattr(kernels, name).signatures) for name in ("rigid_predict", "distance_misfit", "update_distances", "kabsch_rms")}
    assert all(n == 1 for n in before.values()), before
    _, cur, labeled, partners, snap, var, n, mean = _random_case(1)
    kernels.rigid_predict(partners, snap, var, cur, labeled, labeled)
    kernels.distance_misfit(partners, n, mean, var, cur, labeled, np.flatnonzero(labeled))
    kernels.update_distances(n, mean, var, mean.copy(), var.copy(), cur, labeled, 0.02, 0.002)
    kernels.kabsch_rms(snap[:4, :5].copy(), snap[4:8, :5].copy(), np.ones((4, 5), bool))
    after = {name: len(getattr(kernels, name).signatures) for name in before}
    assert after == before
