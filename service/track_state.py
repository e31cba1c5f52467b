"""What every part of the per-subject tracker shares: a subject's calibration (`SubjectModel`), what changes
frame to frame (`TrackState`), and the few small helpers the others all call (norms, gathering the labeled
points, a compiled rigid motion, the pose's joints, the segments with a label).

The tracker is split by concept, and its modules import one way: this one, then `partners` (the rigid
partners learned online), `segment_search` (finding a segment few of whose markers are labeled), `layouts`
(a segment's calibrated marker layout and what it corrects), and `tracker` (the per-frame loop). Only what
more than one of them needs lives here.
"""

from __future__ import annotations

import collections
import dataclasses
import functools

import numpy as np

from protocol.skeleton import N_SEGMENTS, PARENTS
from service import kernels

STILL_FRAMES = 3  # frames of unlabeled points kept (`TrackState.free_history`)
SHAPE_LAYOUT_TOL_M = 0.02  # only markers that kept their offset in their segment this well [m] take part in layout checks
_PARENTS = np.asarray(PARENTS, np.int64)


def _norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (np.linalg.norm costs several times more on these small arrays)."""
    return np.sqrt(np.einsum("...i,...i->...", v, v))


@dataclasses.dataclass(frozen=True)
class SubjectModel:
    """A subject's calibration: its markers and, when known, its skeleton."""

    name: str
    markers: tuple[str, ...]
    marker_segment: np.ndarray  # (M,) int, segment index of each marker (-1 until the skeleton is calibrated)
    marker_offsets_m: np.ndarray  # (M, 3) offset in the segment frame
    joint_offsets_m: np.ndarray  # (14, 3) segment origin in the parent frame
    has_skeleton: bool = False
    # The segments' marker layouts as first calibrated (from given labels, in seeded mode), which the
    # tracker checks labels against (`_relabel_by_shape`): refinements on the engine's own labels move
    # marker_offsets_m, never these. (M, 3) offsets, and (M,) how well each marker kept its offset over
    # the calibration frames [m] (`calibration.layout_residuals`); None = not measured.
    layout_offsets_m: np.ndarray | None = None
    layout_rms_m: np.ndarray | None = None

    @property
    def n_markers(self) -> int:
        return len(self.markers)

    @functools.cached_property
    def layout_joints_m(self) -> np.ndarray:
        """(N_SEGMENTS, 3) where each segment's joint, as the model has it now, lies in its calibrated layout
        (zeros without a measured layout). Refinement moves the joints and the offsets, keeping the
        segments' rotations, but not the layout: the searches and checks that hang a layout from a joint
        hang it here, not at the layout's own origin (the joint as calibrated). There, a serving forearm
        whose elbow refinement had moved 66 mm had its joint 5.5 cm off the upper arm's length from the
        shoulder, and stayed unlabeled in view for 45 frames (two players at L2). The rigid motion taking
        the model's offsets onto the layout places it: refinement reshapes a segment a little too (a head's
        back markers moved 5 cm more than its front ones, 85_12), and the mean shift of its markers
        then put a head's joint where its mirror image fitted better."""
        out = np.zeros((N_SEGMENTS, 3))
        if self.layout_rms_m is None or len(self.layout_rms_m) != self.n_markers:
            return out
        measured = (self.layout_rms_m < SHAPE_LAYOUT_TOL_M) & (self.marker_segment >= 0)
        for k in np.unique(self.marker_segment[measured]):
            rows = measured & (self.marker_segment == k)
            if rows.sum() >= 3:
                out[k] = rigid_motion(self.marker_offsets_m[rows], self.layout_offsets_m[rows])[1]
            else:  # (two markers: no rotation to take out)
                out[k] = np.mean(self.layout_offsets_m[rows] - self.marker_offsets_m[rows], axis=0)
        return out


@dataclasses.dataclass
class TrackState:
    """Everything that changes frame to frame for one subject (owned by the engine's registry)."""

    pos_m: np.ndarray  # (M, 3) last observed or predicted position
    vel_m_s: np.ndarray  # (M, 3)
    labeled: np.ndarray  # (M,) bool, labeled in the last processed frame
    ever_seen: np.ndarray  # (M,) bool
    last_t_ns: int
    # rigid-partner memory
    dist_n: np.ndarray  # (M, M) samples in the running distance statistics
    dist_mean_m: np.ndarray  # (M, M)
    dist_var_m2: np.ndarray  # (M, M)
    dist_slow_mean_m: np.ndarray  # (M, M) the same, with a long memory (SLOW_ALPHA)
    dist_slow_var_m2: np.ndarray  # (M, M)
    partners: np.ndarray  # (M, K) int, -1 = none
    snap_m: np.ndarray  # (M, M, 3): row i = every marker's position when i was last labeled (NaN = unlabeled then)
    snap_kept_m: np.ndarray  # (M, M, 3): row i of snap_m as it was before i's label was re-acquired (off probation)
    provisional: np.ndarray  # (M,) int, frames left in which a re-acquired label is re-checked
    # skeleton
    t_root_m: np.ndarray  # (3,)
    R_parent_segment: np.ndarray  # (14, 3, 3)
    skipped: int = 0  # solves skipped in a row
    frames: int = 0  # frames processed, counted from the subject's phase (`new_state`)
    search_waits: bool = False  # a segment search waits for the solve launched on the last frame
    lost_frames: int = 0  # frames running on which the subject was lost (fewer than 4 labels after tracking)
    last_labeled_t_ns: int = 0
    fit_rms_m: float = float("nan")  # of the latest completed fit
    fit_iterations: int = 0  # of the latest completed fit
    # the fit launched on a frame's final labels, (PendingFit, t_ns), collected at the next frame (`collect`)
    pending: tuple | None = None
    # a frame's bookkeeping (the layout check, the state update, the solve launch) that `step(defer=True)`
    # left for after its labels were published; `finish` runs it, and so does anything that reads the
    # state (`collect`)
    unfinished: object | None = None
    skel_pred_m: np.ndarray | None = None  # (M, 3) marker positions of the latest completed fit ...
    skel_vel_m_s: np.ndarray | None = None  # (M, 3) ... their velocity (from the fit before it) ...
    skel_t_ns: int = 0  # ... and the time of the frame it fitted
    acc_m_s2: np.ndarray | None = None  # (M, 3) from two measured velocities (labeled 3 frames running), else 0
    vel_measured: np.ndarray | None = None  # (M,) bool: vel_m_s comes from two observations
    acc_dt_s: float = 0.0  # the frame interval acc_m_s2 was measured over
    hidden_frames: np.ndarray | None = None  # (M,) int: frames since the marker was last labeled
    layout_hold: np.ndarray | None = None  # (M,) int: frames left in which the skeleton may not swap labels the layout checks moved
    settled: np.ndarray | None = None  # (M,) bool: the label is beyond the layout check's doubt (SETTLED_MIN_LABELS)
    # the layout check (`_relabel_by_shape`): per segment, the relabelling asked for on the last checks
    # and on how many checks running; per set of labeled markers (bytes), the RMS of each of its
    # relabellings of the layout onto itself; per segment, the share of checks on which the labels or a
    # permutation of them fitted the layout, and how many checks there were
    shape_votes: dict = dataclasses.field(default_factory=dict)
    shape_symmetry: dict = dataclasses.field(default_factory=dict)
    shape_fit: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(N_SEGMENTS))
    shape_checks: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(N_SEGMENTS))
    # `_complete_by_free_point`: per segment, the relabelling asked for on the last checks, and how many running
    complete_votes: dict = dataclasses.field(default_factory=dict)
    # `_reseat_outliers`: per marker, the point owner (marker, -1 = a free point) proposed on the last checks, and how many running
    reseat_votes: dict = dataclasses.field(default_factory=dict)
    # `_joints_m`: the segment origins of the pose (t_root_m, R_parent_segment, joint offsets) they were computed for
    joints_cache: tuple | None = None
    # (t_ns, points (N, 3)) of the last STILL_FRAMES frames: the points the subject left unlabeled, newest
    # last (`tracker._still_on_moving`)
    free_history: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=STILL_FRAMES))


def _gather(points: np.ndarray, point_index: np.ndarray) -> np.ndarray:
    """(M, 3) positions of the points each marker is labeled with, NaN where unlabeled (safe for N = 0)."""
    out = np.full((len(point_index), 3), np.nan)
    ok = point_index >= 0
    out[ok] = points[point_index[ok]]
    return out


def rigid_motion(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`calibration.rigid_motion`, compiled (`kernels.rigid_motion`): the searches make hundreds a frame."""
    return kernels.rigid_motion(np.require(a, np.float64, "CW"), np.require(b, np.float64, "CW"))


def _kabsch_rms(A: np.ndarray, B: np.ndarray, w: np.ndarray) -> np.ndarray:
    """RMS misfit (C,) of the best rigid motion taking A onto B, both (C, N, 3), over the points where
    w (C, N) is True. The optimal trace is s1 + s2 + sign(det H) s3 over the singular values of the
    cross-covariance H (Kabsch), so no rotation is formed, and they are the square roots of H^T H's
    eigenvalues, in closed form (the trigonometric solution of the characteristic cubic)."""
    # (a compiled loop, `kernels`: one call instead of ~50 numpy calls on small batches; A and B may be
    # broadcast views, the kernel takes writable contiguous arrays of one type: one compilation)
    return kernels.kabsch_rms(np.require(A, np.float64, "CW"), np.require(B, np.float64, "CW"), np.require(w, bool, "CW"))


def _joints_m(model: SubjectModel, st: TrackState) -> np.ndarray:
    """World positions (14, 3) of the segment origins in the current pose. Kept until the pose changes (a
    fit is collected: new arrays, never changed in place), since the searches ask several times a frame."""
    pose = (st.t_root_m, st.R_parent_segment, model.joint_offsets_m)
    c = st.joints_cache
    if c is None or any(a is not b for a, b in zip(c[:3], pose)):
        # (a fit's arrays come read-only from XLA: copies, so the kernel sees one type and compiles once)
        c = st.joints_cache = (*pose, kernels.world_transforms(*(np.require(a, np.float64, "CW") for a in pose), _PARENTS)[1])
    return c[3]


def _observed_segments(marker_segment: np.ndarray, labeled: np.ndarray) -> np.ndarray:
    """(N_SEGMENTS,) bool: segments with at least one labeled marker."""
    observed = np.zeros(N_SEGMENTS, bool)
    observed[marker_segment[labeled & (marker_segment >= 0)]] = True
    return observed
