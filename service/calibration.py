"""Subject calibration: from a cloud of identified markers in an upright pose (or lying on the floor,
`lying_rotations`: stood up, calibrated, laid back down) to a skeleton model.

Works for any marker set, with no template: the one thing read from marker names, where they have it, is
their side (LKNE / RKNE are twins, `mirror_name`). The subject's size is the height of its top marker above
its lowest; the vertical axis is z; the left-right axis is the main horizontal axis of the
cloud above the knees (shoulders and, in a T-pose, arms span it); forward is the perpendicular that points
from the shanks to the feet (toes stick out forward). Arms are placed along the line from each shoulder
to the farthest marker on that side, so a T-pose, hanging arms or a reach all calibrate. Each marker then
goes to the segment whose bone (a capsule of anthropometric radius) is nearest; segment frames equal the
body frame in the calibration pose (so joint angles are zero there: in a T-pose, the standard rest pose);
marker offsets are the markers' positions in their segment frames.

From labeled history (`calibrate_from_history`), the markers that keep their distances go to one segment
(`_by_rigidity`), a left/right pair of limb segments crossed by the geometry is uncrossed by the chain above
it (`_uncross_sides`), and of several frames' calibrations the one whose segments move most rigidly and whose
joints hold best over the history is kept (one frame's pose can mislead the body frame). Where the names
give twins, the kept calibration puts them on mirror segments: two segments that took each other's
markers exchange them back (`_mirror_segments`), then each twin off its mirror segment goes where the
history says (`_mirror_pairs`).

`detect_tpose` finds people standing in a T-pose in an unlabeled cloud (automatic initialisation).
"""

from __future__ import annotations

import dataclasses
import os
import warnings

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from protocol.skeleton import MIRRORS, N_SEGMENTS, PARENTS, SEGMENTS

S = {name: i for i, name in enumerate(SEGMENTS)}

# Anthropometric fractions of standing height (after Winter, Biomechanics of Human Movement, tab. 4.1).
_HIP_Z, _HIP_Y = 0.51, 0.085
_LUMBAR_Z, _THORACIC_Z, _NECK_Z = 0.63, 0.72, 0.845
_SHOULDER_Z, _SHOULDER_Y = 0.815, 0.125
_UPPERARM, _FOREARM_HAND = 0.186, 0.25
_KNEE_Z, _ANKLE_Z = 0.285, 0.045
_FOOT_FWD = 0.11
_SHIN_ABOVE_FOOT = 0.04  # (`_body_frame`) a foot marker this far above the others [height] is a shin marker
_FOOT_LENGTH = 0.16  # heel to toe tip, with a marker's reach: Winter's 0.152 of height
_PELVIS_RISE = 0.04  # the pelvis's bone across the hips runs this far above the hip joints
# A subject kneeling upright (knees on the floor, thighs and trunk upright, shins flat on the floor behind):
# its knee joints sit _KNEEL_KNEE_Z above the floor, so its trunk stands _KNEEL_DROP lower than standing and
# the top of its head is at _KNEEL_TOP of its standing height.
_KNEEL_KNEE_Z = 0.03
_KNEEL_DROP = _KNEE_Z - _KNEEL_KNEE_Z
_KNEEL_TOP = 1.0 - _KNEEL_DROP
# a marker inside the shoulders' width is an arm marker within this of the estimated arm bones (an upper-arm
# marker of an arm held against the chest sat 0.045-0.06 from them and went to the torso); above the
# shoulder joint, less (the acromion marker rides the shoulder girdle, which the torso carries)
_ARM_BONE_REACH, _ARM_BONE_REACH_TOP = 0.06, 0.045
ARM_NEIGHBOURS = 2  # (`calibrate`) a marker beside the body, outside its segment's capsule, whose this many nearest markers are one arm segment's, joins it
# Capsule radius of each segment [fraction of height] for the nearest-bone assignment. The abdomen is
# narrower than the pelvis (at 0.08 it took the four waist markers of the CMU set, leaving the root none).
_RADIUS = {
    "pelvis": 0.075, "abdomen": 0.06, "torso": 0.085, "head": 0.06,
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
    return _body_frame(P)[0]


def _body_frame(P: np.ndarray) -> tuple[BodyFrame, float]:
    """`body_frame` and how sure it is which way the body faces: how far [m] the toes lie ahead of the
    ankles, summed over the feet."""
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
    # left-right is the long horizontal axis of the shoulder band (shoulders are twice as wide as deep,
    # and swinging arms or legs hardly reach it); the whole upper body if the band is too sparse
    band = P[(z > 0.72) & (z < 0.9), :2]
    ref = band if len(band) >= 4 else upper
    w, V = np.linalg.eigh(np.cov((ref - ref.mean(0)).T))
    lateral = V[:, 1]
    fwd = np.array([-lateral[1], lateral[0]])
    # Forward is where the toes point: on each foot the highest marker sits over the ankle, at the back,
    # and the marker farthest from it is at the toes. (Marker heights alone mislead: some sets put the
    # toe marker on top of the toes, above the heel; shank markers sit on the front of the shin.)
    foot = z < 0.12
    if foot.sum() < 2:
        raise CalibrationError("no foot markers near the floor: the person is not standing")
    votes, strays = [], []
    # the feet are split by the midline between them (the upper body's put a foot of a wide stance under a
    # leaning trunk in the other foot's half: its "toe" was the other foot)
    side_of = (P[:, :2] - P[foot, :2].mean(0)) @ lateral
    for side in (side_of > 0, side_of <= 0):
        f_idx = np.flatnonzero(foot & side)
        # a marker standing well above the foot's others is low on the shin, not the ankle's (an ankle
        # marker sits 3-5 cm above heel and toe; a tennis player's tibia marker, 18 cm up, took the
        # ankle's place as the top marker and the foot voted backwards)
        z_top = np.sort(P[f_idx, 2])
        if len(f_idx) >= 3 and z_top[-1] - z_top[-2] > _SHIN_ABOVE_FOOT * h:
            f_idx = f_idx[P[f_idx, 2] < z_top[-1]]
        if len(f_idx) < 2:
            continue
        top = f_idx[np.argmax(P[f_idx, 2])]
        reach = np.linalg.norm(P[f_idx, :2] - P[top, :2], axis=1)
        far = f_idx[np.argmax(reach)]
        vote = (P[far, :2] - P[top, :2]) @ fwd
        # longer than a foot: the other foot, a stride away, fell in its half (a walker's heel-strike frame
        # weighed 1.7 m where a foot's vote is under 0.2 m, and turned cmu/07_01 around)
        if reach.max() > _FOOT_LENGTH * h:
            strays.append(vote)
            continue
        # The top marker must sit between the foot's ends (heel and toe: its two markers farthest apart),
        # nearer the heel. A foot with its toes raised has the toe marker on top, one on tiptoe a low shin
        # marker, and both then vote backwards (a tennis player turning into his serve faced backwards
        # on half the seed's frames). The vote counts by how clearly the top marker sits toward one end.
        d = np.linalg.norm(P[f_idx, None, :2] - P[None, f_idx, :2], axis=2)
        ends = np.unravel_index(np.argmax(d), d.shape)
        t = int(np.flatnonzero(f_idx == top)[0])
        if t in ends:  # (always so with two markers)
            strays.append(vote)
            continue
        near_end, far_end = sorted(d[t, list(ends)])
        votes.append(vote * (far_end - near_end) / (far_end + near_end))
    if not votes and not strays:
        raise CalibrationError("no foot markers near the floor: the person is not standing")
    if sum(votes or strays) < 0:  # strays decide only when no foot votes, and the frame is then unsure
        fwd = -fwd
    forward = np.array([fwd[0], fwd[1], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    left = np.cross(up, forward)
    origin = np.array([c[0], c[1], floor])
    return BodyFrame(np.stack([forward, left, up], axis=1), origin, float(h)), abs(float(sum(votes)))


def _arm_floor(kneel: bool) -> float:
    """The height [heights] above which markers out beside the body are taken for arm markers: above the
    knees standing; above the hips kneeling, where the thighs and shins lie lower (`_kneeling_frame`)."""
    return _HIP_Z if kneel else 0.3


def _kneeling_frame(P: np.ndarray) -> BodyFrame:
    """Body frame of a person kneeling upright (see _KNEEL_TOP) from their marker positions P (M, 3): its
    origin is where a standing person's feet would be, _KNEEL_DROP below the floor, so that the template's
    trunk and thighs stand where they kneel, and its height is the standing height. Left-right is the
    shoulder band's long axis, as standing; forward is away from the markers on the floor (the shins and
    feet lie behind the knees)."""
    P = P[np.isfinite(P[:, 0])]
    if len(P) < 8:
        raise CalibrationError(f"only {len(P)} markers visible; at least 8 are needed")
    floor, top = P[:, 2].min(), P[:, 2].max()
    h = (top - floor) / _KNEEL_TOP
    if not 1.0 < h < 2.4:
        raise CalibrationError(f"cloud is {top - floor:.2f} m tall; a person kneeling upright is {_KNEEL_TOP:.2f}-{2.4 * _KNEEL_TOP:.2f} m")
    z = (P[:, 2] - floor) / h + _KNEEL_DROP  # heights of the standing template
    upper = P[z > _HIP_Z, :2]
    low = P[z < _KNEEL_DROP + 0.06, :2]
    band = P[(z > 0.72) & (z < 0.9), :2]
    ref = band if len(band) >= 4 else upper
    if len(upper) < 4 or len(low) < 2:
        raise CalibrationError("no trunk above markers on the floor: the person is not kneeling upright")
    _, V = np.linalg.eigh(np.cov((ref - ref.mean(0)).T))
    fwd = np.array([-V[1, 1], V[0, 1]])
    if (low.mean(0) - upper.mean(0)) @ fwd > 0:
        fwd = -fwd
    forward = np.array([fwd[0], fwd[1], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    c = upper.mean(0)
    return BodyFrame(np.stack([forward, np.cross(up, forward), up], axis=1), np.array([c[0], c[1], floor - _KNEEL_DROP * h]), float(h))


def heading_votes(history_m: np.ndarray, n: int = 24) -> list[tuple[np.ndarray, np.ndarray]]:
    """Up to n frames of the history, evenly spread, each as (its markers (M, 3), which way it faces (3,)
    weighted by how sure it is, `_body_frame`), for `_vote_heading`. Each frame's hidden markers are filled
    in from nearby frames: a foot whose toe marker is hidden votes with its heel for the toe, backwards
    (cmu/85_12 and a tennis serve at L3 faced backwards). (Computed once per history: a calibration tries
    several frames, each twice.)"""
    votes = []
    for f in np.linspace(0, len(history_m) - 1, min(n, len(history_m))).astype(int):
        P = fill_reference(history_m, frame=f)
        try:
            bf_f, sure = _body_frame(P)
        except CalibrationError:
            continue
        votes.append((P, sure * bf_f.R_world_body[:, 0]))
    return votes


def _vote_heading(bf: BodyFrame, positions_m: np.ndarray, votes: list[tuple[np.ndarray, np.ndarray]]) -> BodyFrame:
    """Let the history's frames (`heading_votes`) vote on which way the body faces (at `positions_m`), so
    that one frame with a foot lifted or an arm across the shoulders cannot turn the subject around. A
    subject who turned meanwhile is turned back first: each frame's facing is carried onto `positions_m` by
    the rigid motion of the markers the two share (trimmed: swinging limbs drop out), and the votes are
    weighted by how sure each frame is."""
    fwd = bf.R_world_body[:, 0]
    total = np.zeros(3)
    ref_ok = np.isfinite(positions_m[:, 0])
    if votes:  # (every frame's two Kabsch solves batched: `_rigid_motions`)
        P = np.stack([p for p, _ in votes])  # (V, M, 3)
        facing = np.stack([f for _, f in votes])
        w = (ref_ok[None] & np.isfinite(P[:, :, 0])).astype(float)
        use = w.sum(1) >= 8
        P, facing, w = P[use], facing[use], w[use]
        ref = np.nan_to_num(positions_m)
        # from each frame to `positions_m`: b ~ R a + t, here with the frame's points as b (one `a` for all)
        # and inverted, as R^T takes the frame onto the reference
        Q = np.where(w[:, :, None] > 0, P, 0.0)
        R, t = _rigid_motions(ref, Q, w)
        err = np.linalg.norm(np.einsum("vyx,vmy->vmx", R, Q - t[:, None]) - ref, axis=2)
        cut = _nanquantile_rows(np.where(w > 0, err, np.nan), 0.6)
        keep = ((w > 0) & (err <= cut[:, None])).astype(float)
        R, _ = _rigid_motions(ref, Q, keep)
        total = np.einsum("vyx,vy->x", R, facing)
    if total @ fwd >= 0:
        return bf
    R = bf.R_world_body * np.array([-1.0, -1.0, 1.0])  # turn 180 degrees about z
    return BodyFrame(R, bf.origin_m, bf.height_m)


def _seg_dist(q, a, b):
    ab = b - a
    t = np.clip(((q - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.linalg.norm(q - (a + t[:, None] * ab), axis=1)


def _template(positions_m: np.ndarray, history_m: np.ndarray | None, feet_of: np.ndarray | None, votes: list | None,
              kneel: bool = False):
    """`calibrate`'s template of an upright subject on one frame of its markers (M, 3): (body frame, the
    markers in body coordinates [heights], joint positions {segment: (3,)} and bone tips there, cost (M, 14):
    each marker's distance from each segment's bone less its capsule radius [heights]). `kneel`: of a
    subject kneeling upright (`_kneeling_frame`), its shins and feet flat on the floor behind the knees."""
    bf = _kneeling_frame(positions_m) if kneel else body_frame(positions_m)
    if history_m is not None and len(history_m) >= 10 and not kneel:  # (the votes read standing feet)
        bf = _vote_heading(bf, positions_m, heading_votes(history_m) if votes is None else votes)
    h = bf.height_m
    Q = (positions_m - bf.origin_m) @ bf.R_world_body / h  # body coordinates, in heights
    J = {}  # joint positions (segment origins), body coordinates, in heights
    J["pelvis"] = np.array([0.0, 0.0, _HIP_Z])
    J["abdomen"] = np.array([0.0, 0.0, _LUMBAR_Z])
    J["torso"] = np.array([0.0, 0.0, _THORACIC_Z])
    J["head"] = np.array([0.0, 0.0, _NECK_Z])
    tips = {}
    heels = {"l": [-0.04, 0.0, -0.03], "r": [-0.04, 0.0, -0.03]}  # the heel's end of the foot, from the ankle
    bends = {}  # segment -> its rotation from its parent in the template's pose (kneeling), else none
    for side, s in (("l", 1.0), ("r", -1.0)):
        sh = np.array([0.0, s * _SHOULDER_Y, _SHOULDER_Z])
        ok = np.isfinite(Q[:, 0]) & (Q[:, 2] > _arm_floor(kneel))
        arm = Q[ok & ((s * Q[:, 1] > _SHOULDER_Y + 0.03) | ((s * Q[:, 1] > 0.09) & (np.linalg.norm(Q - sh, axis=1) < _UPPERARM + _FOREARM_HAND)))]
        # the elbow: toward the markers about one upper-arm length from the shoulder; the hand: the
        # farthest arm marker. Straight arms (T-pose, hanging) and bent ones alike.
        r = np.linalg.norm(arm - sh, axis=1) if len(arm) else np.zeros(0)
        mid = arm[(r > 0.12) & (r < 0.26)]
        if len(arm) and len(mid):
            d_ua = mid.mean(0) - sh
        elif len(arm):
            d_ua = arm[np.argmax(r)] - sh
        else:
            d_ua = np.array([0.0, s, 0.0])
        d_ua /= max(np.linalg.norm(d_ua), 1e-9)
        elbow = sh + d_ua * _UPPERARM
        # the hand: the farthest arm marker out beside the body, if any reaches past the elbow (a hand
        # hanging by a spread thigh is farther out than the thigh's markers, which may be farther away)
        out = s * arm[:, 1] > _SHOULDER_Y + 0.03 if len(arm) else np.zeros(0, bool)
        reach = np.where(out, r, -1.0) if (out & (r > _UPPERARM * 1.2)).any() else r
        if len(arm) and r.max() > _UPPERARM * 1.2:
            d_fa = arm[np.argmax(reach)] - elbow
            d_fa /= max(np.linalg.norm(d_fa), 1e-9)
        else:
            d_fa = d_ua
        J[f"{side}_upperarm"] = sh
        J[f"{side}_forearm"] = elbow
        tips[f"{side}_forearm"] = elbow + d_fa * _FOREARM_HAND
        hip = np.array([0.0, s * _HIP_Y, _HIP_Z])
        # with `feet_of` (the marker segments of a first calibration), the leg runs from the hip to where
        # that calibration's foot stands: a wide stance or a foot set back bent the straight-down leg away
        # from the markers (a toe went to the shank and a shin marker to the thigh, cmu/85_02). The sides
        # come from the first calibration, whose legs `_uncross_sides` has checked (feet taken by the
        # midline between them came out crossed mid-stride, and the legs above them with them, cmu/07_01).
        ankle = np.array([0.0, s * _HIP_Y, _ANKLE_Z])
        if kneel:
            leg = _kneeling_leg(Q, s)
            J[f"{side}_thigh"], J[f"{side}_shank"], J[f"{side}_foot"] = hip, leg["knee"], leg["ankle"]
            tips[f"{side}_thigh"], tips[f"{side}_shank"], tips[f"{side}_foot"] = leg["knee"], leg["ankle"], leg["tip"]
            tips[f"{side}_upperarm"] = J[f"{side}_forearm"]
            heels[side] = leg["heel"]
            bends.update({S[f"{side}_{stem}"]: R for stem, R in leg["bends"].items()})
            continue
        if feet_of is not None:
            on_foot = np.isfinite(Q[:, 0]) & (feet_of == S[f"{side}_foot"])
            if on_foot.any():
                ankle[:2] = Q[on_foot, :2].mean(0) - [0.5 * _FOOT_FWD, 0.0]
        J[f"{side}_thigh"] = hip
        J[f"{side}_shank"] = hip + (ankle - hip) * (_HIP_Z - _KNEE_Z) / (_HIP_Z - _ANKLE_Z)
        J[f"{side}_foot"] = ankle
        tips[f"{side}_foot"] = np.array([ankle[0] + _FOOT_FWD, ankle[1], 0.01])
        tips[f"{side}_shank"] = J[f"{side}_foot"]
        tips[f"{side}_thigh"] = J[f"{side}_shank"]
        tips[f"{side}_upperarm"] = J[f"{side}_forearm"]
    tips["pelvis"], tips["abdomen"], tips["torso"], tips["head"] = J["abdomen"], J["torso"], J["head"], np.array([0.0, 0, 1.0])
    bones = {name: [(J[name], tips[name])] for name in SEGMENTS}
    # the pelvis spans the hips above the hip joints (below them is thigh: a marker high on the thigh is not pelvis)
    bones["pelvis"].append((J["l_thigh"] + [0, 0, _PELVIS_RISE], J["r_thigh"] + [0, 0, _PELVIS_RISE]))
    # the shoulder girdle, short of the shoulder joints so upper-arm markers go to the arm
    bones["torso"].append((J["l_upperarm"] * [1, 0.6, 1], J["r_upperarm"] * [1, 0.6, 1]))
    bones["l_foot"].append((J["l_foot"] + heels["l"], tips["l_foot"]))
    bones["r_foot"].append((J["r_foot"] + heels["r"], tips["r_foot"]))
    cost = np.full((len(Q), len(SEGMENTS)), np.inf)
    for k, name in enumerate(SEGMENTS):
        d = np.min([_seg_dist(Q, a, b) for a, b in bones[name]], axis=0)
        cost[:, k] = d - _RADIUS[name]
    return bf, Q, J, tips, cost, bends


def _pitch(degrees: float) -> np.ndarray:
    """The rotation by `degrees` about the body's left axis: positive swings a limb hanging down backwards."""
    c, s_ = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]])


#: (`_kneeling_leg`) the legs tried for a subject kneeling upright, as (thigh, shin, foot) angles [degrees]
#: from standing straight (the foot flat ahead), positive swinging backwards: the knee on the floor with the
#: shin flat behind it, the instep on the floor or the toes tucked under; or the knee up with the foot
#: planted flat (kneeling on one knee), the shin upright or slanted. Of legs the markers fit alike, the
#: first is taken.
KNEELING_LEGS = ((0.0, 90.0, 180.0), (0.0, 90.0, 90.0),
                 (-90.0, 0.0, 0.0), (-90.0, 20.0, 0.0), (-90.0, -20.0, 0.0), (-90.0, 40.0, 0.0))


def _kneeling_leg(Q: np.ndarray, s: float) -> dict:
    """One leg of `_template`'s kneeling subject (s = 1 left, -1 right; Q its markers in body coordinates):
    of KNEELING_LEGS, the one the markers on its side around and below the hips sit closest to the bones of
    (or to the pelvis). {"knee", "ankle", "tip" (the toes) [heights], "heel" (from the ankle), "bends":
    {"thigh" | "shank" | "foot": the segment's rotation from its parent in that pose, the zero pose standing
    straight with the foot flat}}."""
    hip = np.array([0.0, s * _HIP_Y, _HIP_Z])
    thigh, shin = _HIP_Z - _KNEE_Z, _KNEE_Z - _ANKLE_Z
    mine = Q[np.isfinite(Q[:, 0]) & (s * Q[:, 1] > 0.0) & (Q[:, 2] < _HIP_Z + 2 * _PELVIS_RISE)]
    pelvis = _seg_dist(mine, hip + [0, 0, _PELVIS_RISE], hip * [1, -1, 1] + [0, 0, _PELVIS_RISE]) - _RADIUS["pelvis"]
    best, best_misfit = None, np.inf
    for a_thigh, a_shin, a_foot in KNEELING_LEGS:
        down = np.array([0.0, 0.0, -1.0])
        knee = hip + _pitch(a_thigh) @ down * thigh
        ankle = knee + _pitch(a_shin) @ down * shin
        foot_R = _pitch(a_foot)
        tip = ankle + foot_R @ [_FOOT_FWD, 0.0, -0.02]
        heel = foot_R @ [-0.04, 0.0, -0.03]
        d = np.stack([
            pelvis,
            _seg_dist(mine, hip, knee) - _RADIUS["l_thigh"],
            _seg_dist(mine, knee, ankle) - _RADIUS["l_shank"],
            np.minimum(_seg_dist(mine, ankle, tip), _seg_dist(mine, ankle + heel, tip)) - _RADIUS["l_foot"],
        ])
        misfit = float(np.maximum(d.min(0), 0.0).sum())
        if misfit < best_misfit:
            bends = {"thigh": _pitch(a_thigh), "shank": _pitch(a_shin - a_thigh), "foot": _pitch(a_shin).T @ foot_R}
            best, best_misfit = {"knee": knee, "ankle": ankle, "tip": tip, "heel": heel, "bends": bends}, misfit
    return best


def template_misfit(positions_m: np.ndarray, marker_segment: np.ndarray, kneel: bool = False) -> float:
    """How far [heights] the markers (M, 3) of an upright subject sit outside the capsules of the segments
    `marker_segment` gives them on `calibrate`'s template, mean over those seen: under 0.015 for a body
    lying still stood up head end first, two to four times that feet first (`calibrate_from_history`'s
    lying subjects, LYING_MAX_MISFIT)."""
    cost = _template(positions_m, None, None, None, kneel)[4]
    ok = np.isfinite(positions_m[:, 0])
    return float(np.mean(np.maximum(cost[ok, marker_segment[ok]], 0.0)))


def calibrate(
    positions_m: np.ndarray, history_m: np.ndarray | None = None, distance_sd: np.ndarray | None = None,
    feet_of: np.ndarray | None = None, votes: list | None = None, mirror_of: np.ndarray | None = None,
    given: np.ndarray | None = None, kneel: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Skeleton of an upright subject from one frame of its markers (M, 3; NaN = unseen, filled by caller).
    With `history_m` (F, M, 3) showing motion, markers whose nearest bones are close calls go to the
    segment whose markers keep the steadiest distances to them (they move rigidly together);
    `distance_sd`, the history's `_distance_sd` if the caller has it. `feet_of`, the marker segments of a
    first calibration of the same frame: its feet keep their markers, and the legs run to where they stand.
    `votes`, the history's `heading_votes` if the caller has them. `mirror_of`, each marker's named twin
    (`mirror_index`): with a history, twins are then put on mirror segments (`_mirror_pairs`). `given`: the
    marker segments to take instead of this frame's own (`calibrate_from_history`'s medoid), twins still
    mended; the frame gives the skeleton and the offsets. `kneel`: the subject kneels upright (`_template`).

    Returns (marker_segment (M,), marker_offsets_m (M, 3), joint_offsets_m (14, 3), t_world_root_m (3,),
    R_parent_segment (14, 3, 3)) — the calibration pose is the model's zero pose, but for a kneeling
    subject's legs: its zero pose stands straight, feet flat, and the calibration pose bends them as it
    kneels (`_kneeling_leg`), so joint angles read alike for subjects calibrated standing and kneeling.
    """
    bf, Q, J, tips, cost, bends = _template(positions_m, history_m, feet_of, votes, kneel)
    h = bf.height_m
    # Markers out to the side above the knees are arm markers (T-pose or hanging arms alike): split them
    # between upper arm and forearm by how far along the arm they sit. The rest take the nearest bone.
    arm_cols = [S[n] for n in ("l_upperarm", "l_forearm", "r_upperarm", "r_forearm")]
    bone_cost = cost.copy()
    cost[:, arm_cols] = np.inf
    marker_segment = np.argmin(np.nan_to_num(cost, nan=np.inf), axis=1)
    reach = np.where(Q[:, 2] > _SHOULDER_Z, _ARM_BONE_REACH_TOP, _ARM_BONE_REACH)
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        sh, el, tip = J[f"{side}_upperarm"], J[f"{side}_forearm"], tips[f"{side}_forearm"]
        d_up, d_fore = _seg_dist(Q, sh, el), _seg_dist(Q, el, tip)
        on_arm = np.isfinite(Q[:, 0]) & (Q[:, 2] > _arm_floor(kneel)) & (
            (sgn * Q[:, 1] > _SHOULDER_Y + 0.03) | ((sgn * Q[:, 1] > 0.09) & (np.minimum(d_up, d_fore) < reach))
        )
        marker_segment[on_arm] = np.where(d_up[on_arm] < d_fore[on_arm], S[f"{side}_upperarm"], S[f"{side}_forearm"])
        # a hand resting on the hip: its markers off the estimated forearm (the hand turned in), outside
        # the pelvis's capsule yet nearest to it, go with the arm markers nearest them (cmu/85_12: a wrist
        # marker calibrated onto the pelvis was lost in the first occlusion after the seed, for good)
        arm_segs = [S[f"{side}_upperarm"], S[f"{side}_forearm"]]
        beside = np.isfinite(Q[:, 0]) & (Q[:, 2] > _arm_floor(kneel)) & (sgn * Q[:, 1] > 0.09) & ~np.isin(marker_segment, arm_segs)
        for i in np.flatnonzero(beside):
            own = marker_segment[i]
            if cost[i, own] <= 0.0:
                continue  # inside its segment's capsule
            d = np.linalg.norm(Q - Q[i], axis=1)
            d[i] = np.inf
            d = np.where(np.isfinite(d), d, np.inf)
            near = np.argsort(d)[:ARM_NEIGHBOURS]
            k = marker_segment[near[0]]
            if k in arm_segs and np.all(marker_segment[near] == k) and d[near[-1]] < d[marker_segment == own].min(initial=np.inf):
                marker_segment[i] = k
    if given is not None:
        marker_segment = given.copy()
    elif feet_of is not None:  # the first pass's feet keep their markers (a heel raised mid-stride is not shank)
        on_feet = np.isin(feet_of, [S["l_foot"], S["r_foot"]])
        marker_segment[on_feet] = feet_of[on_feet]
    if history_m is not None and len(history_m) >= 10:
        sd = _distance_sd(history_m) if distance_sd is None else distance_sd
        if given is None:
            marker_segment = _by_rigidity(marker_segment, cost, history_m, bone_cost, sd=sd)
            marker_segment = _uncross_sides(marker_segment, sd)
        if mirror_of is not None:
            marker_segment = _mirror_pairs(_mirror_segments(marker_segment, mirror_of), sd, mirror_of, bone_cost)
    joints_world = np.stack([J[n] for n in SEGMENTS]) * h @ bf.R_world_body.T + bf.origin_m
    R = np.tile(np.eye(3), (len(SEGMENTS), 1, 1))
    R[0] = bf.R_world_body
    for k, bend in bends.items():
        R[k] = bend
    R_world, _ = world_transforms(joints_world[0], R, np.zeros((len(SEGMENTS), 3)))
    joint_offsets = np.zeros((len(SEGMENTS), 3))
    for i, p in enumerate(PARENTS):
        if p >= 0:
            joint_offsets[i] = R_world[p].T @ (joints_world[i] - joints_world[p])
    marker_offsets = (positions_m - joints_world[marker_segment]) @ bf.R_world_body
    for k in bends:
        on = marker_segment == k
        marker_offsets[on] = (positions_m[on] - joints_world[k]) @ R_world[k]
    return marker_segment, marker_offsets, joint_offsets, joints_world[0], R


# `_by_rigidity`: a marker moves when another segment's markers keep their distances to it at least twice as
# steady as its own segment's (JOINED_RATIO: four times, for the segment across a joint from it), and its
# own segment's do not within MIN_UNSTEADY_M.
MIN_UNSTEADY_M = 0.004
JOINED_RATIO = 0.25
STEADY_TIE = 1.5  # segments this close to the steadiest are told apart by their bones' distance


def _by_rigidity(
    marker_segment: np.ndarray, cost: np.ndarray, history_m: np.ndarray, bone_cost: np.ndarray | None = None, margin: float = 0.08,
    sd: np.ndarray | None = None,
) -> np.ndarray:
    """Reassign each marker among its plausible segments (bone cost within `margin` heights of the best,
    arm segments always plausible) to the one whose other markers keep the steadiest distances to it,
    when the history moved enough to tell (the best choice is clearly steadier than the geometric one).
    `sd`: the history's `_distance_sd`, if the caller has it.

    Markers move one at a time, the clearest case first, and each move changes the segments' members: hands
    hanging at the hips sit in the pelvis's capsule, and until they leave it, the pelvis markers' distances
    to them make the pelvis look unsteady to its own markers (a tennis player's ASIS/PSIS went to the thigh)."""
    sd = _distance_sd(history_m) if sd is None else sd
    m, n_seg = cost.shape
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a marker unseen in the frame has no finite cost
        best_cost = np.nanmin(np.where(np.isfinite(cost), cost, np.nan), axis=1)
    plausible = (cost - best_cost[:, None] < margin) | ~np.isfinite(cost)
    candidate = plausible & (np.isfinite(cost) | np.array([_is_arm(k) for k in range(n_seg)])[None, :])

    def steadiness_of(assignment):  # (M, S): median sd of each marker's distances to each segment's others
        st = np.full((m, n_seg), np.nan)
        for k in np.unique(assignment):
            vals = np.where((assignment == k)[None, :] & ~np.eye(m, dtype=bool), sd, np.nan)
            st[:, k] = _nanmedian_columns(vals.T)  # (NaN: no other member seen with it)
        return st

    # a marker its segment's other markers left is judged by the segment's first members (a hand hanging by
    # the thigh, once the thigh's markers went to the shank, is still told to go to the forearm)
    first = steadiness_of(marker_segment)[np.arange(m), marker_segment]
    out = marker_segment.copy()
    moved = np.zeros(m, bool)
    for _ in range(m):
        steadiness = steadiness_of(out)
        own = steadiness[np.arange(m), out]
        own = np.where(np.isfinite(own), own, first)
        options = np.where((candidate | (np.arange(n_seg)[None, :] == out[:, None])) & np.isfinite(steadiness), steadiness, np.inf)
        k_best = np.argmin(options, axis=1)
        if bone_cost is not None:
            # segments about as steady as the steadiest (an elbow that hardly bent leaves upper arm and
            # forearm alike): the nearest bone among them (a wrist hanging at the hip is forearm)
            near = options <= STEADY_TIE * options[np.arange(m), k_best][:, None]
            k_best = np.where(near.any(1), np.argmin(np.where(near, np.nan_to_num(bone_cost, nan=np.inf), np.inf), axis=1), k_best)
        best = options[np.arange(m), k_best]
        joined = np.array([PARENTS[kb] == o or PARENTS[o] == kb for kb, o in zip(k_best, out)])
        ratio = np.where(joined, JOINED_RATIO, 0.5)
        go = ~moved & np.isfinite(own) & (k_best != out) & (best < ratio * own) & (own > MIN_UNSTEADY_M)
        if not go.any():
            break
        i = int(np.argmax(np.where(go, own / np.maximum(best, 1e-9), -np.inf)))  # the clearest case
        out[i] = k_best[i]
        moved[i] = True
    return out


def _distance_sd(history_m: np.ndarray) -> np.ndarray:
    """(M, M) standard deviation of each pair of markers' distance over labeled history (F, M, 3) [m]; NaN
    for pairs seen together in fewer than 10 frames."""
    d = np.stack([cdist(frame, frame) for frame in history_m])  # (F, M, M); 20x faster than broadcasting
    n = np.isfinite(d).sum(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pairs never seen together: all-NaN
        return np.where(n >= 10, np.nanstd(d, axis=0), np.nan)


# `_uncross_sides`: a left/right pair of limb segments trades its markers when each side's markers keep their
# distances to the other side's chain above (parent and grandparent) this much steadier than to their own.
UNCROSS_RATIO = 0.5
_SIDE_PAIRS = tuple((S[f"l_{n}"], S[f"r_{n}"]) for n in ("thigh", "shank", "foot", "upperarm", "forearm"))


def _uncross_sides(marker_segment: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Give a left/right pair of limb segments each other's markers when the history says they are crossed.

    The nearest bone takes a foot set down across the midline (a walker's stride, 07_01) for the other
    foot, all of its markers at once, and `_by_rigidity` cannot see it: each foot's markers still move
    rigidly together. Its chain can: a foot's markers keep their distances to the shank and thigh above
    it, not to the other leg's. Pairs are judged proximal first, each against its chain as already
    settled (the thighs, hanging from the pelvis, keep the side the geometry gave them); `sd` is
    `_distance_sd` of the history, and a history that hardly moved (sd under MIN_UNSTEADY_M) changes
    nothing."""
    out = marker_segment.copy()

    def steadiness(own: np.ndarray, k: int) -> float:
        up = [p for p in (PARENTS[k], PARENTS[PARENTS[k]] if PARENTS[k] >= 0 else -1) if p >= 0]
        v = sd[np.ix_(own, np.isin(out, up))]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # no pair seen together: all-NaN
            return float(np.nanmedian(v)) if v.size else float("nan")

    for left, right in _SIDE_PAIRS:
        on_l, on_r = out == left, out == right
        if not on_l.any() or not on_r.any():
            continue
        now = steadiness(on_l, left) + steadiness(on_r, right)
        crossed = steadiness(on_r, left) + steadiness(on_l, right)
        if now > MIN_UNSTEADY_M and crossed < UNCROSS_RATIO * now:  # NaN compares False
            out[on_l], out[on_r] = right, left
    return out


# Named twins on mirror segments: two segments exchange their markers when that mends MIRROR_SWAP_GAIN more
# twins than it parts (`_mirror_segments`); a twin may move to a segment up to MIRROR_STEADY_RATIO times
# less steady to it than its own (`_mirror_pairs`); the mended calibration is kept if it scores within
# MIRROR_SCORE_SLACK of the one chosen unmended (`calibrate_from_history`).
MIRROR_SWAP_GAIN = 3
MIRROR_STEADY_RATIO = 1.5
MIRROR_SCORE_SLACK = 1.25


def _mirror_pairs(marker_segment: np.ndarray, sd: np.ndarray, mirror_of: np.ndarray, bone_cost: np.ndarray
                  ) -> np.ndarray:
    """Put named twins (LTHI and RTHI: `mirror_of[i]`, the index of marker i's twin, or -1) on mirror
    segments. Where they are not, one of the two is on the wrong segment, and one of two moves mends it:
    the twin whose distances to the new segment's markers are about as steady as to its own's (within
    MIRROR_STEADY_RATIO) may move, and of two that may, the one nearer its new bone (`bone_cost`, in
    heights) does (an elbow that hardly bent in the history leaves a forearm marker's steadiness alike on
    both arm segments). A move onto a segment left empty, from one next to it (a shin marker on the thigh,
    the shank bare), is taken when no other is."""
    out = marker_segment.copy()
    m = len(out)

    def steadiness(i: int, k: int) -> float:
        own = np.flatnonzero((out == k) & (np.arange(m) != i))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # no pair seen together: all-NaN
            return float(np.nanmedian(sd[i, own])) + 0.001 if len(own) else float("nan")

    for i in range(m):
        j = int(mirror_of[i])
        if j <= i or MIRROR_SEGMENT[out[i]] == out[j]:
            continue
        options, bare = [], []
        for x, k in ((i, int(MIRROR_SEGMENT[out[j]])), (j, int(MIRROR_SEGMENT[out[i]]))):
            now, new = steadiness(x, out[x]), steadiness(x, k)
            if new <= MIRROR_STEADY_RATIO * now:  # (NaN compares False)
                options.append((np.nan_to_num(bone_cost[x, k], nan=np.inf), new / now, x, k))
            elif not (out == k).any() and (PARENTS[k] == out[x] or PARENTS[out[x]] == k):
                bare.append((0.0, 0.0, x, k))
        if options or bare:
            _, _, x, k = min(options or bare)
            out[x] = k
    return out


def _mirror_segments(marker_segment: np.ndarray, mirror_of: np.ndarray) -> np.ndarray:
    """Give two segments each other's markers when that puts MIRROR_SWAP_GAIN more named twins on mirror
    segments than it parts, the best such exchange first. Rigidity gathers the markers that move together,
    and the bones' geometry names the groups; a hand resting on the hip through the seed sat by the
    pelvis's bone, and the groups' names came out exchanged (a tennis player's ASIS and PSIS on the right
    forearm, its wrist and finger markers on the pelvis: LFIN on the left forearm, RFIN on the pelvis).
    """
    out = marker_segment.copy()
    pairs = np.flatnonzero(mirror_of > np.arange(len(out)))
    partner = mirror_of[pairs]

    def agreeing(seg: np.ndarray) -> int:
        return int((MIRROR_SEGMENT[seg[pairs]] == seg[partner]).sum())

    for _ in range(len(SEGMENTS)):
        now, best, swap = agreeing(out), MIRROR_SWAP_GAIN - 1, None
        present = np.unique(out)
        for a in present:
            for b in present[present > a]:
                trial = np.where(out == a, b, np.where(out == b, a, out))
                gain = agreeing(trial) - now
                if gain > best:
                    best, swap = gain, trial
        if swap is None:
            break
        out = swap
    return out


def mirror_index(markers) -> np.ndarray:
    """(M,) each marker's named twin (`mirror_name`) among `markers`, -1 where it has none."""
    have = {name: i for i, name in enumerate(markers)}
    return np.array([have.get(other or "", -1) for other in mirror_names(markers)], dtype=np.int64)


def _is_arm(k: int) -> bool:
    return SEGMENTS[k].endswith(("upperarm", "forearm"))


def rigid_motion(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R (3, 3) and translation t (3,) that best take points a (N, 3) onto b (N, 3), b ~ R a + t
    (Kabsch). Hand-written: scipy's Rotation.align_vectors gives the same rotation at ~85 us a call, 4x
    this, and calibration makes thousands (nearly collinear points get the best fit there is, no warning)."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0  # a reflection: flip the least significant axis
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cb - R @ ca


def _rigid_motions(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`rigid_motion` of many frames at once: for each row p, the R (3, 3) and t (3,) taking the points a
    (K, 3) onto b[p] (K, 3) where w[p] (K,) is 1 (0: not used; those points must be finite, any value).
    Returns R (P, 3, 3), t (P, 3). One batched SVD instead of a call per frame: calibration makes thousands."""
    n = w.sum(1)[:, None]
    ca, cb = (w @ a) / n, np.einsum("pk,pkx->px", w, b) / n
    H = np.einsum("pk,pkx,pky->pxy", w, a[None] - ca[:, None], b - cb[:, None])
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    d = np.sign(np.linalg.det(V @ Ut))
    D = np.zeros((len(w), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)  # a reflection: flip the least significant axis
    R = V @ D @ Ut
    return R, cb - np.einsum("pxy,py->px", R, ca)


def layout_residuals(history_m: np.ndarray, marker_segment: np.ndarray, marker_offsets_m: np.ndarray, n_frames: int = 40) -> np.ndarray:
    """How well each marker keeps its offset in its segment over labeled history (F, M, 3): the median,
    over up to n_frames frames, of its distance [m] from where the rigid motion (Kabsch) of its segment's
    markers seen in that frame (3 or more) puts it. NaN where never measured. Skin over a joint, a marker
    given the wrong segment or a hand marker on the forearm read centimetres; markers of one bone, a few
    millimetres. (Every frame's Kabsch of a segment in one batched SVD: calibration scores ten candidate
    models this way, and one `rigid_motion` call per frame and segment made it ~40 % of a calibration.)"""
    F, M = history_m.shape[:2]
    pick = np.linspace(0, F - 1, min(n_frames, F)).astype(int) if F else np.zeros(0, int)
    if not len(pick):
        return np.full(M, np.nan)
    res = np.full((len(pick), M), np.nan)
    frames = history_m[pick]
    seen = np.isfinite(frames[:, :, 0])
    for k in np.unique(marker_segment):
        idx = np.flatnonzero(marker_segment == k)
        w = seen[:, idx].astype(float)  # (P, K)
        rows = np.flatnonzero(w.sum(1) >= 3)
        if len(idx) < 3 or not len(rows):
            continue
        w = w[rows]
        a = marker_offsets_m[idx]  # (K, 3)
        b = np.where(w[:, :, None] > 0, frames[rows][:, idx], 0.0)  # (P, K, 3)
        R, t = _rigid_motions(a, b, w)
        err = np.linalg.norm(np.einsum("pxy,ky->pkx", R, a) + t[:, None] - b, axis=2)
        res[np.ix_(rows, idx)] = np.where(w > 0, err, np.nan)
    return _nanmedian_columns(res)


def _nanmedian_columns(v: np.ndarray) -> np.ndarray:
    """np.nanmedian(v, axis=0) of a 2-D array, NaN for all-NaN columns, without its warnings and at a
    fraction of its cost on small arrays (it goes through masked arrays: ~0.4 ms a call here, and
    calibration makes hundreds). Hand-written: NaN sorts last, so each column's median is read at its count."""
    s = np.sort(v, axis=0)
    n = np.isfinite(v).sum(0)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[None], 0)[0]
    hi = np.take_along_axis(s, np.maximum(n // 2, 0)[None], 0)[0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def _nanquantile_rows(v: np.ndarray, q: float) -> np.ndarray:
    """np.nanquantile(v, q, axis=1) of a 2-D array whose rows each hold a finite value, to the bit (its
    linear interpolation, as numpy computes it). Hand-written: numpy's runs a Python function per row
    (apply_along_axis), 1.7 ms on 24 x 41 against 30 us here; it was a tenth of a calibration's time
    (`_vote_heading`). NaN sorts last, so each row's quantile is read at its count."""
    s = np.sort(v, axis=1)
    n = np.isfinite(v).sum(1)
    pos = q * (n - 1)
    lo = np.floor(pos).astype(np.intp)
    t = pos - lo
    rows = np.arange(len(v))
    a, b = s[rows, lo], s[rows, np.minimum(lo + 1, n - 1)]
    d = b - a
    return np.where(t >= 0.5, b - d * (1 - t), a + d * t)  # (numpy's lerp, from the nearer end)


def fill_reference(history_m: np.ndarray, n_near: int = 5, frame: int | None = None) -> np.ndarray:
    """One frame (M, 3) for calibration from labeled history (F, M, 3): `frame`, by default the one with
    most markers seen, with markers unseen there moved in from the nearest frame that has them, by the
    rigid motion (Kabsch) of their n_near nearest markers seen in both frames: a limb that turned between
    the two frames carries its markers along (the cloud's mean shift put a sternum marker seen 2 s earlier 6-15 cm off, where it
    was never found again). With fewer than 3 such neighbours, the shift of the markers the frames share."""
    seen = np.isfinite(history_m[..., 0])
    ref_i = int(np.argmax(seen.sum(1))) if frame is None else frame
    ref = history_m[ref_i].copy()
    for j in np.flatnonzero(~seen[ref_i]):
        frames = np.flatnonzero(seen[:, j])
        if len(frames) == 0:
            continue
        f = frames[np.argmin(np.abs(frames - ref_i))]
        common = np.flatnonzero(seen[f] & seen[ref_i])
        src = history_m[f]
        if len(common) >= 3:
            near = common[np.argsort(np.linalg.norm(src[common] - src[j], axis=1))[:n_near]]
            R, t = rigid_motion(src[near], history_m[ref_i, near])
            ref[j] = R @ src[j] + t
        else:
            shift = (history_m[ref_i, common] - src[common]).mean(0) if len(common) else 0.0
            ref[j] = src[j] + shift
    return ref


# `calibrate_from_history` tries the frame with most markers seen and up to CANDIDATE_FRAMES others seen
# about as fully (at most 2 markers fewer), and takes another's calibration only if it explains the history
# clearly better (its score under CANDIDATE_GAIN times the first's).
CANDIDATE_FRAMES = 4
CANDIDATE_GAIN = 0.35
# The frames' calibrations vote, too: the marker segments of the one that agrees most with the others
# (`_medoid`) are taken, on the chosen frame's skeleton and offsets, if that scores within MEDOID_SCORE_SLACK
# of the chosen calibration and leaves no more named twins apart (`_twins_apart`). The score hardly tells a
# heel on the shank from one on the foot (a dribbling player's ankles bent little in the seed: the fullest
# frame, a heel raised, put both heels and ankles on the shanks, four frames on the feet). A majority can be
# wrong too: with a hand resting on the hip, three frames of four put the pelvis's markers on the forearm and
# the hand's on the pelvis, which the twins tell (the hips' markers on one forearm). (Seed calibrations of all
# labeled files, L2/L3, 18 seeds, `benchmarks.skeleton`: markers off their named segment 748 -> 656 of
# 13644; cmu/07_01 39 -> 6, two players 16 -> 2. Dev suite: L3 98.495 -> 98.524 %, the dribbling player's
# worst run 90.0 -> 94.6 %; L2 99.315 -> 99.317 %.)
MEDOID_MIN_FRAMES = 3
MEDOID_SCORE_SLACK = 2.0


#: With a pose solver (the engine passes its own), the candidates are also judged by what the tracker will
#: do with them: their skeletons posed on SOLVE_FRAMES frames of the history (`solve_misfit`). The static
#: score reads rigid clusters and joints, not whether the bones can reach the markers: a dribbling player's
#: fullest frame scored 14.7 mm and its skeleton posed the history to 28 mm, another frame's to 10 mm; its
#: heels then went to the shanks by the frames' vote (`_medoid`, scored 11.3 mm), and the skeleton posed it
#: to 69 mm; the engine's solves missed by 90-110 mm for 1.6 s, the left foot 0.3 m off (basketball at L2,
#: seed 1). So when the chosen calibration misfits by more than SOLVE_FLOOR_M (skin moves markers by ~1 cm:
#: under it, every candidate fits and the static score chose), another frame's is taken if it misfits
#: under SOLVE_GAIN times as much; the medoid's segments and the mended twins are kept only if theirs
#: misfits within SOLVE_SLACK of it (or the floor). (Dev suite, 18 realizations: the solves' residual p90,
#: mean over runs, 23.5 -> 20.9 mm at L2 and 24.5 -> 22.1 at L3, the worst run 107 -> 74 and 83 -> 60 mm;
#: labels L2 99.324 -> 99.317 %, L3 98.561 -> 98.562 %, 11 runs up, 12 down. Without the floor a lying
#: seed's 7 mm gave way to 2.4, and 03_rolling lost 8 points on that run.)
SOLVE_FRAMES = 12
SOLVE_GAIN = 0.5
SOLVE_SLACK = 1.25
SOLVE_FLOOR_M = 0.015


def solve_misfit(solver, history_m: np.ndarray, frame: int, result: tuple, n_frames: int = SOLVE_FRAMES) -> float:
    """Median RMS [m] of calibration `result` (as `calibrate_from_history` returns it), made from history
    frame `frame`, posed by `solver` (a `PoseSolver`) on n_frames frames spread over history_m (F, M, 3):
    tracked from `frame` forwards and backwards, each frame solved (up to twice, as the engine's catch-up)
    from the pose of the frame before it. A failed solve counts as 1 m. The median: tracked across ~0.1 s
    gaps, a fast limb can lose its pose on a few frames whatever the skeleton (a serving player's, 0.8 m
    off on the last three of twelve, and 5-24 mm on the rest)."""
    seg, off, joints, t_root, R, _ = result
    picks = np.unique(np.linspace(0, len(history_m) - 1, n_frames).astype(int))
    misfits = []
    for chain in (picks[picks >= frame], picks[picks < frame][::-1]):
        t, Rp = t_root, R
        for k in chain:
            seen = np.isfinite(history_m[k, :, 0])
            if seen.sum() < 4:
                continue
            for _ in range(2):  # (the second only if the first left the markers SOLVE_FLOOR_M off)
                fit = solver.fit(t, Rp, joints, seg, off, history_m[k], seen)
                if not fit.ok:
                    break
                t, Rp = fit.t_world_root_m, fit.R_parent_segment
                if fit.residual_rms_m <= SOLVE_FLOOR_M:
                    break
            misfits.append(fit.residual_rms_m if fit.ok else 1.0)
    return float(np.median(misfits)) if misfits else np.inf


def lopsided(marker_segment: np.ndarray) -> bool:
    """True if a limb segment carries no marker while its twin on the other side carries two or more: a
    calibration that put a whole forearm's markers on the upper arm, or a hand hanging by the hip on the
    pelvis (a marker set is laid out alike on both sides; the person is not)."""
    count = np.bincount(marker_segment[marker_segment >= 0], minlength=N_SEGMENTS)
    return bool(np.any((count == 0) & (count[MIRROR_SEGMENT] >= 2)))  # (a trunk segment is its own mirror)


def calibrate_from_history(history_m: np.ndarray, mirror_of: np.ndarray | None = None, solver=None):
    """(marker_segment, marker_offsets_m, joint_offsets_m, t_world_root_m, R_parent_segment, layout_rms_m)
    of the calibration that best explains labeled history (F, M, 3), or None if no frame of it calibrates:
    that of an upright subject (`_calibrate_upright`), or, for a subject lying down (`lying_rotations`), its
    calibration stood up the way (head end first, feet first, or along the arms) whose frame the template
    explains best (`template_misfit`, under LYING_MAX_MISFIT), laid back down. With `solver` (a
    `PoseSolver`), candidates are judged by their solves too (SOLVE_GAIN). Pure, for the helper process."""
    upright = _calibrate_upright(history_m, mirror_of, solver=solver)
    if kneels(history_m):
        # a still seed scores any assignment alike; kneeling, it scored better kneeling than standing
        # (KneeltoProne, L2, seeds 0-2: 6.9-8.3 mm against 9.6-20.6 mm), or nearly as well (a recalibration
        # at L3, seed 1: 9.5 against 9.3 mm, and the standing one's spine ran off 170 degrees); a standing
        # subject the low markers took for kneeling scored 18-180 % worse kneeling (basketball, 3 seeds of 48)
        kneeling = _calibrate_upright(history_m, mirror_of, kneel=True, solver=solver)
        if kneeling is not None and (upright is None or kneeling[0] < KNEEL_SCORE_SLACK * upright[0]):
            return kneeling[1]
    if upright is not None:
        return upright[1]
    # stood up each way, the template's assignment of one frame says which way is up (a subject lying
    # still moves no joint, so the history's score cannot tell); the history calibrates that way alone
    # (each way in full took 2.3x an upright calibration, 0.5 s on 03_rolling's seed beside the benchmark;
    # this way 0.18 s on an idle machine)
    best, best_misfit = None, LYING_MAX_MISFIT
    fullest = fill_reference(history_m)
    for R_up in lying_rotations(fullest):
        ref = fullest @ R_up.T
        try:
            misfit = template_misfit(ref, calibrate(ref)[0])
        except CalibrationError:
            continue
        if misfit < best_misfit:
            best, best_misfit = R_up, misfit
    if best is None:
        return None
    stood = _calibrate_upright(history_m @ best.T, mirror_of, solver=solver)
    if stood is None:
        return None
    seg, off, joints, t_root, R, layout = stood[1]
    R = R.copy()
    R[0] = best.T @ R[0]  # the root's turn and place back in the lying world (the rest are body-relative)
    return seg, off, joints, best.T @ t_root, R, layout


#: (`lying_rotations`) a frame under this tall [m] and at least this long horizontally is a subject lying
#: down (an upright one is 1.0-2.4 m tall, `_body_frame`)
LYING_MAX_HEIGHT_M, LYING_MIN_LENGTH_M = 1.0, 1.0
#: ... which is calibrated stood up the way round whose fullest frame `calibrate`'s template explains better
#: (the history's score cannot tell: a subject lying still moves no joint), if its markers sit outside their
#: capsules by under this [heights] on average (`template_misfit`). numediart/03_rolling's seed, lying prone
#: and still, over 5 realizations: 0.004-0.015 head end up, 0.014-0.039 feet up; frames of it rolling over
#: 0.06-0.22 either way.
LYING_MAX_MISFIT = 0.025


def lying_rotations(positions_m: np.ndarray) -> list[np.ndarray]:
    """For a subject lying down in one frame of its markers (M, 3; NaN = unseen; see LYING_MAX_HEIGHT_M),
    the rotations (3, 3) that may stand it up, p -> R p: each turns one of the frame's main horizontal axes
    to the vertical, one way or the other, about a horizontal axis (head to feet is the longer axis, unless
    the arms are stretched out: a T-pose's span is its height). None otherwise. A subject lying is an
    upright one turned over: the bones and markers are the same (numediart/03_rolling rolls on the floor
    from its first frame)."""
    P = positions_m[np.isfinite(positions_m[:, 0])]
    if len(P) < 8 or np.ptp(P[:, 2]) >= LYING_MAX_HEIGHT_M:
        return []
    _, V = np.linalg.eigh(np.cov((P[:, :2] - P[:, :2].mean(0)).T))
    if np.ptp(P[:, :2] @ V[:, -1]) < LYING_MIN_LENGTH_M:
        return []
    turns = []
    for axis in (V[:, 1], V[:, 0]):
        for u in (axis, -axis):  # u to +z: a quarter turn about the horizontal axis u x z
            k = np.array([u[1], -u[0], 0.0])
            K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
            turns.append(np.eye(3) + K + K @ K)  # Rodrigues at 90 degrees (|k| = 1)
    return turns


#: (`kneels`) a frame shows a subject kneeling when the markers low on one side of it (under a seventh of its
#: height: a shin and foot on the floor, or a foot) reach this share of its height apart: a shin lying flat
#: with its foot (KneeltoProne: 0.38-0.41) rather than a foot (standing: 0.08-0.16 of a standing height)
KNEEL_MIN_SPAN = 0.3
#: ... and its kneeling calibration is taken if it scores under this times the standing one's
KNEEL_SCORE_SLACK = 1.1


def kneels(history_m: np.ndarray, n_frames: int = 9) -> bool:
    """Whether labeled history (F, M, 3) shows a subject kneeling upright (KNEEL_MIN_SPAN) in most of up to
    n_frames frames, evenly spread, and no taller than a kneeling person is (`_kneeling_frame`): then
    `calibrate_from_history` calibrates it kneeling too, and keeps the better scoring calibration."""
    votes = tried = 0
    for f in np.linspace(0, len(history_m) - 1, min(n_frames, len(history_m))).astype(int):
        P = history_m[f][np.isfinite(history_m[f, :, 0])]
        if len(P) < 8:
            continue
        tried += 1
        floor, hk = P[:, 2].min(), np.ptp(P[:, 2])
        if not 1.0 < hk / _KNEEL_TOP < 2.4:
            continue
        z = (P[:, 2] - floor) / hk
        band = P[(z > 0.62) & (z < 0.87), :2]
        low = P[z < 0.15, :2]
        if len(band) < 3 or len(low) < 3:
            continue
        _, V = np.linalg.eigh(np.cov((band - band.mean(0)).T))
        side = (low - low.mean(0)) @ V[:, 1]
        span = max((cdist(low[m], low[m]).max() for m in (side > 0, side <= 0) if m.sum() >= 2), default=0.0)
        votes += span > KNEEL_MIN_SPAN * hk
    return 2 * votes > tried > 0


def _calibrate_upright(history_m: np.ndarray, mirror_of: np.ndarray | None = None, kneel: bool = False,
                       solver=None):
    """(score, calibration) of the calibration that best explains labeled history (F, M, 3) of an upright
    subject, or None if no frame of it calibrates; the score, lower the better, is `layout_residuals`'
    median plus `articulation_error` [m].

    One frame's pose can mislead `calibrate` (a boxer's guard, arms forward across the shoulder line, turned
    its body frame: head markers went to the forearm, 22 of 33 markers off their segment, cmu_02_05).
    So several frames are calibrated, each scored by how rigidly its segments' markers move over the
    history (`layout_residuals`) plus how well its joints hold the segments together
    (`articulation_error`); the best replaces the fullest frame's when it scores under CANDIDATE_GAIN of
    it. Each frame is calibrated twice, legs straight down and then to where the first pass's feet stand
    (`calibrate`'s feet_of), and the better scoring of the two counts. A lopsided calibration (`lopsided`: a
    forearm left empty while the other carries its markers) loses to any that is not, whatever their scores:
    a seed held still lets an arm's markers move as one. In the two-player tennis recording a forearm's
    markers went to the upper arm, or to the upper arm and pelvis, in 2 of 36 seed calibrations at L2; over
    the 36, 39 markers were off their segment, 8 now (all files, 18 realizations: 880 -> 748 of 13644; dev
    suite: L3 98.410 -> 98.439 %, two players at L3 98.06 -> 98.26 %, 9 runs up, 1 down). The frames then
    vote on each marker's segment (`_medoid`, see MEDOID_SCORE_SLACK). Markers never
    seen keep offset zero on whatever segment the calibration left them (nothing is known of them: a
    refinement, `engine.refined_model`, moves them once they are seen and the fit suffers). With `mirror_of` (each
    marker's named twin, `mirror_index`), the chosen calibration is made again with its twins mended
    (`calibrate`'s mirror_of), and kept if it scores within MIRROR_SCORE_SLACK of it. With `solver`, the
    skeletons' solves of the history judge too (`solve_misfit`, SOLVE_GAIN, SOLVE_SLACK)."""
    seen = np.isfinite(history_m[..., 0]).sum(1)
    first = int(np.argmax(seen))
    full = np.flatnonzero(seen >= seen[first] - 2)
    others = full[np.linspace(0, len(full) - 1, min(CANDIDATE_FRAMES, len(full))).astype(int)]
    sd = _distance_sd(history_m)
    votes = heading_votes(history_m) if len(history_m) >= 10 else None  # (as `calibrate` would, once)

    def attempt(ref: np.ndarray, feet_of: np.ndarray | None, mirror: np.ndarray | None,
                given: np.ndarray | None = None):  # (score, result)
        ok = np.isfinite(ref[:, 0])
        seg, off, joints, t_root, R = calibrate(np.where(ok[:, None], ref, np.nan), history_m, sd, feet_of, votes,
                                                mirror, given, kneel)
        off = np.where(ok[:, None], off, 0.0)  # never seen: at the segment's origin (see above)
        layout = layout_residuals(history_m, seg, off)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # nothing measured: NaN, scored as the worst
            score = np.nanmedian(layout) + articulation_error(ref, history_m, seg, joints, t_root, R)
        return (score if np.isfinite(score) else np.inf), (seg, off, joints, t_root, R, layout)

    best, best_score, first_score, best_args, best_lop = None, np.inf, np.inf, None, False
    tried = []  # (score, result, args, lopsided) of each frame
    for i in [first, *sorted(set(others.tolist()) - {first})]:
        ref = fill_reference(history_m, frame=i)
        score, result, feet_of, args = np.inf, None, None, None
        for _ in range(2):  # legs straight down, then to where the first pass's feet stand; the better counts
            try:
                s_, r_ = attempt(ref, feet_of, None)
            except CalibrationError:
                break
            if result is None or s_ < score:
                score, result, args = s_, r_, (ref, feet_of, i)
            feet_of = r_[0]
        if result is None:
            continue
        if best is None:
            first_score = score
        lop = lopsided(result[0])
        tried.append((score, result, args, lop))  # (args: ref, feet_of, frame)
        better = score < best_score and score < CANDIDATE_GAIN * first_score
        if best is None or (best_lop and not lop) or (lop == best_lop and better):
            best, best_score, best_args, best_lop = result, score, args, lop
    if best is None:
        return None
    best_fit = np.inf  # the chosen calibration's `solve_misfit` (with a solver)
    if solver is not None:
        best_fit = solve_misfit(solver, history_m, best_args[2], best)
        fits = [np.inf if result is best or (lop and not best_lop) or best_fit <= SOLVE_FLOOR_M
                else solve_misfit(solver, history_m, args[2], result) for _, result, args, lop in tried]
        k = int(np.argmin(fits))
        if best_fit > SOLVE_FLOOR_M and fits[k] < SOLVE_GAIN * best_fit:
            best_score, best, best_args, best_lop = tried[k]
            best_fit = fits[k]

    def fits_as_well(result: tuple) -> bool:  # (without a solver, always)
        if solver is None:
            return True
        fit = solve_misfit(solver, history_m, best_args[2], result)
        return fit <= max(SOLVE_SLACK * best_fit, SOLVE_FLOOR_M)

    medoid, given = _medoid(tried, best_lop), None
    if (medoid is not None and (medoid[1][0] != best[0]).any()
            and _twins_apart(medoid[1][0], mirror_of) <= _twins_apart(best[0], mirror_of)):
        # the medoid's segments on the chosen frame's skeleton and offsets (the fullest frame's: a frame with
        # a marker hidden leaves its offset unknown)
        score, result = attempt(*best_args[:2], None, medoid[1][0])
        if (score <= MEDOID_SCORE_SLACK * best_score and (best_lop or not lopsided(result[0]))
                and fits_as_well(result)):
            best, best_score, given = result, score, medoid[1][0]
    if mirror_of is not None and (mirror_of >= 0).any():
        # named twins mended on the chosen calibration only (mended, a poor frame's calibration scored
        # close enough to a good one's to keep it: the tennis player's wrists stayed on the thighs)
        score, result = attempt(*best_args[:2], mirror_of, given)
        if (score <= MIRROR_SCORE_SLACK * best_score and (best_lop or not lopsided(result[0]))
                and fits_as_well(result)):
            best, best_score = result, score
    return best_score, best


def _twins_apart(marker_segment: np.ndarray, mirror_of: np.ndarray | None) -> int:
    """How many markers with a named twin (`mirror_index`) are not on the mirror image of its segment (0
    without names)."""
    if mirror_of is None:
        return 0
    has = np.flatnonzero(mirror_of >= 0)
    return int(np.count_nonzero(MIRROR_SEGMENT[marker_segment[has]] != marker_segment[mirror_of[has]]))


def _medoid(tried: list, lop_allowed: bool):
    """Of the frames' calibrations `tried` ((score, result, args, lopsided), lopsided ones only if
    `lop_allowed`), the one whose marker segments agree most with the others' (markers on the same segment,
    summed over them), or None with fewer than MEDOID_MIN_FRAMES."""
    tried = [t for t in tried if lop_allowed or not t[3]]
    if len(tried) < MEDOID_MIN_FRAMES:
        return None
    segs = np.stack([t[1][0] for t in tried])  # (C, M)
    agree = (segs[:, None, :] == segs[None, :, :]).sum(axis=(1, 2))
    return tried[int(np.argmax(agree))]


def articulation_error(ref: np.ndarray, history_m: np.ndarray, marker_segment: np.ndarray, joint_offsets_m: np.ndarray,
                       t_root: np.ndarray, R_parent_segment: np.ndarray, n_frames: int = 20) -> float:
    """How well a calibration's joints hold its segments together over labeled history (F, M, 3): the
    median [m], over up to n_frames frames and the joints whose two segments each show 3 markers there and
    in `ref` (the calibration frame), of the distance between where the two segments' rigid motions from
    `ref` carry the joint. A segment given another bone's markers, or a joint far from where its segments
    turn, reads centimetres; NaN if no joint could be checked."""
    _, joints = world_transforms(t_root, R_parent_segment, joint_offsets_m)
    pick = np.linspace(0, len(history_m) - 1, min(n_frames, len(history_m))).astype(int)
    frames = history_m[pick]
    both = np.isfinite(frames[:, :, 0]) & np.isfinite(ref[:, 0])[None]  # (P, M)
    moved = np.zeros((len(pick), N_SEGMENTS), bool)
    at = np.zeros((len(pick), N_SEGMENTS, 3))  # where segment k's motion carries its own joint
    at_parent = np.zeros((len(pick), N_SEGMENTS, 3))  # ... and where its parent's carries it
    parents = np.asarray(PARENTS)
    for k in np.unique(marker_segment[marker_segment >= 0]):
        idx = np.flatnonzero(marker_segment == k)
        w = both[:, idx].astype(float)
        rows = np.flatnonzero(w.sum(1) >= 3)
        if not len(rows):
            continue
        w = w[rows]
        R, t = _rigid_motions(np.nan_to_num(ref[idx]), np.where(w[:, :, None] > 0, frames[rows][:, idx], 0.0), w)
        moved[rows, k] = True
        at[rows, k] = np.einsum("pxy,y->px", R, joints[k]) + t
        for child in np.flatnonzero(parents == k):  # the joints of k's children, by k's motion
            at_parent[rows, child] = np.einsum("pxy,y->px", R, joints[child]) + t
    both_moved = moved & np.where(parents >= 0, moved[:, np.maximum(parents, 0)], False)
    errors = np.linalg.norm(at - at_parent, axis=2)[both_moved]
    return float(np.median(errors)) if len(errors) else float("nan")


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


MIRROR_SEGMENT = np.array(MIRRORS)  # (each segment's mirror image, as an array to index with arrays)
_SIDE_PREFIXES = (("Left", "Right"), ("left", "right"))
_SIDE_SEPARATORS = "_.- "


def mirror_name(name: str) -> str | None:
    """The name of the marker on the other side by the usual conventions, or None if `name` names no side:
    LHEE / RHEE (Plug-in Gait, CMU), L_HEE, L.Heel, LeftAnkle / RightAnkle, HEE_L / HEE_R, heel.l."""
    for a, b in _SIDE_PREFIXES:
        for x, y in ((a, b), (b, a)):
            if name.startswith(x) and len(name) > len(x):
                return y + name[len(x):]
    if len(name) > 1 and name[0] in "LR" and (name[1].isupper() or name[1].isdigit() or name[1] in _SIDE_SEPARATORS):
        return {"L": "R", "R": "L"}[name[0]] + name[1:]
    if len(name) > 2 and name[-1] in "LRlr" and name[-2] in _SIDE_SEPARATORS:
        return name[:-1] + {"L": "R", "R": "L", "l": "r", "r": "l"}[name[-1]]
    return None


def mirror_names(markers) -> list[str | None]:
    """`mirror_name` of each of a marker set's names, read after the prefix all of them share: numediart's
    Qualisys set starts every name with L (LL_HLE / LR_HLE, LLAC / LRAC, LCLAV), and its L is no side."""
    markers = list(markers)
    # (every name keeps a rest past the prefix)
    prefix = os.path.commonprefix(markers)[: min(map(len, markers)) - 1] if len(markers) > 1 else ""
    return [None if (o := mirror_name(n[len(prefix):])) is None else prefix + o for n in markers]


def mirrored_markers(markers, marker_segment: np.ndarray, marker_offsets_m: np.ndarray, clear_m: float
                     ) -> list[tuple[str, int, np.ndarray]]:
    """The markers a subject's names imply but its model lacks (RBHD for a model with LBHD and no RBHD: a
    marker hidden through the whole seed), as (name, segment, offset): where the named marker's mirror image
    sits. The image is taken across the plane the subject's own pairs show: the named pairs between the
    marker's segment and its mirror segment (LFHD and RFHD for a head marker; the toes and heels for a foot)
    place the mirror segment, turned about the vertical (`_yaw_motion`; flipping y in the rest frames alone
    left RBHD 6 cm off on the tennis serve: a head turned in the seed turns its frame); with one pair or
    none, the flip alone. Left out: an image
    within `clear_m` of a marker the model has on that segment (a midline marker's image is itself,
    whatever its name), and names its markers imply twice."""
    have = {name: i for i, name in enumerate(markers)}
    flip = np.array([1.0, -1.0, 1.0])
    found: dict[str, tuple[str, int, np.ndarray] | None] = {}
    mirrors = mirror_names(markers)
    for name, other, k, off in zip(markers, mirrors, marker_segment, marker_offsets_m):
        if other is None or other in have or k < 0:
            continue
        seg = int(MIRROR_SEGMENT[k])
        src, dst = [], []
        for i, a in enumerate(mirrors):
            j = have.get(a or "")
            if j is not None and marker_segment[i] == k and marker_segment[j] == seg:
                src.append(marker_offsets_m[i] * flip)
                dst.append(marker_offsets_m[j])
        image = off * flip
        if len(src) >= 2:  # (the pairs alone: the calibration may place the two joints unlike)
            R, t = _yaw_motion(np.array(src), np.array(dst))
            image = R @ image + t
        mine = marker_offsets_m[marker_segment == seg]
        if len(mine) and np.min(np.linalg.norm(mine - image, axis=1)) < clear_m:
            continue
        found[other] = None if other in found else (other, seg, image)
    return [v for v in found.values() if v is not None]


def _yaw_motion(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation about z (3, 3) and translation (3,) that best take points a (N, 3) onto b (N, 3): a
    segment's frame and its mirror segment's, both upright in the calibration pose, differ by how the
    two limbs turn. (A free rotation, fitted to a foot's joint and two markers, points nearly in a line
    whose joints the calibration placed unlike on the two feet, turned a mirrored heel 14 cm upwards:
    tennis at L3, a left heel hidden through the seed never found.)"""
    ca, cb = a.mean(0), b.mean(0)
    p, q = a - ca, b - cb
    theta = np.arctan2(np.sum(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]), np.sum(p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1]))
    c, s_ = np.cos(theta), np.sin(theta)
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    return R, cb - R @ ca


def world_transforms(t_root: np.ndarray, R_parent_segment: np.ndarray, joint_offsets: np.ndarray):
    """World rotations (..., 14, 3, 3) and origins (..., 14, 3) of the segments, for one pose or a batch."""
    Rs = np.empty(R_parent_segment.shape)
    ps = np.empty(R_parent_segment.shape[:-1])
    for i, p in enumerate(PARENTS):
        if p < 0:
            Rs[..., i, :, :], ps[..., i, :] = R_parent_segment[..., i, :, :], t_root
        else:
            Rs[..., i, :, :] = Rs[..., p, :, :] @ R_parent_segment[..., i, :, :]
            ps[..., i, :] = ps[..., p, :] + np.einsum("...ij,j->...i", Rs[..., p, :, :], joint_offsets[i])
    return Rs, ps


# `reassign` moves a marker across a joint of its segment (to its parent or a child), or farther only out
# along the chain to a segment that carries it within REASSIGN_FAR_M (a hand calibrated onto the pelvis, the
# hands resting on the hips through the calibration), and only when it was seen in REASSIGN_MIN_SHARE of
# the frames: the solved poses follow the engine's own labels, and a marker mislabeled or hidden most of the
# window "stays most still" on some segment or other (a left heel whose labels wandered went to the right
# thigh). Never farther in toward the trunk: a hand held against the chest for the window is carried by the
# chest about as well as by its forearm, and moved there it broke the fit as soon as the hand moved away
# (CMU 135_02 at L3: two hand markers went to the trunk and the fit stayed 10-20 cm off for 2 s).
# And only across a joint that turned by REASSIGN_MIN_TURN_RAD (RMS over the window) or more: where the joint
# hardly moved, the segment on its other side carries the marker about as still, and a frame solved a little
# off (a thorax turned by shoulder markers riding the shoulder blades) makes it look stiller. Across a neck
# turned 6 degrees a clavicle, sternum and acromion went to the head, and across an ankle turned 4 degrees a
# fifth metatarsal to the shank, where the foot's heel and toe, alone, were then re-found swapped and kept
# so for 2000 frames (HDM05 at L3). (Dev suite, 18 realizations: L3 98.439 -> 98.495 %, that run 91.4 ->
# 96.0 %; L2 99.320 -> 99.315 %: in two runs of 135_02 the changed model led the fit another way, and a
# wrist pair swapped there.)
REASSIGN_MIN_SHARE = 0.5
REASSIGN_FAR_M = 0.01
REASSIGN_MIN_TURN_RAD = 0.14


def _ancestors(k: int) -> set[int]:
    up = set()
    while PARENTS[k] >= 0:
        k = PARENTS[k]
        up.add(k)
    return up


# DESCENDANT[a, b]: segment b lies below segment a in the chain (a is one of its ancestors)
DESCENDANT = np.array([[a in _ancestors(b) for b in range(len(PARENTS))] for a in range(len(PARENTS))])


def reassign(positions_m: np.ndarray, Rs_world: np.ndarray, ps_world: np.ndarray, marker_segment: np.ndarray) -> np.ndarray:
    """Move each marker to the segment that carries it best over F solved frames: the segment in whose frame
    the marker stays most still (RMS about its mean offset) among its own, those joined to it and those that
    carry it within REASSIGN_FAR_M, if that is under 70 % of its current segment's, the current one is off
    by more than 5 mm, and the two segments turned against each other by REASSIGN_MIN_TURN_RAD or more.
    Motion is what tells segments apart; in a still pose every choice fits, and none moves."""
    local = np.einsum("fsji,fmsj->fmsi", Rs_world, positions_m[:, :, None, :] - ps_world[:, None, :, :])  # (F, M, S, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # markers never seen in the window: all-NaN columns
        spread = np.sqrt(np.nanmean(np.sum((local - np.nanmean(local, axis=0)) ** 2, axis=3), axis=0))  # (M, S)
    out = marker_segment.copy()
    m = np.arange(len(out))
    parents = np.array(PARENTS)
    joined = (parents[None, :] == out[:, None]) | (parents[out][:, None] == np.arange(len(PARENTS))[None, :])
    far = DESCENDANT[out] & (spread < REASSIGN_FAR_M)
    spread = np.where(joined | (np.arange(len(PARENTS))[None, :] == out[:, None]) | far, spread, np.nan)
    best = np.nanargmin(np.where(np.isfinite(spread), spread, np.inf), axis=1)
    better = np.isfinite(spread[m, best]) & (spread[m, best] < 0.7 * spread[m, out]) & (spread[m, out] > 0.005)
    better &= np.isfinite(positions_m[..., 0]).sum(0) >= REASSIGN_MIN_SHARE * len(positions_m)
    for i in np.flatnonzero(better):
        better[i] = _turn_rms(Rs_world[:, out[i]], Rs_world[:, best[i]]) >= REASSIGN_MIN_TURN_RAD
    out[better] = best[better]
    return out


def _turn_rms(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """RMS angle [rad] by which segment b turned relative to segment a about their mean relative rotation,
    over F frames of world rotations Ra, Rb (F, 3, 3): how much their joint articulated."""
    rel = np.einsum("fji,fjk->fik", Ra, Rb)
    U, _, Vt = np.linalg.svd(rel.mean(0))
    mean = U @ Vt
    cos = (np.einsum("fij,ij->f", rel, mean) - 1.0) / 2.0
    return float(np.sqrt(np.mean(np.arccos(np.clip(cos, -1.0, 1.0)) ** 2)))


#: (`functional_joints`) a joint is measured when its two segments turned by at least this much [degrees]
#: about it over the history, and the centre found keeps them together within FUNCTIONAL_MAX_RMS_M RMS, under
#: FUNCTIONAL_GAIN of what the current joint does; FUNCTIONAL_PRIOR is the weight per frame that holds the
#: centre along what the motion does not reveal (a hinge's axis) at the current joint: a shift of 10 cm
#: costs what 1 cm of misfit on every frame does.
FUNCTIONAL_MIN_TURN_DEG = 30.0
FUNCTIONAL_MAX_RMS_M = 0.02
FUNCTIONAL_GAIN = 0.5
FUNCTIONAL_PRIOR = 0.1


def _segment_motions(positions_m: np.ndarray, marker_segment: np.ndarray, marker_offsets_m: np.ndarray):
    """{segment: (R (F, 3, 3), t (F, 3))}, each segment's rigid motion in every frame of labeled history
    (F, M, 3) from its own markers (Kabsch of their offsets onto them; NaN in frames showing fewer than 3),
    for the segments whose markers do not lie in a line."""
    F = len(positions_m)
    motions = {}
    for k in np.unique(marker_segment[marker_segment >= 0]):
        idx = np.flatnonzero(marker_segment == k)
        if len(idx) < 3 or np.linalg.svd(marker_offsets_m[idx] - marker_offsets_m[idx].mean(0), compute_uv=False)[1] < 0.01:
            continue
        w = np.isfinite(positions_m[:, idx, 0]).astype(float)
        rows = np.flatnonzero(w.sum(1) >= 3)
        R, t = np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan)
        if len(rows):
            R[rows], t[rows] = _rigid_motions(marker_offsets_m[idx], np.where(w[rows, :, None] > 0, positions_m[rows][:, idx], 0.0), w[rows])
        motions[int(k)] = (R, t)
    return motions


def functional_joints(positions_m: np.ndarray, marker_segment: np.ndarray, marker_offsets_m: np.ndarray,
                      joint_offsets_m: np.ndarray, rigid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The joints that labeled history (F, M, 3) shows, measured where they are: the point fixed in both
    segments' frames as they turn about it (the symmetrical centre of rotation estimation, SCoRE: Ehrig et
    al., J Biomech 2006), one linear least-squares problem per joint on the segments' own rigid motions, so
    no pose solve can mislead it. A template's joints are guesses where the calibration pose bent nothing
    (a seed kneeling still put the knees 10-20 cm off: the fit missed the markers by 10 cm once the subject
    lay down). Returns (marker_offsets_m, joint_offsets_m, measured (14,) bool): each measured joint's
    segment has its origin moved there (its markers' offsets and its children's joints follow). `rigid`
    (M,) bool: the markers whose segments' motions may be read from (those that kept their offsets in
    their segments: a T-pose's straight arm gave the upper arm the elbow's and a wrist's markers)."""
    motions = _segment_motions(positions_m, np.where(rigid, marker_segment, -1) if rigid is not None else marker_segment,
                               marker_offsets_m)
    in_parent = joint_offsets_m.copy()  # joint k in its parent's frame, about the parent's current origin
    in_own = np.zeros((N_SEGMENTS, 3))  # joint k in its own frame, about its current origin
    measured = np.zeros(N_SEGMENTS, bool)
    for k in range(1, N_SEGMENTS):
        p = PARENTS[k]
        if k not in motions or p not in motions or not SEGMENTS[k].startswith(("l_", "r_")):
            continue  # (the spine's joints join segments that bend within: a chest's C7 and T10 are no rigid body)
        (Rp, tp), (Rk, tk) = motions[p], motions[k]
        both = np.flatnonzero(np.isfinite(Rp[:, 0, 0]) & np.isfinite(Rk[:, 0, 0]))
        if len(both) < 10:
            continue
        rel = np.swapaxes(Rp[both], 1, 2) @ Rk[both]  # the joint's rotation in each frame
        turn = np.degrees(np.arccos(np.clip((np.trace(rel[0].T @ rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
        if turn.max() < FUNCTIONAL_MIN_TURN_DEG:
            continue
        A = np.concatenate([Rp[both], -Rk[both]], axis=2).reshape(-1, 6)
        b = (tk[both] - tp[both]).reshape(-1)
        c0 = np.concatenate([joint_offsets_m[k], np.zeros(3)])
        w = FUNCTIONAL_PRIOR * np.sqrt(len(both))
        c = np.linalg.solve(A.T @ A + w**2 * np.eye(6), A.T @ b + w**2 * c0)
        rms = np.sqrt(np.mean(np.sum((A @ c - b).reshape(-1, 3) ** 2, axis=1)))
        rms0 = np.sqrt(np.mean(np.sum((A @ c0 - b).reshape(-1, 3) ** 2, axis=1)))
        if rms < FUNCTIONAL_MAX_RMS_M and rms < FUNCTIONAL_GAIN * rms0:
            in_parent[k], in_own[k], measured[k] = c[:3], c[3:], True
    offsets = marker_offsets_m - in_own[np.maximum(marker_segment, 0)] * (marker_segment >= 0)[:, None]
    joints = np.zeros_like(joint_offsets_m)
    for k in range(1, N_SEGMENTS):
        joints[k] = in_parent[k] - in_own[PARENTS[k]]  # (the root's origin stays: in_own[0] is zero)
    return offsets, joints, measured


def refine(
    positions_m: np.ndarray,
    R_parent_segment: np.ndarray,
    marker_segment: np.ndarray,
    marker_offsets_m: np.ndarray,
    joint_offsets_m: np.ndarray,
    prior_weight: float = 0.3,
) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares alignment of the skeleton: with the segment rotations of F solved frames fixed,
    marker positions are linear in the marker offsets, the joint offsets and the root positions, so one
    linear least-squares problem gives the offsets that explain all F frames best. A weak prior keeps
    what the motion does not reveal (a joint that never bent) at its previous value.

    positions_m (F, M, 3) NaN = unseen; R_parent_segment (F, 14, 3, 3). Returns (marker_offsets_m,
    joint_offsets_m)."""
    F, M, _ = positions_m.shape
    n_j = len(PARENTS) - 1
    chain = []  # for every segment, the segments whose joint offsets place it
    for s in range(len(PARENTS)):
        c, k = [], s
        while PARENTS[k] >= 0:
            c.append(k)
            k = PARENTS[k]
        chain.append(c)
    Rs, _ = world_transforms(np.zeros((F, 3)), R_parent_segment, joint_offsets_m)
    n_unk = 3 * M + 3 * n_j + 3 * F
    # One 3-row block per observation, built with array indexing (no Python loop per observation: ~100x
    # faster; this runs in the engine's helper process while the frames wait for nothing but the CPU).
    # The system is sparse (a row touches its marker's offset, the joints above its segment and its frame's
    # root): it is assembled sparse and solved through its normal equations (n_unk ~ 300, Cholesky), ~1000x
    # cheaper than a dense SVD least squares of ~5000 x 300, which also let BLAS threads fight the frame loop.
    f_obs, i_obs = np.nonzero(np.isfinite(positions_m[..., 0]))
    n_obs = len(f_obs)
    seg = marker_segment[i_obs]
    r3 = 3 * np.arange(n_obs)[:, None] + np.arange(3)  # (N, 3) row indices of each block
    c3 = np.arange(3)
    rows, cols, vals = [], [], []

    def block(obs: np.ndarray, col0: np.ndarray, values: np.ndarray) -> None:
        """3x3 blocks: rows of observations `obs`, columns col0 + 0..2, entries values (len(obs), 3, 3)."""
        rows.append(np.broadcast_to(r3[obs][:, :, None], values.shape).ravel())
        cols.append(np.broadcast_to(col0[:, None, None] + c3[None, None, :], values.shape).ravel())
        vals.append(values.ravel())

    everyone = np.arange(n_obs)
    block(everyone, 3 * i_obs, Rs[f_obs, seg])
    anc = np.array([[k in chain[s_] for k in range(len(PARENTS))] for s_ in range(len(PARENTS))])
    for k in range(1, len(PARENTS)):
        obs = np.flatnonzero(anc[seg, k])
        if len(obs):
            block(obs, np.full(len(obs), 3 * M + 3 * (k - 1)), Rs[f_obs[obs], PARENTS[k]])
    block(everyone, 3 * M + 3 * n_j + 3 * f_obs, np.broadcast_to(np.eye(3), (n_obs, 3, 3)))
    A = scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n_obs, n_unk))
    b = positions_m[f_obs, i_obs].reshape(-1)
    # prior rows: offsets stay where they were unless the data say otherwise
    n_prior = 3 * M + 3 * n_j
    prior_rhs = prior_weight * np.concatenate([marker_offsets_m.reshape(-1), joint_offsets_m[1:].reshape(-1)])
    N = (A.T @ A).toarray()
    N[np.arange(n_prior), np.arange(n_prior)] += prior_weight**2
    rhs = A.T @ b
    rhs[:n_prior] += prior_weight * prior_rhs
    # the roots of frames with no observation are free: pin them (they touch nothing else)
    free = np.flatnonzero(np.diag(N) == 0)
    N[free, free] = 1.0
    x = scipy.linalg.solve(N, rhs, assume_a="pos")
    marker_offsets = x[: 3 * M].reshape(M, 3)
    joints = joint_offsets_m.copy()
    joints[1:] = x[3 * M : 3 * M + 3 * n_j].reshape(n_j, 3)
    return marker_offsets, joints
