"""The skeleton fit: a jitted optimistix Gauss-Newton solve of the 45-DOF pose to labeled markers.

Compile-once discipline: every array has a fixed shape (markers padded to one of two sizes, `max_markers`
and half of it; unobserved ones are NaN, so the mask is where they are finite), so two compilations, both made at warm-up, serve
every frame, subject and visibility pattern. (The half size exists because J^T J, the solve's costliest
step, grows with the padded rows: a 41-marker subject solves ~1.7x faster padded to 48 than to 96.) Missing
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

from protocol.skeleton import N_SEGMENTS, PARENTS
from service.kinematics import marker_positions, rotvec_left_jacobian, rotvec_to_matrix, segment_transforms

jax.config.update("jax_enable_x64", True)  # float64: the normal equations square the conditioning

DTYPE = np.float64


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Outcome of one solve (numpy, host side)."""

    t_world_root_m: np.ndarray  # (3,)
    R_parent_segment: np.ndarray  # (14, 3, 3)
    predicted_m: np.ndarray  # (max_markers, 3) model position of every marker slot
    residual_rms_m: float  # over observed markers
    iterations: int
    ok: bool  # the solver converged or stopped at max_steps without failing


# ANCESTOR[s, k]: segment k is s or one of its ancestors, so rotating joint k moves the markers of s.
ANCESTOR = np.zeros((N_SEGMENTS, N_SEGMENTS))
for _s in range(N_SEGMENTS):
    _k = _s
    while _k >= 0:
        ANCESTOR[_s, _k] = 1.0
        _k = PARENTS[_k]


@jax.custom_jvp
def _model_markers(x, base_R, joint_offsets, marker_segment, marker_offsets):
    """Marker positions (M, 3) of the pose x = (t_world_root, delta (14 x 3)); see kinematics."""
    R = rotvec_to_matrix(x[3:].reshape(N_SEGMENTS, 3)) @ base_R
    Rs, ps = segment_transforms(x[:3], R, joint_offsets)
    return marker_positions(Rs, ps, marker_segment, marker_offsets)


@_model_markers.defjvp
def _model_markers_jvp(primals, tangents):
    """Analytic derivative (hand-written because autodiff through the 14-link chain costs ~0.45 ms per
    Gauss-Newton step on this CPU, this ~10x less): a change d_k of joint k's rotation vector delta_k
    turns it about the world axis R_world_parent(k) J_l(delta_k) d_k (J_l: the SO(3) left Jacobian), which
    moves every marker below it by that axis x (marker - joint origin). Exact, so Gauss-Newton takes full
    steps: from a start pose 0.3 rad off in every joint, 4 iterations end 3-4 mm from the markers, where
    with J_l taken as the identity they ended 6-9 mm off (tests/test_solver.py). Tangents of the model
    constants are ignored: the solve differentiates the pose only."""
    x, base_R, joint_offsets, marker_segment, marker_offsets = primals
    dx = tangents[0]
    delta = x[3:].reshape(N_SEGMENTS, 3)
    R = rotvec_to_matrix(delta) @ base_R
    Rs, ps = segment_transforms(x[:3], R, joint_offsets)
    pred = marker_positions(Rs, ps, marker_segment, marker_offsets)
    parents = np.array(PARENTS)
    R_parent = jnp.concatenate([jnp.eye(3, dtype=Rs.dtype)[None], Rs[np.maximum(parents[1:], 0)]])
    R_axis = R_parent @ rotvec_left_jacobian(delta)
    axis = jnp.einsum("kij,kj->ki", R_axis, dx[3:].reshape(N_SEGMENTS, 3))  # world rotation axes
    A = jnp.asarray(ANCESTOR, Rs.dtype)[marker_segment]  # (M, 14)
    w = A @ axis
    c = A @ jnp.cross(axis, ps)
    return pred, dx[:3] + jnp.cross(w, pred) - c


@functools.partial(jax.jit, static_argnames=("rtol", "atol", "max_steps"))
def _solve(start, joint_offsets, marker_segment, marker_offsets, observed, weight, prior_w, rtol, atol, max_steps):
    # (the start pose comes as one array, t0 then R0; observed markers as (M, 3) with NaN where unobserved:
    # each argument is a host-to-device transfer, and the launch's dispatch cost grows with their number)
    t0, base_R = start[:3], start[3:].reshape(N_SEGMENTS, 3, 3)
    mask = jnp.isfinite(observed[:, 0])

    def fn(x, _):
        pred = _model_markers(x, base_R, joint_offsets, marker_segment, marker_offsets)
        r = jnp.where(mask[:, None], (pred - jnp.where(mask[:, None], observed, 0.0)) * weight[:, None], 0.0)
        prior = prior_w * (x - jnp.concatenate([t0, jnp.zeros(3 * N_SEGMENTS)]))
        return jnp.concatenate([r.reshape(-1), prior])

    solver = optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
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
    # one array back (t, R, pred, rms, steps, ok), for one device-to-host transfer instead of six
    return jnp.concatenate([t, R.reshape(-1), pred.reshape(-1), jnp.stack([rms, sol.stats["num_steps"], ok]).astype(t.dtype)])


@functools.partial(jax.jit)
def _predict(t, R_parent_segment, joint_offsets, marker_segment, marker_offsets):
    Rs, ps = segment_transforms(t, R_parent_segment, joint_offsets)
    return marker_positions(Rs, ps, marker_segment, marker_offsets), Rs, ps


class PendingFit:
    """A launched solve; `result()` waits for it (once) and converts it to a `FitResult`."""

    def __init__(self, outputs, n_markers: int):
        self._outputs = outputs
        self._m = n_markers
        self._result: FitResult | None = None

    def result(self) -> FitResult:
        if self._result is None:
            out = np.asarray(self._outputs)
            n_r = 3 + 9 * N_SEGMENTS
            self._result = FitResult(
                t_world_root_m=out[:3].copy(),
                R_parent_segment=out[3:n_r].reshape(N_SEGMENTS, 3, 3).copy(),
                predicted_m=out[n_r:-3].reshape(-1, 3)[: self._m].copy(),
                residual_rms_m=float(out[-3]),
                iterations=int(out[-2]),
                ok=bool(out[-1]),
            )
            self._outputs = None
        return self._result


class PoseSolver:
    """Fits the skeleton of one subject model; holds only the compiled shapes and the settings."""

    def __init__(
        self, max_markers: int, max_steps: int = 8, rtol: float = 1e-4, prior_weight: float = 0.05, atol: float = 1e-7
    ):
        self.max_markers = max_markers
        self.sizes = tuple(sorted({max(4, max_markers // 2), max_markers}))  # the compiled marker counts
        self.max_steps = max_steps
        self.rtol = rtol
        self.atol = atol
        # Per-parameter prior weights: translation [1/m scale] weaker than rotations [rad].
        self.prior_w = np.concatenate([np.full(3, 0.2 * prior_weight), np.full(3 * N_SEGMENTS, prior_weight)])
        self._prior_w = jax.device_put(self.prior_w)
        self._ones = {n: jax.device_put(np.ones(n, DTYPE)) for n in self.sizes}
        self._constants: list = []  # [((joint_offsets, marker_segment, marker_offsets), device arrays)], newest first

    def size(self, n_markers: int) -> int:
        """The compiled marker count a subject of n_markers is padded to."""
        for n in self.sizes:
            if n_markers <= n:
                return n
        raise ValueError(f"{n_markers} markers: the solve is compiled for at most {self.max_markers} (max_markers)")

    def pad(self, a: np.ndarray, fill=0.0) -> np.ndarray:
        out = np.full((self.size(len(a)),) + a.shape[1:], fill, dtype=DTYPE if a.dtype.kind == "f" else a.dtype)
        out[: len(a)] = a
        return out

    def warm_up(self) -> None:
        """Compile (or load from the persistent cache) the solve and the FK for every padded size."""
        t, R, joints = np.zeros(3), np.tile(np.eye(3), (N_SEGMENTS, 1, 1)), np.zeros((N_SEGMENTS, 3))
        for n in self.sizes:
            seg, offsets = np.zeros(n, int), np.zeros((n, 3))
            self.fit(t, R, joints, seg, offsets, np.zeros((n, 3)), np.ones(n, bool))
            self.predict(t, R, joints, seg, offsets)

    def launch(
        self,
        t0_m: np.ndarray,
        R0_parent_segment: np.ndarray,
        joint_offsets_m: np.ndarray,
        marker_segment: np.ndarray,
        marker_offsets_m: np.ndarray,
        observed_m: np.ndarray,
        mask: np.ndarray,
        weight: np.ndarray | None = None,
    ) -> PendingFit:
        """Start the fit from the start pose (t0, R0) to `observed_m` (M, 3) where `mask` (M,) is True, and
        return at once: JAX dispatches asynchronously, XLA computes on its own thread without the GIL, so
        the caller's numpy work and the solve share the two cores. Every input is copied into fresh arrays
        here, so the caller may change its own afterwards."""
        m = len(marker_segment)
        joints, segments, offsets = self._model_constants(joint_offsets_m, marker_segment, marker_offsets_m)
        start = np.concatenate([np.ravel(t0_m), np.ravel(R0_parent_segment)]).astype(DTYPE)
        observed = np.full((self.size(m), 3), np.nan, DTYPE)
        observed[:m] = np.where(np.asarray(mask, bool)[:, None] & np.isfinite(observed_m), observed_m, np.nan)
        outputs = _solve(
            start,
            joints,
            segments,
            offsets,
            observed,
            self._ones[self.size(m)] if weight is None else self.pad(np.asarray(weight, DTYPE)),
            self._prior_w,
            rtol=self.rtol,
            atol=self.atol,
            max_steps=self.max_steps,
        )
        return PendingFit(outputs, m)

    def fit(self, *args, **kwargs) -> FitResult:
        """`launch(...)` with the same arguments, waiting for its result (calibration, refinement, tests)."""
        return self.launch(*args, **kwargs).result()

    def _model_constants(self, joint_offsets_m, marker_segment, marker_offsets_m):
        """A subject model's arrays, padded and on the device once per model rather than once per solve
        (it halves the dispatch cost). Cached by identity: models are immutable and replaced, not edited."""
        key = (joint_offsets_m, marker_segment, marker_offsets_m)
        for k, v in self._constants:
            if all(a is b for a, b in zip(k, key)):
                return v
        v = tuple(jax.device_put(a) for a in (
            np.array(joint_offsets_m, DTYPE),
            self.pad(np.asarray(marker_segment, np.int32)),
            self.pad(np.asarray(marker_offsets_m, DTYPE)),
        ))
        self._constants = [(key, v)] + self._constants[:31]
        return v

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
        """How many times the solve has been traced (a test asserts it stays len(sizes) after warm-up)."""
        return _solve._cache_size()
