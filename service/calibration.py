"""Subject calibration: from a cloud of identified markers in an upright pose to a skeleton model.

Works for any marker set: nothing here knows marker names. The subject's size is the height of its top
marker above its lowest; the vertical axis is z; the left-right axis is the main horizontal axis of the
cloud above the knees (shoulders and, in a T-pose, arms span it); forward is the perpendicular that points
from the shanks to the feet (toes stick out forward). Arms are placed along the line from each shoulder
to the farthest marker on that side, so a T-pose, hanging arms or a reach all calibrate. Each marker then
goes to the segment whose bone (a capsule of anthropometric radius) is nearest; segment frames equal the
body frame in the calibration pose (so joint angles are zero there: in a T-pose, the standard rest pose);
marker offsets are the markers' positions in their segment frames.

`detect_tpose` finds people standing in a T-pose in an unlabeled cloud (automatic initialisation).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from protocol.skeleton import PARENTS, SEGMENTS

S = {name: i for i, name in enumerate(SEGMENTS)}

# Anthropometric fractions of standing height (after Winter, Biomechanics of Human Movement, tab. 4.1).
_HIP_Z, _HIP_Y = 0.51, 0.085
_LUMBAR_Z, _THORACIC_Z, _NECK_Z = 0.63, 0.72, 0.845
_SHOULDER_Z, _SHOULDER_Y = 0.815, 0.125
_UPPERARM, _FOREARM_HAND = 0.186, 0.25
_KNEE_Z, _ANKLE_Z = 0.285, 0.045
_FOOT_FWD = 0.11
# Capsule radius of each segment [fraction of height] for the nearest-bone assignment.
_RADIUS = {
    "pelvis": 0.075, "abdomen": 0.08, "torso": 0.085, "head": 0.06,
    "l_upperarm": 0.03, "l_forearm": 0.025, "r_upperarm": 0.03, "r_forearm": 0.025,
    "l_thigh": 0.05, "l_shank": 0.035, "l_foot": 0.03, "r_thigh": 0.05, "r_shank": 0.035, "r_foot": 0.03,
}


class CalibrationError(ValueError):
    """The markers do not show an upright person this calibration can read."""


@dataclasses.dataclass(frozen=True)
class BodyFrame:
    R_world_body: np.ndarray  # (3, 3) columns: forward, left, up
    origin_m: np.ndarray  # (3,) floor point below the cloud's centre
    height_m: float


def body_frame(P: np.ndarray) -> BodyFrame:
    """Body frame of an upright person from their marker positions P (M, 3)."""
    P = P[np.isfinite(P[:, 0])]
    if len(P) < 8:
        raise CalibrationError(f"only {len(P)} markers visible; at least 8 are needed")
    floor, top = P[:, 2].min(), P[:, 2].max()
    h = top - floor
    if not 1.0 < h < 2.4:
        raise CalibrationError(f"cloud is {h:.2f} m tall; an upright person is 1.0-2.4 m")
    z = (P[:, 2] - floor) / h
    upper = P[z > 0.3, :2]
    c = upper.mean(0)
    w, V = np.linalg.eigh(np.cov((upper - c).T))
    lateral = V[:, 1]
    fwd = np.array([-lateral[1], lateral[0]])
    # Forward is where the toes point: on a foot the lowest markers (toe, metatarsals) lie ahead of the
    # higher ones (heel, ankle). Shank markers are no guide: they sit on the front of the shin in some sets.
    foot = z < 0.12
    if foot.sum() < 2:
        raise CalibrationError("no foot markers near the floor: the person is not standing")
    fz = z[foot]
    low = fz <= np.median(fz)
    if low.all():
        low = fz < fz.max()
    if (P[foot][low, :2].mean(0) - P[foot][~low, :2].mean(0)) @ fwd < 0:
        fwd = -fwd
    forward = np.array([fwd[0], fwd[1], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    left = np.cross(up, forward)
    origin = np.array([c[0], c[1], floor])
    return BodyFrame(np.stack([forward, left, up], axis=1), origin, float(h))


def _seg_dist(q, a, b):
    ab = b - a
    t = np.clip(((q - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.linalg.norm(q - (a + t[:, None] * ab), axis=1)


def calibrate(positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Skeleton of an upright subject from one frame of its markers (M, 3; NaN = unseen, filled by caller).

    Returns (marker_segment (M,), marker_offsets_m (M, 3), joint_offsets_m (14, 3), t_world_root_m (3,),
    R_parent_segment (14, 3, 3)) — the calibration pose is the model's zero pose.
    """
    bf = body_frame(positions_m)
    h = bf.height_m
    Q = (positions_m - bf.origin_m) @ bf.R_world_body / h  # body coordinates, in heights
    J = {}  # joint positions (segment origins), body coordinates, in heights
    J["pelvis"] = np.array([0.0, 0.0, _HIP_Z])
    J["abdomen"] = np.array([0.0, 0.0, _LUMBAR_Z])
    J["torso"] = np.array([0.0, 0.0, _THORACIC_Z])
    J["head"] = np.array([0.0, 0.0, _NECK_Z])
    tips = {}
    for side, s in (("l", 1.0), ("r", -1.0)):
        sh = np.array([0.0, s * _SHOULDER_Y, _SHOULDER_Z])
        arm = Q[np.isfinite(Q[:, 0]) & (s * Q[:, 1] > _SHOULDER_Y + 0.03) & (Q[:, 2] > 0.3)]
        if len(arm):
            far = arm[np.argmax(np.linalg.norm(arm - sh, axis=1))]
            d = (far - sh) / max(np.linalg.norm(far - sh), 1e-9)
        else:
            d = np.array([0.0, s, 0.0])
        J[f"{side}_upperarm"] = sh
        J[f"{side}_forearm"] = sh + d * _UPPERARM
        tips[f"{side}_forearm"] = sh + d * (_UPPERARM + _FOREARM_HAND)
        hip = np.array([0.0, s * _HIP_Y, _HIP_Z])
        J[f"{side}_thigh"] = hip
        J[f"{side}_shank"] = np.array([0.0, s * _HIP_Y, _KNEE_Z])
        J[f"{side}_foot"] = np.array([0.0, s * _HIP_Y, _ANKLE_Z])
        tips[f"{side}_foot"] = np.array([_FOOT_FWD, s * _HIP_Y, 0.01])
        tips[f"{side}_shank"] = J[f"{side}_foot"]
        tips[f"{side}_thigh"] = J[f"{side}_shank"]
        tips[f"{side}_upperarm"] = J[f"{side}_forearm"]
    tips["pelvis"], tips["abdomen"], tips["torso"], tips["head"] = J["abdomen"], J["torso"], J["head"], np.array([0.0, 0, 1.0])
    bones = {name: [(J[name], tips[name])] for name in SEGMENTS}
    bones["pelvis"].append((J["l_thigh"], J["r_thigh"]))
    # the shoulder girdle, short of the shoulder joints so upper-arm markers go to the arm
    bones["torso"].append((J["l_upperarm"] * [1, 0.6, 1], J["r_upperarm"] * [1, 0.6, 1]))
    bones["l_foot"].append((J["l_foot"] - [0.04, 0, 0.03], tips["l_foot"]))
    bones["r_foot"].append((J["r_foot"] - [0.04, 0, 0.03], tips["r_foot"]))
    cost = np.full((len(Q), len(SEGMENTS)), np.inf)
    for k, name in enumerate(SEGMENTS):
        d = np.min([_seg_dist(Q, a, b) for a, b in bones[name]], axis=0)
        cost[:, k] = d - _RADIUS[name]
    marker_segment = np.argmin(np.nan_to_num(cost, nan=np.inf), axis=1)
    joints_world = np.stack([J[n] for n in SEGMENTS]) * h @ bf.R_world_body.T + bf.origin_m
    joint_offsets = np.zeros((len(SEGMENTS), 3))
    for i, p in enumerate(PARENTS):
        if p >= 0:
            joint_offsets[i] = bf.R_world_body.T @ (joints_world[i] - joints_world[p])
    marker_offsets = (positions_m - joints_world[marker_segment]) @ bf.R_world_body
    R = np.tile(np.eye(3), (len(SEGMENTS), 1, 1))
    R[0] = bf.R_world_body
    return marker_segment, marker_offsets, joint_offsets, joints_world[0], R


def fill_reference(history_m: np.ndarray) -> np.ndarray:
    """One frame (M, 3) for calibration from labeled history (F, M, 3): the frame with most markers seen,
    with markers unseen there moved in from the nearest frame that has them (by the shift of the markers
    the two frames share)."""
    seen = np.isfinite(history_m[..., 0])
    ref_i = int(np.argmax(seen.sum(1)))
    ref = history_m[ref_i].copy()
    for j in np.flatnonzero(~seen[ref_i]):
        frames = np.flatnonzero(seen[:, j])
        if len(frames) == 0:
            continue
        f = frames[np.argmin(np.abs(frames - ref_i))]
        common = seen[f] & seen[ref_i]
        shift = (history_m[ref_i, common] - history_m[f, common]).mean(0) if common.any() else 0.0
        ref[j] = history_m[f, j] + shift
    return ref


def is_tpose(P: np.ndarray) -> bool:
    """An upright person with both arms stretched out horizontally (arm span about the body height)."""
    try:
        bf = body_frame(P)
    except CalibrationError:
        return False
    Q = (P - bf.origin_m) @ bf.R_world_body / bf.height_m
    span = Q[:, 1].max() - Q[:, 1].min()
    depth = Q[:, 0].max() - Q[:, 0].min()
    far = np.abs(Q[:, 1]) > 0.3
    if not (0.75 < span < 1.3) or depth > 0.4 or far.sum() < 4:
        return False
    arms_level = np.all((Q[far, 2] > 0.65) & (Q[far, 2] < 0.97))
    both = (Q[far, 1] > 0).any() and (Q[far, 1] < 0).any()
    return bool(arms_level and both)


def clusters(points: np.ndarray, radius_m: float = 0.5, min_points: int = 15) -> list[np.ndarray]:
    """Groups of points linked by chains of neighbours closer than radius_m (one group per person)."""
    if len(points) < min_points:
        return []
    pairs = cKDTree(points).query_pairs(radius_m, output_type="ndarray")
    from scipy.sparse import coo_matrix

    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    n, lab = connected_components(g, directed=False)
    return [np.flatnonzero(lab == k) for k in range(n) if (lab == k).sum() >= min_points]


def detect_tpose(points: np.ndarray, free: np.ndarray) -> list[np.ndarray]:
    """Indices (into points) of each group of free points that is a person in a T-pose."""
    idx = np.flatnonzero(free)
    return [idx[c] for c in clusters(points[idx]) if is_tpose(points[idx[c]])]
