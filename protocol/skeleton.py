"""The skeleton every tracked subject shares: 14 segments, 45 degrees of freedom.

The root (pelvis) has 6 DOF; each of the 13 other segments hangs from its parent by a 3-DOF ball joint
(6 + 13 * 3 = 45). Every segment frame is aligned with the subject's body frame in the rest (T-)pose:
x forward, y to the subject's left, z up. So in the rest pose every rotation is the identity and every
joint angle is zero.

Why these 14: the contract fixes 14 segments and 13 ball joints. The spine is split in two (abdomen,
torso) because floor work, squats and rolling bend it far more than a rigid trunk can follow, while the
hand rides on the forearm: common marker sets put one marker on the hand (FIN), which cannot fix a
3-DOF wrist anyway, so a separate hand segment would add three unobservable angles and no label.

This module is the static part of the wire contract (``segments`` and ``parents`` of the pose message);
it imports nothing but the standard library.
"""

SEGMENTS: tuple[str, ...] = (
    "pelvis",
    "abdomen",
    "torso",
    "head",
    "l_upperarm",
    "l_forearm",
    "r_upperarm",
    "r_forearm",
    "l_thigh",
    "l_shank",
    "l_foot",
    "r_thigh",
    "r_shank",
    "r_foot",
)

#: index of each segment's parent in SEGMENTS, -1 for the root. Parents always precede children.
PARENTS: tuple[int, ...] = (-1, 0, 1, 2, 2, 4, 2, 6, 0, 8, 9, 0, 11, 12)

#: index of each segment's mirror image across the body's sagittal plane (y = 0 in the rest frames): left
#: and right limbs swap, the trunk and head mirror onto themselves
MIRRORS: tuple[int, ...] = tuple(SEGMENTS.index({"l_": "r_", "r_": "l_"}.get(n[:2], n[:2]) + n[2:]) for n in SEGMENTS)

N_SEGMENTS = len(SEGMENTS)
N_JOINTS = N_SEGMENTS - 1  # ball joints: every segment but the root
N_DOF = 6 + 3 * N_JOINTS

assert N_SEGMENTS == 14 and N_DOF == 45
assert all(p < i for i, p in enumerate(PARENTS))

#: name of each ball joint, by the child segment it moves (SEGMENTS[1:]).
JOINTS: tuple[str, ...] = (
    "lumbar",
    "thoracic",
    "neck",
    "l_shoulder",
    "l_elbow",
    "r_shoulder",
    "r_elbow",
    "l_hip",
    "l_knee",
    "l_ankle",
    "r_hip",
    "r_knee",
    "r_ankle",
)

#: joint_angles convention: intrinsic y-x-z Cardan angles [rad] of the child's rotation relative to its
#: parent, both in their rest frames (x forward, y left, z up): angle 0 about y (flexion/extension, first so
#: that knees and hips bend past 90 degrees without a jump), then angle 1 about the new x (ab/adduction),
#: then angle 2 about the new z (axial rotation). The middle angle is limited to +-90 degrees.
JOINT_ANGLE_CONVENTION = "intrinsic YXZ (scipy 'YXZ'), radians, child relative to parent, rest pose = 0"
