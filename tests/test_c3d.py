"""recordings/c3d.py: exact round trip, units, vertical axis, the real recordings' known facts, and errors."""

from __future__ import annotations

from pathlib import Path

import ezc3d
import numpy as np
import pytest

from tests.conftest import data_path

from recordings.c3d import UP_AXES, C3DError, read_c3d, write_c3d, z_up_rotation
from recordings.recording import is_marker_label, split_label



def walker(n_frames: int = 240, seed: int = 0) -> np.ndarray:
    """(F, 20, 3) [m] z-up cloud like a person walking along x: 4 foot points stay on the floor."""
    rng = np.random.default_rng(seed)
    body_m = np.column_stack(
        [rng.uniform(-0.25, 0.25, 20), rng.uniform(-0.2, 0.2, 20), rng.uniform(0.3, 1.75, 20)]
    )
    body_m[:4, 2] = 0.03  # feet
    t_s = np.arange(n_frames) / 120.0
    travel_m = np.column_stack([1.2 * t_s, 0.1 * np.sin(t_s), np.zeros(n_frames)])
    jitter_m = rng.normal(0.0, 0.04, (n_frames, 20, 3))
    jitter_m[:, :4, 2] = rng.normal(0.0, 0.003, (n_frames, 4))
    return body_m + travel_m[:, np.newaxis, :] + jitter_m


def with_gaps(points_m: np.ndarray, fraction: float = 0.1, seed: int = 1) -> np.ndarray:
    points_m = points_m.copy()
    points_m[np.random.default_rng(seed).random(points_m.shape[:2]) < fraction] = np.nan
    return points_m


def patch_units(source: Path, target: Path, units: list[str]) -> None:
    c3d = ezc3d.c3d(str(source))
    c3d["parameters"]["POINT"]["UNITS"]["value"] = units
    c3d.write(str(target))


def float32_mm(points_m: np.ndarray) -> np.ndarray:
    """What a float C3D in mm keeps of points_m, back in metres."""
    return np.float32(points_m * 1000.0).astype(np.float64) / 1000.0


# --- round trip -------------------------------------------------------------------------------------------


def test_round_trip_keeps_values_gaps_labels_and_rate(tmp_path):
    points_m = with_gaps(walker())
    labels = [f"Ann:M{i}" for i in range(10)] + [f"Bob:M{i}" for i in range(10)]
    write_c3d(tmp_path / "walk.c3d", points_m, labels, 119.88)

    recording = read_c3d(tmp_path / "walk.c3d")  # no up_axis: the file and the data must both say z up

    np.testing.assert_array_equal(np.isnan(recording.points_m), np.isnan(points_m))
    np.testing.assert_array_equal(recording.points_m, float32_mm(points_m))
    assert recording.points_m.dtype == np.float64
    assert recording.labels == tuple(labels)
    assert recording.rate_hz == pytest.approx(119.88, rel=1e-6)
    assert recording.source == str(tmp_path / "walk.c3d")


def test_written_file_is_mm_with_negative_residual_for_gaps(tmp_path):
    points_m = with_gaps(walker(n_frames=50))
    write_c3d(tmp_path / "walk.c3d", points_m, [f"S:M{i}" for i in range(20)], 100.0)

    raw = ezc3d.c3d(str(tmp_path / "walk.c3d"))
    point = raw["parameters"]["POINT"]
    assert point["UNITS"]["value"] == ["mm"]
    assert point["RATE"]["value"][0] == 100.0
    assert point["LABELS"]["value"][:2] == ["S:M0", "S:M1"]
    residuals = raw["data"]["meta_points"]["residuals"][0].T  # (F, N)
    missing = np.isnan(points_m[..., 0])
    assert (residuals[missing] == -1).all() and (residuals[~missing] >= 0).all()
    raw_mm = raw["data"]["points"][:3].transpose(2, 1, 0)
    np.testing.assert_allclose(raw_mm[~missing], 1000 * points_m[~missing], rtol=1e-6)


def test_round_trip_of_more_than_255_points_keeps_every_label(tmp_path):
    """C3D stores labels in blocks of 255 (LABELS, LABELS2, ...): all must come back in order."""
    points_m = np.tile(walker(n_frames=10), (1, 15, 1))  # 300 points
    labels = [f"P{i}" for i in range(300)]
    write_c3d(tmp_path / "many.c3d", points_m, labels, 60.0)

    recording = read_c3d(tmp_path / "many.c3d", up_axis="z")

    assert recording.labels == tuple(labels)
    np.testing.assert_array_equal(recording.points_m, float32_mm(points_m))


def test_all_zero_coordinates_and_negative_residuals_read_as_missing(tmp_path):
    points_m = walker(n_frames=30)
    write_c3d(tmp_path / "walk.c3d", points_m, [f"M{i}" for i in range(20)], 100.0)
    c3d = ezc3d.c3d(str(tmp_path / "walk.c3d"))
    raw = c3d["data"]["points"]
    raw[:3, 5, 7] = 0.0  # all-zero sample: a gap in C3D convention
    residuals = c3d["data"]["meta_points"]["residuals"]
    residuals[0, 6, 8] = -1.0  # negative residual: a gap though coordinates are present
    c3d["data"]["points"] = raw
    c3d["data"]["meta_points"]["residuals"] = residuals
    c3d.write(str(tmp_path / "gaps.c3d"))

    recording = read_c3d(tmp_path / "gaps.c3d", up_axis="z")

    missing = np.isnan(recording.points_m).any(axis=2)
    assert missing[7, 5] and missing[8, 6]
    assert missing.sum() == 2


def test_write_rejects_inconsistent_arguments(tmp_path):
    with pytest.raises(ValueError, match="frames, points, 3"):
        write_c3d(tmp_path / "x.c3d", np.zeros((5, 3)), ["a"] * 5, 100.0)
    with pytest.raises(ValueError, match="2 labels for 3 points"):
        write_c3d(tmp_path / "x.c3d", np.zeros((5, 3, 3)), ["a", "b"], 100.0)
    with pytest.raises(ValueError, match="at least one frame and one point"):
        write_c3d(tmp_path / "x.c3d", np.zeros((0, 3, 3)), ["a", "b", "c"], 100.0)
    with pytest.raises(ValueError, match="rate_hz"):
        write_c3d(tmp_path / "x.c3d", np.zeros((5, 3, 3)), ["a", "b", "c"], 0.0)


# --- units ------------------------------------------------------------------------------------------------


def test_units_parameter_sets_the_scale(tmp_path):
    points_m = walker(n_frames=60)
    write_c3d(tmp_path / "mm.c3d", points_m, [f"M{i}" for i in range(20)], 100.0)  # file numbers: mm
    expected_mm = float32_mm(points_m)

    patch_units(tmp_path / "mm.c3d", tmp_path / "m.c3d", ["m"])
    patch_units(tmp_path / "mm.c3d", tmp_path / "cm.c3d", ["cm"])

    np.testing.assert_allclose(read_c3d(tmp_path / "m.c3d", up_axis="z").points_m, 1000 * expected_mm, rtol=1e-12)
    np.testing.assert_allclose(read_c3d(tmp_path / "cm.c3d", up_axis="z").points_m, 10 * expected_mm, rtol=1e-12)


def test_empty_units_are_inferred_from_the_cloud_size(tmp_path):
    points_m = walker(n_frames=60)
    labels = [f"M{i}" for i in range(20)]
    write_c3d(tmp_path / "mm.c3d", points_m, labels, 100.0)  # numbers ~1000: must be mm
    write_c3d(tmp_path / "metre_numbers.c3d", points_m / 1000.0, labels, 100.0)  # numbers ~1: must be m
    patch_units(tmp_path / "mm.c3d", tmp_path / "mm_empty.c3d", [""])
    patch_units(tmp_path / "metre_numbers.c3d", tmp_path / "m_empty.c3d", [])

    np.testing.assert_array_equal(read_c3d(tmp_path / "mm_empty.c3d").points_m, float32_mm(points_m))
    np.testing.assert_allclose(read_c3d(tmp_path / "m_empty.c3d").points_m, points_m, rtol=1e-6)


def test_unknown_units_are_a_c3d_error_naming_the_valid_ones(tmp_path):
    write_c3d(tmp_path / "mm.c3d", walker(n_frames=10), [f"M{i}" for i in range(20)], 100.0)
    patch_units(tmp_path / "mm.c3d", tmp_path / "ft.c3d", ["ft"])

    with pytest.raises(C3DError, match="'ft'; supported are 'mm', 'cm', 'm' or empty"):
        read_c3d(tmp_path / "ft.c3d")


# --- vertical axis ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("up", ["+x", "-x", "+y", "-y", "+z", "-z"])
def test_z_up_rotation_is_proper_and_takes_up_to_z(up):
    rotation = z_up_rotation(up)
    up_vector = np.zeros(3)
    up_vector["xyz".index(up[1])] = 1.0 if up[0] == "+" else -1.0

    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rotation @ up_vector, [0.0, 0.0, 1.0], atol=1e-12)


def test_y_up_becomes_x_minus_z_y():
    np.testing.assert_array_equal(z_up_rotation("y") @ [1.0, 2.0, 3.0], [1.0, -3.0, 2.0])


@pytest.mark.parametrize("up", ["+y", "-y", "+x", "-x", "-z"])
def test_a_floor_on_another_axis_is_found_and_turned_to_z(tmp_path, up):
    """A z-up walker stored with `up` as vertical (and no screen hint) reads back z up."""
    points_m = with_gaps(walker())
    stored_m = points_m @ z_up_rotation(up)  # inverse rotation: z up -> `up`
    write_c3d(tmp_path / "turned.c3d", stored_m, [f"M{i}" for i in range(20)], 120.0)
    c3d = ezc3d.c3d(str(tmp_path / "turned.c3d"))  # drop X_SCREEN/Y_SCREEN: the data alone must decide
    c3d["parameters"]["POINT"]["Y_SCREEN"]["value"] = ["?"]
    c3d.write(str(tmp_path / "turned_no_hint.c3d"))

    recording = read_c3d(tmp_path / "turned_no_hint.c3d")

    np.testing.assert_allclose(recording.points_m, points_m, atol=1e-6)


def test_explicit_up_axis_wins_over_the_data(tmp_path):
    points_m = walker(n_frames=60)
    write_c3d(tmp_path / "walk.c3d", points_m, [f"M{i}" for i in range(20)], 100.0)

    recording = read_c3d(tmp_path / "walk.c3d", up_axis="Y")

    np.testing.assert_array_equal(recording.points_m, float32_mm(points_m) @ z_up_rotation("y").T)


def test_invalid_up_axis_names_the_choices(tmp_path):
    with pytest.raises(ValueError, match="must be one of x, y, z"):
        read_c3d(tmp_path / "whatever.c3d", up_axis="up")
    assert "-z" in UP_AXES


def _mean_height_m(recording, names: set[str]) -> float:
    columns = [i for i, label in enumerate(recording.labels) if split_label(label)[1] in names]
    assert len(columns) == len(names), f"expected markers {names} in {recording.source}"
    return float(np.nanmean(recording.points_m[:, columns, 2]))


def test_georgiatech_squat_is_y_up_and_read_z_up():
    path = data_path("georgiatech/squat.c3d")
    raw_mm = ezc3d.c3d(str(path))["data"]["points"][:3].transpose(2, 1, 0)

    recording = read_c3d(path)

    head_m = _mean_height_m(recording, {"LFHD", "RFHD", "LBHD", "RBHD"})
    feet_m = _mean_height_m(recording, {"LTOE", "RTOE", "LHEL", "RHEL"})
    assert head_m > feet_m + 1.0
    assert 0.0 < np.nanpercentile(recording.points_m[..., 2], 1) < 0.15  # floor near z = 0
    # (x, y, z) -> (x, -z, y), exactly
    np.testing.assert_allclose(recording.points_m[..., 2], raw_mm[..., 1] / 1000.0, rtol=1e-12)
    np.testing.assert_allclose(recording.points_m[..., 1], -raw_mm[..., 2] / 1000.0, rtol=1e-12)
    np.testing.assert_array_equal(recording.points_m, read_c3d(path, up_axis="y").points_m)


@pytest.mark.parametrize("relative", ["cmu/07_01.c3d", "numediart/03_rolling.c3d"])
def test_z_up_files_are_not_rotated(relative):
    """CMU says +Z in Y_SCREEN; numediart says -Z there but its floor is at z = 0 below the body."""
    path = data_path(relative)
    raw_mm = ezc3d.c3d(str(path))["data"]["points"][:3].transpose(2, 1, 0)

    recording = read_c3d(path)

    seen = np.isfinite(recording.points_m)
    np.testing.assert_allclose(recording.points_m[seen], raw_mm[seen] / 1000.0, rtol=1e-12)


def test_cmu_head_is_above_feet():
    recording = read_c3d(data_path("cmu/07_01.c3d"))

    head_m = _mean_height_m(recording, {"LFHD", "RFHD", "LBHD", "RBHD"})
    feet_m = _mean_height_m(recording, {"LTOE", "RTOE", "LHEE", "RHEE"})
    assert 1.4 < head_m < 2.0 and 0.0 < feet_m < 0.2


# --- the README's per-file facts --------------------------------------------------------------------------

# file, frames, rate [Hz], points, named markers, metres per file unit
README_FACTS = [
    ("hdm05/HDM_mm_01-02_03_120.c3d", 3990, 120, 44, 41, 1e-3),
    ("hdm05/HDM_dg_06-03_03_120.c3d", 202, 120, 44, 41, 1e-3),
    ("cmu/135_02.c3d", 5202, 120, 41, 41, 1e-3),
    ("cmu/85_12.c3d", 4499, 120, 41, 41, 1e-3),
    ("cmu/85_02.c3d", 810, 120, 41, 41, 1e-3),
    ("cmu/cmu_02_05.c3d", 1854, 120, 41, 41, 1e-3),
    ("cmu/cmu_dribble_shoot_basketball.c3d", 494, 120, 41, 41, 1e-3),
    ("cmu/07_01.c3d", 316, 120, 41, 41, 1e-3),
    ("georgiatech/squat.c3d", 2539, 120, 53, 53, 1e-3),
    ("numediart/03_rolling.c3d", 2305, 175, 68, 68, 1e-3),
    ("clouthier/KneeltoProne01.c3d", 1745, 240, 62, 62, 1e-3),
    ("clouthier/S09_KneeltoRun02.c3d", 1479, 240, 75, 0, 1e-3),
    ("kineticstoolkit/kinematics_tennis_serve.c3d", 1092, 50, 39, 39, 1.0),
    ("kineticstoolkit/kinematics_tennis_serve_2players.c3d", 599, 50, 78, 78, 1.0),
]


@pytest.mark.parametrize(
    ("relative", "n_frames", "rate_hz", "n_points", "n_named", "metres_per_unit"), README_FACTS
)
def test_readme_facts(relative, n_frames, rate_hz, n_points, n_named, metres_per_unit):
    path = data_path(relative)

    recording = read_c3d(path)

    assert recording.points_m.shape == (n_frames, n_points, 3)
    assert recording.rate_hz == rate_hz
    assert sum(is_marker_label(label) for label in recording.labels) == n_named
    assert all(label == label.strip() for label in recording.labels)
    # Units: a visible sample's height equals the file's vertical coordinate times the unit (z up files).
    if relative != "georgiatech/squat.c3d":
        raw = ezc3d.c3d(str(path))["data"]["points"][2].T
        seen = np.isfinite(recording.points_m[..., 2])
        np.testing.assert_allclose(recording.points_m[..., 2][seen], raw[seen] * metres_per_unit, rtol=1e-12)
    assert -0.05 < np.nanpercentile(recording.points_m[..., 2], 1) < 0.15  # the floor, in metres
    assert 0.4 < np.nanmax(recording.points_m[..., 2]) < 2.5  # a person's reach (numediart never stands)


@pytest.mark.parametrize(
    ("relative", "low", "high"),
    [
        ("georgiatech/squat.c3d", 0.01, 0.025),
        ("numediart/03_rolling.c3d", 0.20, 0.26),
        ("hdm05/HDM_dg_06-03_03_120.c3d", 0.0, 0.0),
    ],
)
def test_readme_missing_fractions(relative, low, high):
    recording = read_c3d(data_path(relative))

    missing = np.isnan(recording.points_m).any(axis=2).mean()

    assert low <= missing <= high


def test_two_players_file_has_two_subjects_of_39():
    recording = read_c3d(data_path("kineticstoolkit/kinematics_tennis_serve_2players.c3d"))

    subjects = [split_label(label)[0] for label in recording.labels]

    assert sorted({s: subjects.count(s) for s in subjects}.values()) == [39, 39]


# --- errors -----------------------------------------------------------------------------------------------


def assert_one_sentence(error: C3DError, path: Path) -> None:
    message = str(error)
    assert str(path) in message and message.endswith(".") and "\n" not in message


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes(), "not a readable C3D"),
        (bytes([2, 0x50]) + np.random.default_rng(1).bytes(5000), "not a readable C3D"),
        (b"", "is empty"),
        (b"frame,x,y,z\n1,0.1,0.2,0.3\n" * 20, "not a readable C3D"),
    ],
    ids=["random", "random-with-c3d-magic", "empty", "text"],
)
def test_corrupt_file_is_a_c3d_error(tmp_path, content, reason):
    path = tmp_path / "bad.c3d"
    path.write_bytes(content)

    with pytest.raises(C3DError, match=reason) as caught:
        read_c3d(path)

    assert_one_sentence(caught.value, path)


def test_truncated_file_is_a_c3d_error(tmp_path):
    write_c3d(tmp_path / "walk.c3d", walker(), [f"M{i}" for i in range(20)], 100.0)
    whole = (tmp_path / "walk.c3d").read_bytes()
    path = tmp_path / "cut.c3d"
    path.write_bytes(whole[: len(whole) * 2 // 3])

    with pytest.raises(C3DError, match="truncated: its header promises 240 frames") as caught:
        read_c3d(path)

    assert_one_sentence(caught.value, path)


def test_missing_file_and_directory_are_c3d_errors(tmp_path):
    with pytest.raises(C3DError, match="does not exist") as caught:
        read_c3d(tmp_path / "absent.c3d")
    assert_one_sentence(caught.value, tmp_path / "absent.c3d")

    with pytest.raises(C3DError, match="is not a file"):
        read_c3d(tmp_path)


def test_unwritable_path_is_a_c3d_error(tmp_path):
    path = tmp_path / "no_such_folder" / "x.c3d"

    with pytest.raises(C3DError, match="does not exist") as caught:
        write_c3d(path, walker(n_frames=2), [f"M{i}" for i in range(20)], 100.0)

    assert_one_sentence(caught.value, path)


def test_c3d_error_is_a_value_error():
    assert issubclass(C3DError, ValueError)


def test_file_without_points_is_a_c3d_error(tmp_path):
    path = tmp_path / "empty_points.c3d"
    c3d = ezc3d.c3d()  # 10 frames of zero points (write_c3d refuses to make such a file)
    c3d["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c3d["data"]["points"] = np.ones((4, 0, 10))
    c3d["data"]["meta_points"]["residuals"] = np.zeros((1, 0, 10))
    c3d.write(str(path))

    with pytest.raises(C3DError, match="no POINT data") as caught:
        read_c3d(path)

    assert_one_sentence(caught.value, path)
