"""service/kinematics.py: the rotation map against scipy and its known derivative, forward kinematics of
the rest pose, and the marker Jacobian against central finite differences (float64)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol.skeleton import N_SEGMENTS, PARENTS
from recordings.synthetic import perform
from service.kinematics import joint_angles, marker_positions, matrix_to_quat_xyzw, rotvec_to_matrix, segment_transforms

jax.config.update("jax_enable_x64", True)  # the finite-difference comparison needs float64


def random_rotvecs(shape, seed=0) -> np.ndarray:
    """Rotation vectors of every size: tiny (Taylor branch), ordinary, and close to pi."""
    rng = np.random.default_rng(seed)
    v = rng.standard_normal(shape + (3,))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    angle = rng.choice([1e-9, 1e-7, 1e-3, 0.5, 2.0, 3.1], size=shape)
    return v * angle[..., None]


@pytest.mark.parametrize("shape", [(7,), (3, 5), (2, 2, 4)])
def test_rotvec_to_matrix_is_a_rotation_over_batches(shape):
    R = np.asarray(rotvec_to_matrix(jnp.asarray(random_rotvecs(shape))))
    assert R.shape == shape + (3, 3)
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_rotvec_to_matrix_equals_scipy():
    v = random_rotvecs((50,), seed=1)
    np.testing.assert_allclose(np.asarray(rotvec_to_matrix(jnp.asarray(v))), Rotation.from_rotvec(v).as_matrix(),
                               atol=1e-12)


def test_rotvec_to_matrix_derivative_at_zero_is_the_generator():
    """d R / d v_k at v = 0 is the skew matrix of e_k (finite, exact), what Gauss-Newton steps from."""
    J = np.asarray(jax.jacfwd(rotvec_to_matrix)(jnp.zeros(3)))  # (3, 3, 3): dR_ij / dv_k
    assert np.all(np.isfinite(J))
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        np.testing.assert_allclose(J[..., k], _skew(e), atol=1e-12)
    g = jax.grad(lambda v: jnp.sum(rotvec_to_matrix(v) ** 2))(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))


def _skew(e: np.ndarray) -> np.ndarray:
    x, y, z = e
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def test_rest_pose_puts_segment_origins_at_cumulative_joint_offsets():
    rng = np.random.default_rng(2)
    offsets = rng.uniform(-0.3, 0.3, (N_SEGMENTS, 3))
    offsets[0] = 0.0
    t = np.array([0.5, -1.0, 0.9])
    Rs, ps = segment_transforms(jnp.asarray(t), jnp.tile(jnp.eye(3), (N_SEGMENTS, 1, 1)), jnp.asarray(offsets))
    expected = np.zeros((N_SEGMENTS, 3))
    for i in range(N_SEGMENTS):  # walk up to the root, summing offsets
        j, total = i, t.copy()
        while j > 0:
            total += offsets[j]
            j = PARENTS[j]
        expected[i] = total
    np.testing.assert_allclose(np.asarray(ps), expected, atol=1e-12)
    np.testing.assert_allclose(np.asarray(Rs), np.tile(np.eye(3), (N_SEGMENTS, 1, 1)), atol=1e-12)


def test_marker_positions_match_the_synthetic_performer():
    """The JAX FK reproduces the generator's own (numpy/scipy) markers for a moving frame: same convention."""
    perf = perform(3, duration_s=4.0)
    f = 400  # walking, arms down
    R_parent = Rotation.from_quat(perf.rotations_xyzw[f]).as_matrix()
    Rs, ps = segment_transforms(jnp.asarray(perf.root_position_m[f]), jnp.asarray(R_parent), jnp.asarray(perf.joint_offsets_m))
    P = marker_positions(Rs, ps, jnp.asarray(perf.marker_segment), jnp.asarray(perf.marker_offsets_m))
    np.testing.assert_allclose(np.asarray(P), perf.recording.points_m[f], atol=1e-9)


def test_marker_jacobian_matches_central_differences():
    perf = perform(4, duration_s=0.1)
    rng = np.random.default_rng(4)
    base = Rotation.from_rotvec(rng.normal(0, 0.4, (N_SEGMENTS, 3))).as_matrix()
    joints, seg, off = map(jnp.asarray, (perf.joint_offsets_m, perf.marker_segment, perf.marker_offsets_m))

    def markers(x):
        R = rotvec_to_matrix(x[3:].reshape(N_SEGMENTS, 3)) @ base
        Rs, ps = segment_transforms(x[:3], R, joints)
        return marker_positions(Rs, ps, seg, off).reshape(-1)

    x0 = jnp.asarray(rng.normal(0, 0.2, 3 + 3 * N_SEGMENTS))
    J = np.asarray(jax.jacfwd(markers)(x0))
    h = 1e-6
    fd = np.stack([(np.asarray(markers(x0.at[k].add(h))) - np.asarray(markers(x0.at[k].add(-h)))) / (2 * h)
                   for k in range(x0.size)], axis=1)
    assert J.shape == (3 * len(perf.marker_segment), 45)
    np.testing.assert_allclose(J, fd, atol=1e-7)
    # every marker moves one to one with the root translation
    np.testing.assert_allclose(J[:, :3], np.tile(np.eye(3), (len(perf.marker_segment), 1)), atol=1e-9)


def test_joint_angles_and_quaternions_of_a_known_rotation():
    R = np.tile(np.eye(3), (N_SEGMENTS, 1, 1))
    R[5] = Rotation.from_euler("YXZ", [0.3, -0.2, 0.1]).as_matrix()  # l_forearm: joint 4
    angles = joint_angles(R)
    assert angles.shape == (N_SEGMENTS - 1, 3)
    np.testing.assert_allclose(angles[4], [0.3, -0.2, 0.1], atol=1e-12)
    np.testing.assert_allclose(np.delete(angles, 4, axis=0), 0.0, atol=1e-12)
    q = matrix_to_quat_xyzw(R)
    np.testing.assert_allclose(q[0], [0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)


def test_quaternions_and_angles_match_scipy_on_random_rotations():
    """The hand-written conversions agree with scipy's (quaternions up to sign: ours have w >= 0)."""
    rot = Rotation.random(5000, random_state=3)
    q = matrix_to_quat_xyzw(rot.as_matrix())
    ref = rot.as_quat()
    ref *= np.where(ref[:, 3:] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, ref, atol=1e-12)
    half_turns = Rotation.from_rotvec(np.pi * np.eye(3))  # where the w-formula breaks down
    q = matrix_to_quat_xyzw(half_turns.as_matrix())
    np.testing.assert_allclose(np.abs(q), np.abs(half_turns.as_quat()), atol=1e-12)
    R = np.concatenate([np.eye(3)[None], rot.as_matrix()[:13]])
    np.testing.assert_allclose(joint_angles(R), rot[:13].as_euler("YXZ"), atol=1e-12)
