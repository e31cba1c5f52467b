"""recordings.bvh: a written file parses back to the same hierarchy and the same rotations."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol.skeleton import PARENTS, SEGMENTS
from recordings.bvh import BvhError, BvhMotion, end_sites_from_markers, read_bvh, write_bvh


def _motion(n_frames=50, seed=0) -> BvhMotion:
    rng = np.random.default_rng(seed)
    return BvhMotion(
        segments=SEGMENTS,
        parents=PARENTS,
        offsets_m=np.vstack([np.zeros(3), rng.uniform(-0.4, 0.4, (len(SEGMENTS) - 1, 3))]),
        root_positions_m=rng.uniform(-3, 3, (n_frames, 3)),
        rotations_xyzw=Rotation.random(n_frames * len(SEGMENTS), random_state=seed)
        .as_quat()
        .reshape(n_frames, len(SEGMENTS), 4),
        rate_hz=120.0,
        end_sites_m={3: np.array([0.0, 0.0, 0.12])},
    )


def _angle_between(q1, q2):
    return (Rotation.from_quat(q1.reshape(-1, 4)).inv() * Rotation.from_quat(q2.reshape(-1, 4))).magnitude()


@pytest.mark.parametrize("unit, up_axis", [("cm", "y"), ("m", "z"), ("m", "y")])
def test_round_trip(tmp_path, unit, up_axis):
    motion = _motion()
    path = tmp_path / "a.bvh"
    write_bvh(path, motion, unit=unit, up_axis=up_axis)
    back = read_bvh(path, unit=unit, up_axis=up_axis)
    assert back.segments == SEGMENTS and back.parents == PARENTS
    assert back.rate_hz == pytest.approx(120.0, rel=1e-6)
    np.testing.assert_allclose(back.offsets_m, motion.offsets_m, atol=1e-6)
    np.testing.assert_allclose(back.root_positions_m, motion.root_positions_m, atol=1e-6)
    assert _angle_between(back.rotations_xyzw, motion.rotations_xyzw).max() < 1e-6
    np.testing.assert_allclose(back.end_sites_m[3], [0.0, 0.0, 0.12], atol=1e-6)
    # every leaf gets an End Site, a zero one where none was given
    assert set(back.end_sites_m) == {3, 5, 7, 10, 13}
    np.testing.assert_allclose(back.end_sites_m[5], 0.0)


def test_known_file_layout(tmp_path):
    """Y-up centimetres: our z-up (0, 0, 0.5) offset of the abdomen is BVH (0, 50, 0); a rotation of
    90 degrees about our z (yaw, to the left) is a rotation about BVH Y, i.e. the Yrotation channel."""
    motion = _motion(n_frames=1)
    offsets = np.zeros((len(SEGMENTS), 3))
    offsets[1] = [0.0, 0.0, 0.5]
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (1, len(SEGMENTS), 1))
    rotations[0, 0] = Rotation.from_euler("z", 90, degrees=True).as_quat()
    motion = BvhMotion(SEGMENTS, PARENTS, offsets, np.array([[1.0, 2.0, 3.0]]), rotations, 60.0)
    path = tmp_path / "b.bvh"
    write_bvh(path, motion)
    text = path.read_text()
    lines = [line.strip() for line in text.splitlines()]
    assert lines[:5] == [
        "HIERARCHY",
        "ROOT pelvis",
        "{",
        "OFFSET 0.000000 0.000000 0.000000",
        "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
    ]
    assert "OFFSET 0.000000 50.000000 0.000000" in lines
    assert "CHANNELS 3 Zrotation Xrotation Yrotation" in lines
    assert "Frames: 1" in lines and "Frame Time: 0.01666667" in lines
    row = np.array(lines[-1].split(), float)
    assert row.shape == (6 + 3 * 13,)
    np.testing.assert_allclose(row[:3], [200.0, 300.0, 100.0], atol=1e-9)  # (y, z, x) in cm
    np.testing.assert_allclose(row[3:6], [0.0, 0.0, 90.0], atol=1e-9)
    np.testing.assert_allclose(row[6:], 0.0, atol=1e-9)


def test_reads_other_channel_orders(tmp_path):
    """A foreign file whose root uses XYZ rotation channels is composed in the listed order."""
    path = tmp_path / "c.bvh"
    path.write_text(
        "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition "
        "Xrotation Yrotation Zrotation\n End Site\n {\n OFFSET 0 10 0\n }\n}\n"
        "MOTION\nFrames: 1\nFrame Time: 0.01\n0 0 0 30 40 50\n"
    )
    back = read_bvh(path, unit="cm", up_axis="z")
    expected = Rotation.from_euler("XYZ", [30, 40, 50], degrees=True)
    assert _angle_between(back.rotations_xyzw[0, 0], expected.as_quat()).max() < 1e-9
    assert back.rate_hz == pytest.approx(100.0)


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "unexpected end"),
        ("HIERARCHY\nJOINT a", "expected 'ROOT'"),
        ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 x", "numbers"),
        ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Wrotation\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n0",
         "unknown channel"),
        ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n0 1",
         "after the 1 frames"),
    ],
)
def test_malformed_files_raise_bvh_error(tmp_path, text, message):
    path = tmp_path / "bad.bvh"
    path.write_text(text)
    with pytest.raises(BvhError, match=message):
        read_bvh(path)


def test_bad_options_and_shapes(tmp_path):
    with pytest.raises(BvhError, match="unit must be one of"):
        write_bvh(tmp_path / "x.bvh", _motion(), unit="mm")
    with pytest.raises(BvhError, match="parents"):
        BvhMotion(SEGMENTS, PARENTS[:-1], np.zeros((14, 3)), np.zeros((1, 3)), np.zeros((1, 14, 4)), 1.0)


def test_end_sites_from_markers():
    sites = end_sites_from_markers(14, PARENTS, [3, 3, 0], [[0, 0, 0.1], [0, 0, 0.3], [1, 1, 1]])
    np.testing.assert_allclose(sites[3], [0, 0, 0.2])
    np.testing.assert_allclose(sites[10], 0.0)
    assert set(sites) == {3, 5, 7, 10, 13}
