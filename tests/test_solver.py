"""service/solver.py: recovering a known pose, masks (garbage and NaN in unobserved slots), the
compile-once discipline, and a degenerate solve that must not produce NaN."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol.skeleton import N_SEGMENTS
from recordings.synthetic import forward_kinematics, marker_positions, perform
from service.solver import PoseSolver

MAX_MARKERS = 96  # the engine's default: the same compiled shapes as the engine's solve


@pytest.fixture(scope="module")
def solver() -> PoseSolver:
    return PoseSolver(MAX_MARKERS)


def known_pose(seed: int, marker_set: str = "cmu41"):
    """A random body and a random pose of it (joints within ~0.5 rad), with its exact markers."""
    perf = perform(seed, marker_set=marker_set, duration_s=0.1)
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(rng.normal(0.0, 0.3, (N_SEGMENTS, 3))).as_matrix()
    R[0] = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)).as_matrix() @ R[0]
    t = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), 0.95])
    quats = Rotation.from_matrix(R).as_quat()[None]
    Rw, pw = forward_kinematics(t[None], quats, perf.joint_offsets_m)
    observed = marker_positions(Rw, pw, perf.marker_segment, perf.marker_offsets_m)[0]
    return perf, t, R, observed


def perturbed(t, R, seed: int, angle_rad: float = 0.1, shift_m: float = 0.05):
    """A start pose ~angle_rad away from (t, R) in every segment."""
    rng = np.random.default_rng(100 + seed)
    axes = rng.standard_normal((N_SEGMENTS, 3))
    axes *= angle_rad / np.linalg.norm(axes, axis=1, keepdims=True)
    return t + rng.normal(0.0, shift_m / np.sqrt(3), 3), Rotation.from_rotvec(axes).as_matrix() @ R


def fit(solver, perf, t0, R0, observed, mask):
    return solver.fit(t0, R0, perf.joint_offsets_m, perf.marker_segment, perf.marker_offsets_m, observed, mask)


def rms_m(a, b) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


@pytest.mark.parametrize("seed, marker_set", [(0, "cmu41"), (1, "gt53"), (2, "cmu41")])
def test_recovers_a_known_pose_from_exact_markers(solver, seed, marker_set):
    perf, t, R, observed = known_pose(seed, marker_set)
    t0, R0 = perturbed(t, R, seed)
    start_rms = rms_m(solver.predict(t0, R0, perf.joint_offsets_m, perf.marker_segment, perf.marker_offsets_m), observed)
    assert start_rms > 0.03  # the start really is off
    res = fit(solver, perf, t0, R0, observed, np.ones(len(observed), bool))
    assert res.ok
    assert rms_m(res.predicted_m, observed) < 0.001
    assert res.residual_rms_m < 0.001
    np.testing.assert_allclose(res.t_world_root_m, t, atol=0.002)
    assert res.R_parent_segment.shape == (N_SEGMENTS, 3, 3)
    np.testing.assert_allclose(np.linalg.det(res.R_parent_segment), 1.0, atol=1e-9)


def test_masked_markers_are_ignored_garbage_or_nan(solver):
    perf, t, R, observed = known_pose(3)
    t0, R0 = perturbed(t, R, 3)
    m = len(observed)
    mask = np.ones(m, bool)
    mask[::4] = False  # a quarter of the markers unobserved
    clean = fit(solver, perf, t0, R0, observed, mask)
    garbage = observed.copy()
    garbage[~mask] = np.random.default_rng(3).uniform(-50.0, 50.0, (int((~mask).sum()), 3))
    with_garbage = fit(solver, perf, t0, R0, garbage, mask)
    poisoned = observed.copy()
    poisoned[~mask] = np.nan
    poisoned[np.flatnonzero(~mask)[0]] = np.inf
    with_nan = fit(solver, perf, t0, R0, poisoned, mask)
    for res in (with_garbage, with_nan):
        assert res.ok
        np.testing.assert_allclose(res.predicted_m, clean.predicted_m, atol=1e-9)
        assert abs(res.residual_rms_m - clean.residual_rms_m) < 1e-9
    # and the observed three quarters still pin the pose (from a start > 3 cm off): even the masked markers
    # land where they are. 2 mm, not 1: with fewer markers per segment the prior toward the start pose
    # (prior_weight) biases the fit by ~1 mm.
    assert rms_m(clean.predicted_m[mask], observed[mask]) < 0.002
    assert rms_m(clean.predicted_m[~mask], observed[~mask]) < 0.01


def test_compiles_once_across_masks_and_subjects(solver):
    perf_a, t_a, R_a, obs_a = known_pose(4, "cmu41")
    perf_b, t_b, R_b, obs_b = known_pose(5, "gt53")
    solver.warm_up()
    count = solver.compile_count()
    assert count >= len(solver.sizes)
    assert solver.size(len(obs_a)) != solver.size(len(obs_b)), "the two subjects should use both padded sizes"
    rng = np.random.default_rng(6)
    for perf, t, R, obs in ((perf_a, t_a, R_a, obs_a), (perf_b, t_b, R_b, obs_b)) * 2:
        mask = rng.random(len(obs)) < 0.7
        fit(solver, perf, t, R, obs, mask)
    fit(solver, perf_b, t_b, R_b, obs_b, np.zeros(len(obs_b), bool))
    fit(solver, perf_a, t_a, R_a, obs_a, np.ones(len(obs_a), bool))
    assert solver.compile_count() == count, "the solve was traced again: a shape or dtype changed"


def test_a_subject_solves_the_same_at_either_padded_size(solver):
    perf, t, R, observed = known_pose(8)
    mask = np.random.default_rng(8).random(len(observed)) < 0.8
    small, large = solver, PoseSolver(2 * MAX_MARKERS)  # 41 markers padded to 48, and to 96
    assert small.size(len(observed)) < large.size(len(observed))
    a, b = fit(small, perf, t, R, observed, mask), fit(large, perf, t, R, observed, mask)
    np.testing.assert_allclose(a.predicted_m, b.predicted_m, atol=1e-9)
    assert a.iterations == b.iterations


def test_more_markers_than_compiled_for_is_a_clear_error(solver):
    with pytest.raises(ValueError, match="max_markers"):
        solver.size(MAX_MARKERS + 1)


def test_no_visible_marker_keeps_a_finite_pose(solver):
    perf, t, R, observed = known_pose(7)
    res = fit(solver, perf, t, R, np.full_like(observed, np.nan), np.zeros(len(observed), bool))
    assert np.all(np.isfinite(res.t_world_root_m)) and np.all(np.isfinite(res.R_parent_segment))
    assert np.all(np.isfinite(res.predicted_m))
    # nothing observed: only the prior speaks, so the pose stays where it started
    np.testing.assert_allclose(res.t_world_root_m, t, atol=1e-6)
    np.testing.assert_allclose(res.R_parent_segment, R, atol=1e-6)


def test_predict_equals_the_fitted_model(solver):
    perf, t, R, observed = known_pose(8)
    np.testing.assert_allclose(
        solver.predict(t, R, perf.joint_offsets_m, perf.marker_segment, perf.marker_offsets_m), observed, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_engine_settings_catch_up_with_a_pose_ten_frames_old(seed):
    """The solve starts from the last fitted pose, up to max_skip_frames old: a fast limb is 0.3 rad away
    by then. The engine's settings (up to solver_max_steps iterations, stopping once converged) reach the
    markers; 3 iterations, the old setting, stop tens of millimetres short."""
    from service.config import EngineConfig

    c = EngineConfig()
    perf, t, R, observed = known_pose(seed)
    t0, R0 = perturbed(t, R, seed, angle_rad=0.3, shift_m=0.1)
    mask = np.ones(len(observed), bool)
    engine = fit(PoseSolver(MAX_MARKERS, c.solver_max_steps, c.solver_rtol, c.prior_weight, c.solver_atol),
                 perf, t0, R0, observed, mask)
    three = fit(PoseSolver(MAX_MARKERS, 3, c.solver_rtol, c.prior_weight, c.solver_atol), perf, t0, R0, observed, mask)
    assert engine.ok and engine.residual_rms_m < 0.005  # the weak prior toward the start holds it a few mm off
    assert three.residual_rms_m > 0.01, three.residual_rms_m
