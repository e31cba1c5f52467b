"""Forward kinematics of the 14-segment skeleton in JAX, and its rotation helpers.

Parametrisation (45 DOF): the root translation t_world_pelvis [m] (3) and, for every segment, a small
rotation vector delta_i [rad] (14 x 3 = 42) applied on top of a base rotation R_base_i that the caller
passes in (the last solved pose). R_parent_segment_i = exp(delta_i) @ R_base_i, so the unknowns stay near
zero and the exponential map is never near its 2*pi singularity, however far a subject turns; 6 of them
(t and delta_0) are the root's, 3 per ball joint for the 13 others.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from protocol.skeleton import PARENTS


def _rotvec_terms(v: jax.Array):
    """The skew matrix K of v (..., 3) and theta^2, with the denominators made safe at 0."""
    theta2 = jnp.sum(v * v, axis=-1, keepdims=True)[..., None]
    small = theta2 <= 1e-12
    safe = jnp.where(small, 1.0, theta2)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    K = jnp.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(v.shape[:-1] + (3, 3))
    return K, theta2, small, safe


def rotvec_to_matrix(v: jax.Array) -> jax.Array:
    """Rodrigues' formula, (..., 3) [rad] -> (..., 3, 3); exact and differentiable at 0."""
    K, theta2, small, safe = _rotvec_terms(v)
    theta = jnp.sqrt(safe)
    # Taylor expansions below 1e-6 rad keep the gradient finite at exactly zero.
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / safe)
    return jnp.eye(3, dtype=v.dtype) + a * K + b * (K @ K)


def rotvec_left_jacobian(v: jax.Array) -> jax.Array:
    """(..., 3) -> (..., 3, 3) J with exp(v + dv) = exp(J dv) exp(v) to first order: a change dv of a
    rotation vector turns the rotation by J dv about axes fixed in the frame it maps into."""
    K, theta2, small, safe = _rotvec_terms(v)
    theta = jnp.sqrt(safe)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / safe)
    c = jnp.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - jnp.sin(theta)) / (safe * theta))
    return jnp.eye(3, dtype=v.dtype) + b * K + c * (K @ K)


# The chain by depth: segments whose parents are all in earlier levels, computed together. Five batched
# steps instead of thirteen sequential 3x3 products: XLA on a CPU pays a few microseconds per operation
# whatever its size, so the level form is ~7x faster (16 vs 110 us) and the solve runs it every step.
_DEPTH = [0] * len(PARENTS)
for _i in range(1, len(PARENTS)):
    _DEPTH[_i] = _DEPTH[PARENTS[_i]] + 1
LEVELS: tuple[np.ndarray, ...] = tuple(
    np.array([i for i in range(len(PARENTS)) if _DEPTH[i] == d]) for d in range(1, max(_DEPTH) + 1)
)


def segment_transforms(
    t_world_root: jax.Array, R_parent_segment: jax.Array, joint_offsets_m: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """World rotations (14, 3, 3) and origins (14, 3) [m] of every segment.

    R_parent_segment: (14, 3, 3), the root's relative to the world. joint_offsets_m: (14, 3), each
    segment's origin in its parent's frame (the root's row is unused).
    """
    Rs = jnp.zeros_like(R_parent_segment).at[0].set(R_parent_segment[0])
    ps = jnp.zeros_like(joint_offsets_m).at[0].set(t_world_root)
    for level in LEVELS:  # static loop: unrolled once at trace time
        parent = np.array([PARENTS[i] for i in level])
        R_world_parent = Rs[parent]
        Rs = Rs.at[level].set(R_world_parent @ R_parent_segment[level])
        ps = ps.at[level].set(ps[parent] + jnp.einsum("kij,kj->ki", R_world_parent, joint_offsets_m[level]))
    return Rs, ps


def marker_positions(
    Rs_world_segment: jax.Array, ps_world_segment: jax.Array, marker_segment: jax.Array, marker_offsets_m: jax.Array
) -> jax.Array:
    """(M, 3) world positions [m] of markers fixed at `marker_offsets_m` in their segments' frames."""
    R = Rs_world_segment[marker_segment]
    return jnp.einsum("mij,mj->mi", R, marker_offsets_m) + ps_world_segment[marker_segment]


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 4) unit quaternions x, y, z, w with w >= 0 (numpy).

    Shepperd's method, vectorised: of the four algebraically equal formulas each quaternion takes the
    one with the largest square root, which is the numerically stable one. Hand-written because
    scipy's Rotation costs ~0.3 ms for 14 matrices, this ~0.03 ms, on every solved frame's pose."""
    shape = R.shape[:-2]
    R = np.asarray(R, np.float64).reshape(-1, 3, 3)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    d21, d02, d10 = R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]
    s01, s02, s12 = R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]
    diag = np.stack([m00 + m11 + m22, m00 - m11 - m22, m11 - m00 - m22, m22 - m00 - m11], axis=1)
    k = np.argmax(diag, axis=1)
    r = 2.0 * np.sqrt(np.maximum(1.0 + diag[np.arange(len(R)), k], 1e-300))  # 4 x the largest component
    cases = np.stack([
        np.stack([d21, d02, d10, 0.25 * r * r], axis=1),  # w largest
        np.stack([0.25 * r * r, s01, s02, d21], axis=1),  # x largest
        np.stack([s01, 0.25 * r * r, s12, d02], axis=1),  # y largest
        np.stack([s02, s12, 0.25 * r * r, d10], axis=1),  # z largest
    ])  # (4, N, 4), each row times r
    q = cases[k, np.arange(len(R))] / r[:, None]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q.reshape(shape + (4,))


def joint_angles(R_parent_segment: np.ndarray) -> np.ndarray:
    """(14, 3, 3) relative rotations -> (13, 3) intrinsic YXZ angles [rad] of every ball joint
    (protocol.skeleton.JOINT_ANGLE_CONVENTION): R = Ry(a) Rx(b) Rz(c), b in [-pi/2, pi/2]. At gimbal lock
    (|b| = pi/2) c is 0 and a carries the whole turn. Closed form, hand-written for the same reason as
    `matrix_to_quat_xyzw`."""
    R = np.asarray(R_parent_segment, np.float64)[1:]
    b = np.arcsin(np.clip(-R[:, 1, 2], -1.0, 1.0))
    locked = np.abs(R[:, 1, 2]) > 1.0 - 1e-12
    a = np.where(locked, np.arctan2(-R[:, 2, 0], R[:, 0, 0]), np.arctan2(R[:, 0, 2], R[:, 2, 2]))
    c = np.where(locked, 0.0, np.arctan2(R[:, 1, 0], R[:, 1, 1]))
    return np.stack([a, b, c], axis=1)
