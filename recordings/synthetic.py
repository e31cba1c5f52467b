"""A synthetic performer with exact ground truth, so the demo and the tests need no data files.

A seeded random body (height, limb lengths, marker placement) wears a marker set and runs a fixed motion
script: a 2 s T-pose, then walking, reaching, turning in place, a squat, walking back and a return to the
T-pose, repeated if the duration is longer. Joint angles come from smooth time windows, so the motion is
continuous; the root is then placed so the lowest foot contact touches the floor (z = 0) and the support
foot does not slide, which makes travel and turning emerge from the legs instead of being scripted.

Frames follow ``protocol.skeleton``: 14 segments, every segment frame aligned with the body in the rest
T-pose (x forward, y left, z up), rotations as quaternions x, y, z, w (root in world, others relative to
parent). Everything here is numpy and scipy only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from protocol.skeleton import N_SEGMENTS, PARENTS, SEGMENTS
from recordings.recording import Recording

_S = {name: i for i, name in enumerate(SEGMENTS)}
_REFERENCE_HEIGHT_M = 1.75  # marker surface offsets below are written for a body of this height
TPOSE_S = 2.0  # the script stands still in a T-pose for this long at the start of every cycle

# Rest-pose joint positions as fractions of body height (x forward, y left, z up): each segment's origin
# in its parent's frame. Proportions after Winter, "Biomechanics and Motor Control of Human Movement".
_JOINT_OFFSETS_H = {
    "abdomen": (-0.01, 0.0, 0.06),  # lumbar joint, hip centres at 0.52 H
    "torso": (0.0, 0.0, 0.12),  # thoracic joint
    "head": (0.005, 0.0, 0.145),  # neck (C7/T1)
    "l_upperarm": (-0.005, 0.10, 0.115),  # glenohumeral joint at 0.815 H
    "l_forearm": (0.0, 0.186, 0.0),  # elbow
    "l_thigh": (0.0, 0.05, 0.0),  # hip joint
    "l_shank": (0.0, 0.0, -0.245),  # knee
    "l_foot": (0.0, 0.0, -0.235),  # ankle, 0.04 H above the floor
}
# Segment "tips" for the leaf segments, fraction of height: head top, wrist, ball of the toes.
_TIPS_H = {"head": (0.0, 0.0, 0.155), "l_forearm": (0.0, 0.146, 0.0), "l_foot": (0.115, 0.0, 0.0)}
_ANKLE_H, _HEEL_H = 0.04, 0.035  # ankle height above the sole, heel behind the ankle [fraction of height]


@dataclasses.dataclass(frozen=True)
class MarkerSpec:
    """Where one marker sits: on `segment`, at fraction `t` along the segment (origin to tip or to its
    first child's joint) plus `surface_m`, the offset to the skin for a 1.75 m body, segment frame."""

    name: str
    segment: str
    t: float
    surface_m: tuple[float, float, float]


def _pair(stem: str, segment: str, t: float, surface_m, t_right: float | None = None) -> list[MarkerSpec]:
    """A left marker and its mirror image; `t_right` places the right one elsewhere (real sets do, so
    that left and right can be told apart)."""
    x, y, z = surface_m
    left, right = ("l_" + segment, "r_" + segment) if "l_" + segment in _S else (segment, segment)
    return [
        MarkerSpec("L" + stem, left, t, (x, y, z)),
        MarkerSpec("R" + stem, right, t if t_right is None else t_right, (x, -y, z)),
    ]


def _limbs(*entries) -> list[MarkerSpec]:
    """`_pair` for each entry, all left markers first, then all right ones (the usual file order)."""
    pairs = [_pair(*entry) for entry in entries]
    return [pair[0] for pair in pairs] + [pair[1] for pair in pairs]


# Surface offsets are in the segment frame of the rest T-pose (arms out, palms down): on the arm the bone
# runs along y, so "lateral" is up (+z); on the leg it runs along -z, so lateral is +y for the left leg.
_FHD, _BHD = ("FHD", "head", 0.70, (0.09, 0.055, 0.0)), ("BHD", "head", 0.45, (-0.075, 0.055, 0.0))
_TRUNK = [
    MarkerSpec("C7", "torso", 1.0, (-0.07, 0.0, 0.0)),
    MarkerSpec("T10", "torso", 0.25, (-0.11, 0.0, 0.0)),
    MarkerSpec("CLAV", "torso", 0.83, (0.08, 0.0, 0.0)),
    MarkerSpec("STRN", "torso", 0.35, (0.11, 0.0, 0.0)),
]
_FWT, _BWT = ("FWT", "pelvis", 0.0, (0.075, 0.125, 0.08)), ("BWT", "pelvis", 0.0, (-0.11, 0.07, 0.07))

#: marker sets by name. Order is the order of points in the recording.
MARKER_SETS: dict[str, tuple[MarkerSpec, ...]] = {
    # The CMU / HDM05 41-marker set; the hand markers (WRA, WRB, FIN) ride on the forearm.
    "cmu41": tuple(
        _pair(*_FHD) + _pair(*_BHD)
        + _TRUNK
        + [MarkerSpec("RBAC", "torso", 0.55, (-0.10, -0.09, 0.0))]  # right scapula only: breaks the symmetry
        + _limbs(
            ("SHO", "upperarm", 0.05, (-0.01, 0.0, 0.05)),
            ("UPA", "upperarm", 0.5, (-0.01, 0.0, 0.045), 0.62),
            ("ELB", "upperarm", 1.0, (-0.035, 0.0, 0.02)),
            ("FRM", "forearm", 0.45, (-0.03, 0.0, 0.03)),
            ("WRA", "forearm", 1.0, (0.035, 0.0, 0.0)),  # thumb side
            ("WRB", "forearm", 1.0, (-0.035, 0.0, 0.0)),  # little-finger side
            ("FIN", "forearm", 1.41, (0.0, 0.0, 0.02)),  # knuckles
        )
        + _pair(*_FWT) + _pair(*_BWT)
        + _limbs(
            ("THI", "thigh", 0.45, (0.02, 0.075, 0.0), 0.62),
            ("KNE", "thigh", 1.0, (0.0, 0.055, 0.0)),
            ("SHN", "shank", 0.5, (0.05, 0.01, 0.0), 0.65),
            ("ANK", "shank", 1.0, (0.0, 0.045, 0.0)),
            ("HEE", "foot", -0.3, (-0.02, 0.0, -0.035)),
            ("TOE", "foot", 0.75, (0.0, 0.0, -0.04)),
            ("MT5", "foot", 0.6, (0.0, 0.045, -0.045)),
        )
    ),
    # A 53-marker Vicon set like the Georgia Tech recordings: head-top marker, two shoulder markers on the
    # upper arm, medial and lateral elbow/wrist/hand/knee markers, mid-waist and hip markers.
    "gt53": tuple(
        [MarkerSpec("ARIEL", "head", 1.0, (0.0, 0.0, 0.01))]
        + _limbs(_FHD, _BHD)
        + _TRUNK
        + _limbs(
            ("FSH", "upperarm", 0.1, (0.05, 0.0, 0.03)),
            ("BSH", "upperarm", 0.1, (-0.05, 0.0, 0.03), 0.16),
            ("UPA", "upperarm", 0.6, (0.0, 0.0, 0.045), 0.4),
            ("ELB", "upperarm", 1.0, (-0.035, 0.0, 0.02)),
            ("IEL", "upperarm", 1.0, (0.0, 0.0, -0.035)),
            ("OWR", "forearm", 1.0, (0.035, 0.0, 0.0)),
            ("IWR", "forearm", 1.0, (-0.035, 0.0, 0.0)),
            ("WRE", "forearm", 0.6, (0.0, 0.0, 0.035)),
            ("IHAND", "forearm", 1.35, (-0.03, 0.0, 0.02)),
            ("OHAND", "forearm", 1.35, (0.035, 0.0, 0.02)),
        )
        + _limbs(_FWT, ("MWT", "pelvis", 0.0, (-0.02, 0.15, 0.09)), _BWT)
        + _limbs(
            ("HIP", "thigh", 0.1, (0.0, 0.09, 0.0), 0.14),
            ("KNE", "thigh", 1.0, (0.0, 0.055, 0.0)),
            ("KNI", "thigh", 1.0, (0.0, -0.055, 0.0)),
            ("SHN", "shank", 0.45, (0.05, 0.01, 0.0), 0.62),
            ("ANK", "shank", 1.0, (0.0, 0.045, 0.0)),
            ("HEL", "foot", -0.3, (-0.02, 0.0, -0.035)),
            ("MT5", "foot", 0.6, (0.0, 0.045, -0.045)),
            ("MT1", "foot", 0.6, (0.0, -0.035, -0.045)),
            ("TOE", "foot", 0.8, (0.0, 0.0, -0.04)),
        )
    ),
}


@dataclasses.dataclass(frozen=True)
class Performance:
    """One synthetic performer: its marker trajectories and the pose and body that produced them."""

    recording: Recording  # labels "Subject:MARKER", points_m (F, M, 3), no NaN
    subject: str
    height_m: float
    root_position_m: np.ndarray  # (F, 3) pelvis origin in world
    rotations_xyzw: np.ndarray  # (F, 14, 4) root in world, others relative to parent
    marker_names: tuple[str, ...]  # (M,)
    marker_segment: np.ndarray  # (M,) int index into SEGMENTS
    marker_offsets_m: np.ndarray  # (M, 3) in the segment frame
    joint_offsets_m: np.ndarray  # (14, 3) segment origin in parent frame; root: zeros
    tpose_frames: int  # frames at the start that are a still T-pose

    def describe(self, stream: str = "default") -> dict:
        """The static skeleton description in the shape of `Engine.describe`, for comparing calibrations."""
        return {"subject": self.subject, "stream": stream, "segments": list(SEGMENTS), "parents": list(PARENTS),
                "markers": list(self.marker_names), "marker_segment": self.marker_segment.tolist(),
                "marker_offsets_m": self.marker_offsets_m.tolist(), "joint_offsets_m": self.joint_offsets_m.tolist()}

    def joint_angles_rad(self) -> np.ndarray:
        """(F, 13, 3) joint angles in the wire convention (protocol.skeleton.JOINT_ANGLE_CONVENTION)."""
        flat = self.rotations_xyzw[:, 1:].reshape(-1, 4)
        return Rotation.from_quat(flat).as_euler("YXZ").reshape(-1, N_SEGMENTS - 1, 3)


def forward_kinematics(root_position_m: np.ndarray, rotations_xyzw: np.ndarray, joint_offsets_m: np.ndarray):
    """World frames of every segment: (R_world_segment (F, 14, 3, 3), p_world_segment (F, 14, 3)).

    Parents precede children, so one pass down the tree suffices.
    """
    n = rotations_xyzw.shape[0]
    R_parent_segment = Rotation.from_quat(rotations_xyzw.reshape(-1, 4)).as_matrix().reshape(n, N_SEGMENTS, 3, 3)
    R_world = np.empty_like(R_parent_segment)
    p_world = np.empty((n, N_SEGMENTS, 3))
    R_world[:, 0], p_world[:, 0] = R_parent_segment[:, 0], root_position_m
    for s in range(1, N_SEGMENTS):
        parent = PARENTS[s]
        R_world[:, s] = R_world[:, parent] @ R_parent_segment[:, s]
        p_world[:, s] = p_world[:, parent] + R_world[:, parent] @ joint_offsets_m[s]
    return R_world, p_world


def marker_positions(R_world_segment, p_world_segment, marker_segment, marker_offsets_m) -> np.ndarray:
    """(F, M, 3) world marker positions: R_world_seg @ offset + p_world_seg."""
    R = R_world_segment[:, marker_segment]
    return np.einsum("fmij,mj->fmi", R, marker_offsets_m) + p_world_segment[:, marker_segment]


def _mirror(v) -> np.ndarray:
    return np.asarray(v, float) * (1.0, -1.0, 1.0)


def _body(height_m: float, marker_set: Sequence[MarkerSpec], rng: np.random.Generator):
    """Joint offsets, marker segments/offsets and foot sole points for one randomised body."""
    joints = np.zeros((N_SEGMENTS, 3))
    tips = np.zeros((N_SEGMENTS, 3))
    for name, offset in _JOINT_OFFSETS_H.items():
        joints[_S[name]] = offset
        if name.startswith("l_"):
            joints[_S["r" + name[1:]]] = _mirror(offset)
    for name, tip in _TIPS_H.items():
        tips[_S[name]] = tip
        if name.startswith("l_"):
            tips[_S["r" + name[1:]]] = _mirror(tip)
    # Each bone a few percent longer or shorter, left and right independently (people are not symmetric).
    scale = height_m * np.clip(1.0 + 0.025 * rng.standard_normal(N_SEGMENTS), 0.93, 1.07)
    joints *= scale[np.asarray(PARENTS).clip(0)][:, None]
    joints[0] = 0.0
    tips *= scale[:, None]
    for s in range(N_SEGMENTS):  # non-leaf segments: the tip is the first child's joint
        if not tips[s].any():
            tips[s] = joints[PARENTS.index(s)]
    girth = height_m / _REFERENCE_HEIGHT_M * rng.uniform(0.92, 1.12)
    segments, offsets = [], []
    for spec in marker_set:
        s = _S[spec.segment]
        surface = np.array(spec.surface_m)
        jitter = np.clip(0.004 * rng.standard_normal(3), -0.01, 0.01)  # real placement is never exact
        segments.append(s)
        offsets.append(spec.t * tips[s] + surface * girth + jitter)
    ankle_m, heel_m = _ANKLE_H * height_m, _HEEL_H * height_m
    soles = {side: np.array([[-heel_m, 0.0, -ankle_m], [tips[_S[side + "_foot"]][0], 0.0, -ankle_m]])
             for side in "lr"}
    return joints, np.array(segments), np.array(offsets), soles


def _smooth(u):
    """Quintic smoothstep 0 -> 1 on [0, 1], zero first and second derivative at both ends (no jerk)."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (u * (6.0 * u - 15.0) + 10.0)


def _window(t, on_s, off_s, ramp_s):
    """1 between on_s + ramp_s and off_s, fading smoothly to 0 over ramp_s on either side."""
    return _smooth((t - on_s) / ramp_s) * (1.0 - _smooth((t - off_s) / ramp_s))


def _script(t_s: np.ndarray, rng: np.random.Generator):
    """Per-frame Euler angles (F, 14, 3) [rad], applied as R_z(a2) R_y(a1) R_x(a0); limbs in left-side
    terms (mirrored for the right at the end), the root's yaw being the accumulated turning."""
    tempo = rng.uniform(0.9, 1.1)
    cadence_hz, stride_rad, depth = rng.uniform(0.85, 1.0), rng.uniform(0.3, 0.4), rng.uniform(0.8, 1.0)
    look_hz, reach = rng.uniform(0.1, 0.2), rng.uniform(0.85, 1.1)
    period_s = TPOSE_S + 18.0 * tempo
    cycle, t = np.divmod(t_s, period_s)

    def win(on, off, ramp):  # script times are written for tempo 1 and stretched after the T-pose
        return _window(t, TPOSE_S + tempo * (on - TPOSE_S), TPOSE_S + tempo * (off - TPOSE_S), tempo * ramp)

    arms = win(2.0, 19.0, 1.0)  # arms down from the T-pose, and back up at the end
    gait = stride_rad * (win(3.0, 5.8, 0.6) + 0.45 * win(10.2, 12.0, 0.5) + win(15.3, 18.4, 0.6))
    g = gait / stride_rad  # 0..1 how much walking is going on
    reach_r, reach_l = reach * win(7.6, 8.4, 0.7), reach * win(8.9, 9.4, 0.7)
    squat = depth * win(12.8, 14.2, 1.0)
    turn = np.pi * (cycle + _smooth((t - TPOSE_S - tempo * 8.3) / (2.0 * tempo)))
    phi = 2.0 * np.pi * cadence_hz * t_s

    a = np.zeros((t_s.size, N_SEGMENTS, 3))
    x, y, z = 0, 1, 2
    a[:, _S["pelvis"], x] = 0.04 * g * np.sin(phi)
    a[:, _S["pelvis"], y] = 0.04 * g + 0.3 * squat + 0.1 * reach_l
    a[:, _S["pelvis"], z] = turn + 0.12 * gait * np.cos(phi)
    a[:, _S["abdomen"], x] = -0.3 * reach_l
    a[:, _S["abdomen"], y] = 0.1 * (reach_r + squat)
    a[:, _S["torso"], x] = -0.15 * reach_l
    a[:, _S["torso"], y] = 0.1 * (reach_r + squat)
    a[:, _S["torso"], z] = -0.25 * gait * np.cos(phi) + 0.25 * reach_r
    a[:, _S["head"], y] = 0.1 * np.sin(2.0 * np.pi * look_hz * 1.7 * t_s) * arms - 0.15 * reach_r - 0.4 * squat
    a[:, _S["head"], z] = 0.4 * np.sin(2.0 * np.pi * look_hz * t_s) * arms
    # side, gait phase, this arm's reach, this arm's forward-up reach (only the right arm reaches forward)
    for side, psi, own_reach, reach_up in (("l", phi, reach_l, 0.0), ("r", phi + np.pi, reach_r, reach_r)):
        swing = np.maximum(0.0, -np.sin(psi)) ** 2  # 1 at mid-swing, 0 through stance
        push = np.maximum(0.0, -np.cos(psi)) * np.maximum(0.0, np.sin(psi))  # late stance
        shoulder, elbow = _S[side + "_upperarm"], _S[side + "_forearm"]
        hip, knee, ankle = _S[side + "_thigh"], _S[side + "_shank"], _S[side + "_foot"]
        a[:, shoulder, x] = -1.35 * arms + 0.3 * own_reach
        a[:, shoulder, y] = 0.6 * gait * np.cos(psi) - 1.3 * squat - 1.9 * reach_up
        a[:, elbow, z] = -(0.25 * arms + 0.15 * g * (1 - np.cos(psi)) / 2 - 0.2 * own_reach - 0.2 * squat)
        a[:, hip, y] = -gait * np.cos(psi) - 0.05 * g - 1.8 * squat - 0.3 * reach_l
        a[:, knee, y] = g * (0.08 + 1.0 * swing) + 2.0 * squat + 0.6 * reach_l
        a[:, ankle, y] = g * (0.15 * push - 0.15 * swing) - 0.5 * squat - 0.3 * reach_l
    right = [i for i, name in enumerate(SEGMENTS) if name.startswith("r_")]
    a[:, right, x] *= -1.0
    a[:, right, z] *= -1.0
    return a


def perform(seed: int = 0, *, marker_set: str = "cmu41", duration_s: float = 20.0, rate_hz: float = 120.0,
            height_m: float | None = None, start: tuple[float, float] = (0.0, 0.0), heading_rad: float = 0.0,
            subject: str = "Performer") -> Performance:
    """Generate one performer from `seed` (same seed, same body and motion).

    marker_set: a key of MARKER_SETS. duration_s [s] and rate_hz [Hz] set the frame count; the script
    repeats after ~20 s. height_m [m]: None draws 1.60-1.90 m. start: (x, y) [m] of the pelvis at frame 0.
    heading_rad [rad]: initial facing direction about z (0 = facing +x). subject: the label prefix.
    """
    if marker_set not in MARKER_SETS:
        raise ValueError(f"unknown marker set {marker_set!r}; choose one of {', '.join(MARKER_SETS)}")
    if not (duration_s > 0 and rate_hz > 0):
        raise ValueError(f"duration_s and rate_hz must be > 0, got {duration_s} and {rate_hz}")
    rng = np.random.default_rng(seed)
    height_m = float(rng.uniform(1.6, 1.9) if height_m is None else height_m)
    specs = MARKER_SETS[marker_set]
    joints, segment, offsets, soles = _body(height_m, specs, rng)
    t_s = np.arange(max(1, round(duration_s * rate_hz))) / rate_hz
    angles = _script(t_s, rng)
    angles[:, 0, 2] += heading_rad
    quats = Rotation.from_euler("ZYX", angles[..., ::-1].reshape(-1, 3)).as_quat().reshape(-1, N_SEGMENTS, 4)

    # Place the root: first the body hanging from a root at the origin, then lift it so the lowest sole
    # point is on the floor, and move it horizontally so the support foot (softly, the lowest sole points)
    # does not slide over the floor.
    R_world, p_world = forward_kinematics(np.zeros((t_s.size, 3)), quats, joints)
    contact = np.concatenate([marker_positions(R_world, p_world, [_S[s + "_foot"]] * 2, soles[s]) for s in "lr"], 1)
    height = contact[..., 2]
    weight = np.exp(-(height - height.min(1, keepdims=True)) / 0.01)
    weight /= weight.sum(1, keepdims=True)
    slide = np.einsum("fc,fcj->fj", weight[1:], np.diff(contact[..., :2], axis=0))
    root = np.zeros((t_s.size, 3))
    root[:, :2] = np.asarray(start, float) - np.concatenate([np.zeros((1, 2)), np.cumsum(slide, 0)])
    root[:, 2] = -height.min(1)
    points = marker_positions(R_world, p_world + root[:, None], segment, offsets)

    names = tuple(spec.name for spec in specs)
    recording = Recording(points, tuple(f"{subject}:{n}" for n in names), float(rate_hz), f"synthetic:{seed}")
    return Performance(recording, subject, height_m, root, quats, names, segment, offsets, joints,
                       int(np.sum(t_s < TPOSE_S)))


def multi_perform(seeds: Sequence[int], *, spacing_m: float = 2.5, start: tuple[float, float] = (0.0, 0.0),
                  heading_rad: float = 0.0, **kwargs) -> tuple[Recording, tuple[Performance, ...]]:
    """Several performers side by side (`spacing_m` apart, to the left of the heading) in one cloud,
    subjects "Performer1", "Performer2", ...; the recording concatenates their points in that order."""
    left = np.array([-np.sin(heading_rad), np.cos(heading_rad)])
    performances = tuple(
        perform(seed, start=tuple(np.asarray(start) + i * spacing_m * left), heading_rad=heading_rad,
                subject=f"Performer{i + 1}", **kwargs)
        for i, seed in enumerate(seeds))
    points = np.concatenate([p.recording.points_m for p in performances], axis=1)
    labels = tuple(label for p in performances for label in p.recording.labels)
    rate = performances[0].recording.rate_hz
    return Recording(points, labels, rate, "synthetic:" + ",".join(map(str, seeds))), performances
