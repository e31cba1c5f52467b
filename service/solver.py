"""The skeleton fit: a jitted optimistix Gauss-Newton solve of the 45-DOF pose to labeled markers.

Compile-once discipline: every array has a fixed shape (markers padded to `max_markers`, a boolean mask
says which are observed), so one compilation serves every frame, subject and visibility pattern. Missing
markers are excluded with `jnp.where`, never by multiplying NaN by zero (which silently yields NaN
gradients and returns the start pose). A weak prior pulls the pose toward its prediction so segments with
fewer than two visible markers stay put instead of diverging. `throw=False`: a failed solve is reported by
its result code and the caller keeps the previous pose.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from protocol.skeleton import N_SEGMENTS
from service.kinematics import marker_positions, rotvec_to_matrix, segment_transforms

jax.config.update("jax_enable_x64", True)  # float64: the normal equations square the conditioning

DTYPE = np.float64
N_PARAMS = 3 + 3 * N_SEGMENTS  # 45: root translation + one rotation vector per segment


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Outcome of one solve (numpy, host side)."""

    t_world_root_m: np.ndarray  # (3,)
    R_parent_segment: np.ndarray  # (14, 3, 3)
    predicted_m: np.ndarray  # (max_markers, 3) model position of every marker slot
    residual_rms_m: float  # over observed markers
    iterations: int
    ok: bool  # the solver converged or stopped at max_steps without failing


@functools.partial(jax.jit, static_argnames=("max_steps",))
def _solve(t0, base_R, joint_offsets, marker_segment, marker_offsets, observed, mask, weight, prior_w, rtol, max_steps):
    def fn(x, _):
        t = x[:3]
        delta = x[3:].reshape(N_SEGMENTS, 3)
        R = rotvec_to_matrix(delta) @ base_R
        Rs, ps = segment_transforms(t, R, joint_offsets)
        pred = marker_positions(Rs, ps, marker_segment, marker_offsets)
        r = jnp.where(mask[:, None], (pred - jnp.where(mask[:, None], observed, 0.0)) * weight[:, None], 0.0)
        prior = prior_w * (x - jnp.concatenate([t0, jnp.zeros(3 * N_SEGMENTS)]))
        return jnp.concatenate([r.reshape(-1), prior])

    solver = optx.GaussNewton(rtol=rtol, atol=1e-7, linear_solver=lx.Normal(lx.Cholesky()))
    x0 = jnp.concatenate([t0, jnp.zeros(3 * N_SEGMENTS)])
    sol = optx.least_squares(fn, solver, x0, max_steps=max_steps, throw=False)
    x = sol.value
    ok = (sol.result == optx.RESULTS.successful) | (sol.result == optx.RESULTS.nonlinear_max_steps_reached)
    ok = ok & jnp.all(jnp.isfinite(x))
    t = x[:3]
    R = rotvec_to_matrix(x[3:].reshape(N_SEGMENTS, 3)) @ base_R
    Rs, ps = segment_transforms(t, R, joint_offsets)
    pred = marker_positions(Rs, ps, marker_segment, marker_offsets)
    err2 = jnp.where(mask, jnp.sum((pred - jnp.where(mask[:, None], observed, 0.0)) ** 2, axis=1), 0.0)
    rms = jnp.sqrt(jnp.sum(err2) / jnp.maximum(jnp.sum(mask), 1))
    return t, R, pred, rms, sol.stats["num_steps"], ok


@functools.partial(jax.jit)
def _predict(t, R_parent_segment, joint_offsets, marker_segment, marker_offsets):
    Rs, ps = segment_transforms(t, R_parent_segment, joint_offsets)
    return marker_positions(Rs, ps, marker_segment, marker_offsets), Rs, ps


class PoseSolver:
    """Fits the skeleton of one subject model; holds only the compiled shapes and the settings."""

    def __init__(self, max_markers: int, max_steps: int = 8, rtol: float = 1e-4, prior_weight: float = 0.05):
        self.max_markers = max_markers
        self.max_steps = max_steps
        self.rtol = rtol
        # Per-parameter prior weights: translation [1/m scale] weaker than rotations [rad].
        self.prior_w = np.concatenate([np.full(3, 0.2 * prior_weight), np.full(3 * N_SEGMENTS, prior_weight)])

    def pad(self, a: np.ndarray, fill=0.0) -> np.ndarray:
        out = np.full((self.max_markers,) + a.shape[1:], fill, dtype=DTYPE if a.dtype.kind == "f" else a.dtype)
        out[: len(a)] = a
        return out

    def fit(
        self,
        t0_m: np.ndarray,
        R0_parent_segment: np.ndarray,
        joint_offsets_m: np.ndarray,
        marker_segment: np.ndarray,
        marker_offsets_m: np.ndarray,
        observed_m: np.ndarray,
        mask: np.ndarray,
        weight: np.ndarray | None = None,
    ) -> FitResult:
        """Fit from the start pose (t0, R0) to `observed_m` (M, 3) where `mask` (M,) is True."""
        m = len(marker_segment)
        if weight is None:
            weight = np.ones(m)
        t, R, pred, rms, steps, ok = _solve(
            np.asarray(t0_m, DTYPE),
            np.asarray(R0_parent_segment, DTYPE),
            np.asarray(joint_offsets_m, DTYPE),
            self.pad(np.asarray(marker_segment, np.int32)),
            self.pad(np.asarray(marker_offsets_m, DTYPE)),
            self.pad(np.nan_to_num(np.asarray(observed_m, DTYPE))),
            self.pad(np.asarray(mask, bool), False),
            self.pad(np.asarray(weight, DTYPE)),
            self.prior_w,
            self.rtol,
            max_steps=self.max_steps,
        )
        ok = bool(ok)
        return FitResult(
            t_world_root_m=np.asarray(t),
            R_parent_segment=np.asarray(R),
            predicted_m=np.asarray(pred)[:m],
            residual_rms_m=float(rms),
            iterations=int(steps),
            ok=ok,
        )

    def predict(self, t_m, R_parent_segment, joint_offsets_m, marker_segment, marker_offsets_m) -> np.ndarray:
        """(M, 3) marker positions of a pose, through the same compiled FK."""
        m = len(marker_segment)
        pred, _, _ = _predict(
            np.asarray(t_m, DTYPE),
            np.asarray(R_parent_segment, DTYPE),
            np.asarray(joint_offsets_m, DTYPE),
            self.pad(np.asarray(marker_segment, np.int32)),
            self.pad(np.asarray(marker_offsets_m, DTYPE)),
        )
        return np.asarray(pred)[:m]

    def compile_count(self) -> int:
        """How many times the solve has been traced (a test asserts it stays 1)."""
        return _solve._cache_size()
