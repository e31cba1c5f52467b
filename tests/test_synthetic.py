"""recordings.synthetic: the generated performer is a plausible human with exact, self-consistent ground truth."""

import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol.skeleton import PARENTS, SEGMENTS
from recordings.synthetic import MARKER_SETS, forward_kinematics, multi_perform, perform

SETS = ("cmu41", "gt53")


@functools.cache
def _perf(seed=0, marker_set="cmu41", duration_s=24.0, heading_rad=0.0):
    """Cached: a performance is immutable, and several tests look at the same one."""
    return perform(seed, marker_set=marker_set, duration_s=duration_s, heading_rad=heading_rad)


def _points(perf, name):
    return perf.recording.points_m[:, perf.marker_names.index(name)]


@pytest.mark.parametrize("marker_set, n_markers", [("cmu41", 41), ("gt53", 53)])
def test_labels_and_shapes(marker_set, n_markers):
    perf = _perf(marker_set=marker_set)
    rec = perf.recording
    n_frames = 24 * 120
    assert rec.points_m.shape == (n_frames, n_markers, 3) and rec.rate_hz == 120.0
    assert not np.isnan(rec.points_m).any()
    assert len(set(perf.marker_names)) == n_markers
    assert rec.labels == tuple(f"Performer:{name}" for name in perf.marker_names)
    assert perf.root_position_m.shape == (n_frames, 3)
    assert perf.rotations_xyzw.shape == (n_frames, 14, 4)
    assert perf.marker_segment.shape == (n_markers,) and perf.marker_offsets_m.shape == (n_markers, 3)
    assert perf.joint_offsets_m.shape == (14, 3) and not perf.joint_offsets_m[0].any()
    assert perf.tpose_frames == 240
    description = perf.describe()
    assert description["segments"] == list(SEGMENTS) and description["parents"] == list(PARENTS)
    assert description["markers"] == list(perf.marker_names)
    # every segment carries at least one marker in both sets, except the abdomen (no set marks it)
    carried = set(perf.marker_segment.tolist())
    assert carried == set(range(14)) - {SEGMENTS.index("abdomen")}


def test_cmu41_names_are_the_cmu_set():
    expected = "LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAC".split() + [
        s + m for s in "LR" for m in "SHO UPA ELB FRM WRA WRB FIN".split()
    ] + "LFWT RFWT LBWT RBWT".split() + [s + m for s in "LR" for m in "THI KNE SHN ANK HEE TOE MT5".split()]
    assert [m.name for m in MARKER_SETS["cmu41"]] == expected
    hands = {m.segment for m in MARKER_SETS["cmu41"] if m.name[1:] in ("WRA", "WRB", "FIN")}
    assert hands == {"l_forearm", "r_forearm"}


def test_unknown_marker_set_lists_the_valid_ones():
    with pytest.raises(ValueError, match="cmu41, gt53"):
        perform(0, marker_set="nope")


@pytest.mark.parametrize("marker_set", SETS)
def test_tpose_at_the_start(marker_set):
    perf = _perf(marker_set=marker_set)
    first = perf.recording.points_m[: perf.tpose_frames]
    assert np.ptp(first, axis=0).max() < 1e-12  # standing still
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (perf.tpose_frames, 14, 1))
    assert np.abs(np.abs(perf.rotations_xyzw[: perf.tpose_frames]) - identity).max() < 1e-12
    frame = first[0]
    height = perf.height_m
    wrist = "WRA" if marker_set == "cmu41" else "OWR"
    shoulder = "SHO" if marker_set == "cmu41" else "FSH"
    for side in "LR":  # arms horizontal: wrist at shoulder height
        z_wrist = frame[perf.marker_names.index(side + wrist), 2]
        assert abs(z_wrist - frame[perf.marker_names.index(side + shoulder), 2]) < 0.06
    hand = "FIN" if marker_set == "cmu41" else "OHAND"
    span = np.linalg.norm(frame[perf.marker_names.index("L" + hand)] - frame[perf.marker_names.index("R" + hand)])
    assert 0.9 * height < span < 1.1 * height
    # facing +x (heading 0): the left hand is at +y
    assert frame[perf.marker_names.index("L" + hand), 1] > 0.7 > frame[perf.marker_names.index("R" + hand), 1] + 1.4
    assert 0.85 * height < frame[:, 2].max() < 1.01 * height  # head markers top the body
    if marker_set == "gt53":
        assert frame[:, 2].argmax() == perf.marker_names.index("ARIEL")


@pytest.mark.parametrize("marker_set", SETS)
def test_feet_on_the_floor_throughout(marker_set):
    lowest = _perf(marker_set=marker_set).recording.points_m[..., 2].min(axis=1)
    assert lowest.min() > 0.0 and lowest.max() < 0.07


def test_support_foot_does_not_slide():
    perf = _perf()
    heels = np.stack([_points(perf, "LHEE"), _points(perf, "RHEE")], axis=1)  # (F, 2, 3)
    speed = np.linalg.norm(np.diff(heels[..., :2], axis=0), axis=-1) * perf.recording.rate_hz
    flat = np.abs(heels[1:, :, 2] - heels[0, :, 2]) < 0.003  # heel as low as when standing
    flat[: perf.tpose_frames] = False  # standing still proves nothing
    assert flat.sum() > 1000
    assert np.median(speed[flat]) < 0.05 and np.percentile(speed[flat], 90) < 0.3


@pytest.mark.parametrize("marker_set", SETS)
def test_segments_are_rigid(marker_set):
    perf = _perf(marker_set=marker_set)
    points = perf.recording.points_m
    for segment in range(14):
        on = np.flatnonzero(perf.marker_segment == segment)
        for i, j in zip(on[:-1], on[1:]):
            distance = np.linalg.norm(points[:, i] - points[:, j], axis=-1)
            assert np.ptp(distance) < 1e-9, (SEGMENTS[segment], perf.marker_names[i], perf.marker_names[j])


def test_deterministic_per_seed_and_different_across_seeds():
    a, b, c = perform(3, duration_s=5.0), perform(3, duration_s=5.0), perform(4, duration_s=5.0)
    np.testing.assert_array_equal(a.recording.points_m, b.recording.points_m)
    np.testing.assert_array_equal(a.rotations_xyzw, b.rotations_xyzw)
    assert a.height_m != c.height_m
    assert np.abs(a.recording.points_m - c.recording.points_m).max() > 0.05
    assert not np.allclose(a.marker_offsets_m, c.marker_offsets_m)


def test_height_is_respected_and_scales_the_body():
    short, tall = perform(1, height_m=1.5, duration_s=1.0), perform(1, height_m=2.0, duration_s=1.0)
    assert short.height_m == 1.5 and tall.height_m == 2.0
    ratio = np.linalg.norm(tall.joint_offsets_m, axis=1)[1:] / np.linalg.norm(short.joint_offsets_m, axis=1)[1:]
    np.testing.assert_allclose(ratio, 2.0 / 1.5, rtol=1e-12)  # same seed: same proportions
    assert np.ptp(tall.recording.points_m[0, :, 2]) > np.ptp(short.recording.points_m[0, :, 2]) + 0.4


@pytest.mark.parametrize("marker_set", SETS)
def test_not_mirror_symmetric(marker_set):
    """Left and right must be distinguishable from the marker layout alone (as in real sets)."""
    perf = _perf(marker_set=marker_set)
    names = perf.marker_names
    frame = perf.recording.points_m[0] - perf.root_position_m[0]
    pairs = [(names.index(n), names.index("R" + n[1:])) for n in names if n[0] == "L" and "R" + n[1:] in names]
    assert len(pairs) >= 15
    mismatch = [np.linalg.norm(frame[i] * (1, -1, 1) - frame[j]) for i, j in pairs]
    assert max(mismatch) > 0.05  # designed asymmetry (e.g. thigh/shank markers at different heights)


@pytest.mark.parametrize("marker_set", SETS)
def test_marker_speeds_are_human(marker_set):
    perf = _perf(marker_set=marker_set)
    speed = np.linalg.norm(np.diff(perf.recording.points_m, axis=0), axis=-1) * perf.recording.rate_hz
    assert 1.5 < speed.max() < 12.0
    acceleration = np.linalg.norm(np.diff(perf.recording.points_m, 2, axis=0), axis=-1) * perf.recording.rate_hz**2
    assert acceleration.max() < 200.0  # smooth: no jumps anywhere


def test_quaternions_are_unit_and_joints_within_limits():
    perf = _perf(duration_s=45.0)  # more than two cycles of the script
    assert np.abs(np.linalg.norm(perf.rotations_xyzw, axis=-1) - 1.0).max() < 1e-12
    rotvec = Rotation.from_quat(perf.rotations_xyzw.reshape(-1, 4)).as_rotvec().reshape(-1, 14, 3)
    angle = np.linalg.norm(rotvec, axis=-1)
    assert angle[:, 1:].max() < 2.5  # no joint turns further than ~145 degrees from the rest pose
    for knee in ("l_shank", "r_shank"):  # a hinge that bends one way only
        k = rotvec[:, SEGMENTS.index(knee)]
        assert np.abs(k[:, [0, 2]]).max() < 1e-12
        assert k[:, 1].min() >= 0.0 and 1.5 < k[:, 1].max() < 2.3  # the squat bends the knee past 90 degrees
    spine = [SEGMENTS.index(s) for s in ("abdomen", "torso")]
    assert angle[:, spine].max() < 0.6


@pytest.mark.parametrize("marker_set", SETS)
def test_stored_pose_reproduces_markers(marker_set):
    """A naive per-frame FK with 4x4 transforms, independent of the module's vectorised one."""
    perf = _perf(marker_set=marker_set)
    for f in (0, 500, 1111, 1700, 2400):
        T_world = []
        for s in range(14):
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(perf.rotations_xyzw[f, s]).as_matrix()
            T[:3, 3] = perf.root_position_m[f] if s == 0 else perf.joint_offsets_m[s]
            T_world.append(T if s == 0 else T_world[PARENTS[s]] @ T)
        for m, (s, offset) in enumerate(zip(perf.marker_segment, perf.marker_offsets_m)):
            expected = (T_world[s] @ np.append(offset, 1.0))[:3]
            np.testing.assert_allclose(perf.recording.points_m[f, m], expected, atol=1e-9)
    R, p = forward_kinematics(perf.root_position_m, perf.rotations_xyzw, perf.joint_offsets_m)
    assert R.shape == (perf.recording.n_frames, 14, 3, 3) and p.shape == (perf.recording.n_frames, 14, 3)


def test_walks_forward_along_heading_then_turns_and_comes_back():
    heading = np.pi / 2  # facing +y
    perf = _perf(seed=2, heading_rad=heading)
    root = perf.root_position_m
    rate = int(perf.recording.rate_hz)
    out = root[: 8 * rate, 1].argmax()
    assert root[out, 1] > 2.0 and abs(root[out, 0]) < 0.3  # walked ~3 m forward along +y
    assert root[-1, 1] < root[out, 1] - 1.5  # and back after the turn
    yaw = Rotation.from_quat(perf.rotations_xyzw[:, 0]).as_euler("ZYX")[:, 0]
    assert yaw[0] == pytest.approx(heading)
    assert abs(np.angle(np.exp(1j * (yaw[-1] - heading - np.pi)))) < 0.2  # turned round


def test_crouches():
    perf = _perf()
    pelvis_z = perf.root_position_m[:, 2]
    assert pelvis_z.min() < 0.7 * pelvis_z[0]


def test_multi_perform_places_performers_apart():
    recording, perfs = multi_perform([0, 1, 2], duration_s=20.0, marker_set="gt53")
    assert [p.subject for p in perfs] == ["Performer1", "Performer2", "Performer3"]
    assert recording.points_m.shape == (2400, 3 * 53, 3)
    assert recording.labels[0] == "Performer1:ARIEL" and recording.labels[53] == "Performer2:ARIEL"
    np.testing.assert_array_equal(recording.points_m[:, 53:106], perfs[1].recording.points_m)
    for a in range(3):
        for b in range(a + 1, 3):
            gap = np.linalg.norm(perfs[a].root_position_m[:, :2] - perfs[b].root_position_m[:, :2], axis=-1)
            assert gap.min() > 1.2


def test_joint_angles_in_the_wire_convention():
    perf = perform(5, duration_s=20.0)  # squat included: YXZ puts flexion first, so knees pass 90 deg
    angles = perf.joint_angles_rad()
    assert angles.shape == (perf.recording.n_frames, 13, 3)
    assert np.abs(angles[: perf.tpose_frames]).max() < 1e-12
    back = Rotation.from_euler("YXZ", angles.reshape(-1, 3))
    difference = back.inv() * Rotation.from_quat(perf.rotations_xyzw[:, 1:].reshape(-1, 4))
    assert difference.magnitude().max() < 1e-9
    knee = angles[:, SEGMENTS.index("l_shank") - 1, 0]  # flexion about y comes first
    assert np.abs(knee).max() > 1.6  # past 90 degrees in the squat, without a jump
    assert np.abs(np.diff(knee)).max() < 0.2
