"""C3D files <-> `Recording`: the one place where C3D units and axes become metres, z up.

Reading and writing go through ezc3d (the maintained C3D library); this module only adds what ezc3d leaves
to the caller: which samples are missing, which unit and which vertical axis the file uses, and one typed
error (`C3DError`) with a one-sentence message for every file that cannot be used.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Sequence

import ezc3d
import numpy as np

from recordings.recording import Recording

__all__ = ["C3DError", "UP_AXES", "read_c3d", "write_c3d", "z_up_rotation"]

logger = logging.getLogger(__name__)

UP_AXES = ("x", "y", "z", "+x", "+y", "+z", "-x", "-y", "-z")
"""Valid values of `read_c3d(up_axis=...)` (case-insensitive), e.g. for argparse choices."""

_UNITS_PER_METRE = {"mm": 1000.0, "cm": 100.0, "m": 1.0}  # divide by these: 1e-3 is inexact

# With POINT:UNITS empty we must guess. A human-sized cloud spans ~0.3-3 m per frame, so a typical extent
# above 50 cannot be metres; it is taken as mm (cm cannot be told apart from mm and is never guessed).
_MM_IF_EXTENT_ABOVE = 50.0

# Proper rotations (det +1, so handedness is kept) taking the named up direction to +z: R @ up = e_z.
_ROTATION_TO_Z_UP = {
    "+z": np.eye(3),
    "-z": np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]]),  # 180 deg about x
    "+y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # (x, y, z) -> (x, -z, y)
    "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),  # (x, y, z) -> (x, z, -y)
    "+x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),  # (x, y, z) -> (-z, y, x)
    "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),  # (x, y, z) -> (z, y, -x)
}

# Up-axis heuristic thresholds (see `_FloorEvidence`); the real recordings in ../shared/data separate by
# a factor >= 2.5, so 1.5 leaves margin without trusting ties.
_DECISIVE_RATIO = 1.5
_STATIC_RANGE_M = 0.1  # a trajectory moving less than this over the whole take is a reflection/prop
_MIN_POINTS_PER_FRAME = 5
_MAX_FRAMES_FOR_HEURISTIC = 2000  # evenly subsampled: keeps reading a long take well under a second


class C3DError(ValueError):
    """A C3D file cannot be used: missing, not a C3D, corrupt, without POINT data, or unsupported content.

    The message is one sentence naming the file, fit to print on a command line as is.
    """


def z_up_rotation(up_axis: str) -> np.ndarray:
    """(3, 3) proper rotation R with R @ up = +z, for `up_axis` in `UP_AXES`; apply as points @ R.T."""
    return _ROTATION_TO_Z_UP[_normalise_axis(up_axis)].copy()


def read_c3d(path: str | os.PathLike, *, up_axis: str | None = None) -> Recording:
    """Read the POINT data of a C3D file as a `Recording` in metres, right-handed, z up.

    Missing samples (NaN, all-zero coordinates, or a negative residual) become NaN. The unit comes from
    POINT:UNITS, or is inferred from the cloud's size when that is empty. The vertical axis is `up_axis` when
    given (one of `UP_AXES`); otherwise it is read off the data (the floor: the axis along which the lowest
    points of every frame stay at one level) and POINT:Y_SCREEN (the axis a viewer draws upwards) settles
    what the data leave open. The data win over Y_SCREEN where they clearly disagree, because exporters
    write Y_SCREEN from display settings (numediart's Qualisys file says -Z and is z up).

    Raises:
        C3DError: the file is missing, is not a readable C3D, has no POINT data, is truncated, or uses a
            unit other than mm, cm, m.
    """
    forced_up = None if up_axis is None else _normalise_axis(up_axis)
    name = os.fspath(path)
    c3d = _open(name)
    params = c3d["parameters"]["POINT"]
    xyz = np.asarray(c3d["data"]["points"])[:3]  # (3, N, F) in file units
    n_points, n_frames = xyz.shape[1], xyz.shape[2]
    if n_points == 0 or n_frames == 0:
        raise C3DError(f"{name} holds no POINT data ({n_points} points, {n_frames} frames).")
    _check_not_truncated(name, n_frames)

    points = np.ascontiguousarray(xyz.transpose(2, 1, 0), dtype=np.float64)  # (F, N, 3)
    missing = np.isnan(points).any(axis=2) | (points == 0.0).all(axis=2)
    residuals = c3d["data"]["meta_points"].get("residuals")
    if residuals is not None and np.shape(residuals) == (1, n_points, n_frames):
        missing |= np.asarray(residuals)[0].T < 0
    points[missing] = np.nan

    points /= _units_per_metre(name, params, points)
    up = forced_up or _resolve_up_axis(points, params)
    if up != "+z":
        points = points @ _ROTATION_TO_Z_UP[up].T
    return Recording(
        points_m=points,
        labels=_labels(params, n_points),
        rate_hz=_rate_hz(name, c3d),
        source=name,
    )


def write_c3d(path: str | os.PathLike, points_m: np.ndarray, labels: Sequence[str], rate_hz: float) -> None:
    """Write labeled points (F, N, 3) [m], z up, NaN = missing, as a float C3D in mm that other tools open.

    Missing samples get residual -1; POINT:LABELS holds `labels` as given ("Subject:Marker"); X_SCREEN/
    Y_SCREEN say z up. Values round-trip through `read_c3d` to float32 precision in mm. A visible point at
    exactly (0, 0, 0) reads back as missing: C3D readers treat all-zero coordinates as a gap.

    Raises:
        ValueError: shapes, labels or rate are inconsistent, or there is no frame or no point.
        C3DError: the file cannot be written.
    """
    points_m = np.asarray(points_m, dtype=np.float64)
    labels = [str(label) for label in labels]
    if points_m.ndim != 3 or points_m.shape[2] != 3:
        raise ValueError(f"points_m must be (frames, points, 3), got {points_m.shape}")
    if points_m.shape[0] == 0 or points_m.shape[1] == 0:
        raise ValueError(f"points_m must hold at least one frame and one point, got {points_m.shape}")
    if len(labels) != points_m.shape[1]:
        raise ValueError(f"{len(labels)} labels for {points_m.shape[1]} points")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be a positive number, got {rate_hz}")
    n_frames, n_points, _ = points_m.shape
    missing = np.isnan(points_m).any(axis=2)  # (F, N)

    points = np.ones((4, n_points, n_frames))  # ezc3d layout: (xyz1, point, frame)
    points[:3] = (points_m * 1000.0).transpose(2, 1, 0)
    points[:3, missing.T] = np.nan
    residuals = np.where(missing.T, -1.0, 0.0)[np.newaxis]

    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(rate_hz)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c3d.add_parameter("POINT", "UNITS", ["mm"])
    c3d.add_parameter("POINT", "X_SCREEN", ["+X"])
    c3d.add_parameter("POINT", "Y_SCREEN", ["+Z"])
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"]["residuals"] = residuals
    name = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(name))
    if not os.path.isdir(folder):
        raise C3DError(f"cannot write {name}: the folder {folder} does not exist.")
    try:
        c3d.write(name)
    except (OSError, RuntimeError, ValueError) as error:
        raise C3DError(f"cannot write {name}: {_reason(error)}.") from error
    if not os.path.isfile(name):  # ezc3d reports some failures (e.g. no permission) by writing nothing
        raise C3DError(f"cannot write {name}: nothing was written.")


def _open(name: str) -> ezc3d.c3d:
    """ezc3d's reader, with its errors turned into one C3DError sentence."""
    # Checked here, not left to ezc3d: given a directory, ezc3d blocks forever instead of failing.
    if not os.path.exists(name):
        raise C3DError(f"{name} does not exist.")
    if not os.path.isfile(name):
        raise C3DError(f"{name} is not a file.")
    if os.path.getsize(name) == 0:
        raise C3DError(f"{name} is empty, not a C3D file.")
    try:
        return ezc3d.c3d(name)
    except (OSError, RuntimeError, ValueError, IndexError, MemoryError) as error:
        raise C3DError(f"{name} is not a readable C3D file ({_reason(error)}).") from error


def _reason(error: BaseException) -> str:
    """ezc3d's message without its ': iostream error' suffix and trailing period."""
    return str(error).removesuffix(": iostream error").rstrip(". ") or type(error).__name__


def _check_not_truncated(name: str, n_frames_read: int) -> None:
    """Fail on a cut-off file: ezc3d silently returns the frames that fit and rewrites its header to match.

    The frame range is read from the raw 512-byte header (words 4 and 5, 1-based, little-endian unless the
    parameter section says MIPS). A long take whose last frame does not fit in 16 bits is not checked.
    """
    with open(name, "rb") as file:
        header = file.read(512)
        parameter_block = header[0]
        file.seek(max(parameter_block - 1, 0) * 512 + 3)
        processor = file.read(1)
    order = ">" if processor == bytes([86]) else "<"  # 84 Intel, 85 DEC: little-endian; 86 MIPS: big
    first_frame, last_frame = np.frombuffer(header[6:10], dtype=f"{order}u2")
    n_frames_promised = int(last_frame) - int(first_frame) + 1
    if n_frames_read < n_frames_promised:
        raise C3DError(
            f"{name} is truncated: its header promises {n_frames_promised} frames but it holds {n_frames_read}."
        )


def _labels(params: dict, n_points: int) -> tuple[str, ...]:
    """POINT:LABELS, LABELS2, ... stripped; points without a label are named '*i' as C3D tools do."""
    labels: list[str] = []
    for key in ["LABELS"] + [f"LABELS{i}" for i in range(2, 100)]:
        if key not in params:
            break
        labels.extend(str(label).strip() for label in params[key]["value"])
    labels = labels[:n_points]
    labels.extend(f"*{i}" for i in range(len(labels), n_points))
    return tuple(labels)


def _rate_hz(name: str, c3d: ezc3d.c3d) -> float:
    """POINT:RATE, falling back to the header's frame rate."""
    rate = c3d["parameters"]["POINT"].get("RATE", {}).get("value", [])
    rate_hz = float(rate[0]) if len(rate) else float(c3d["header"]["points"]["frame_rate"])
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise C3DError(f"{name} has no usable POINT:RATE (got {rate_hz}).")
    return rate_hz


def _units_per_metre(name: str, params: dict, points: np.ndarray) -> float:
    """File units in one metre: POINT:UNITS, or inferred from the cloud's size when empty."""
    value = params.get("UNITS", {}).get("value", [])
    unit = str(value[0]).strip().lower() if len(value) else ""
    if unit in _UNITS_PER_METRE:
        return _UNITS_PER_METRE[unit]
    if unit:
        raise C3DError(f"{name} has POINT:UNITS '{unit}'; supported are 'mm', 'cm', 'm' or empty.")
    visible = points[::max(1, len(points) // 200)]  # ~200 frames are plenty to see the size
    visible = visible[np.isfinite(visible).all(axis=2).sum(axis=1) >= 2]
    if len(visible) == 0:
        return 1.0  # nothing visible: the unit does not matter
    extent = np.nanmax(np.nanmax(visible, axis=1) - np.nanmin(visible, axis=1), axis=1)
    unit = "mm" if np.median(extent) > _MM_IF_EXTENT_ABOVE else "m"
    logger.debug("%s: POINT:UNITS empty, inferred '%s' from a typical extent of %.3g", name, unit, np.median(extent))
    return _UNITS_PER_METRE[unit]


def _normalise_axis(axis: str) -> str:
    """'y', 'Y', '+Y' -> '+y'; '-Z' -> '-z'; anything else is a ValueError listing the choices."""
    text = str(axis).strip().lower()
    if text not in UP_AXES:
        raise ValueError(f"up axis must be one of {', '.join(UP_AXES)} (case-insensitive), got {axis!r}")
    return text if text[0] in "+-" else "+" + text


def _screen_up(params: dict) -> str | None:
    """POINT:Y_SCREEN as a signed axis when it names one (and X_SCREEN, if present, names another)."""

    def parse(key: str) -> str | None:
        value = params.get(key, {}).get("value", [])
        try:
            return _normalise_axis(value[0]) if len(value) else None
        except ValueError:
            return None

    up, right = parse("Y_SCREEN"), parse("X_SCREEN")
    if up is None or (right is not None and right[1] == up[1]):
        return None
    return up


@dataclasses.dataclass(frozen=True)
class _FloorEvidence:
    """What the points say about the vertical, per axis x, y, z.

    A floor shows as a level that the lowest points of every frame keep (feet, or the body lying on it)
    while the cloud moves along the other axes; an upright body also makes the vertical extent large.
    `score` is the spread over frames of the per-frame low end, over the median per-frame extent (small =
    floor-like). `sign` is +1 where the low end is steadier than the high end (floor below), else -1.
    """

    score: np.ndarray  # (3,)
    sign: np.ndarray  # (3,) +1 / -1
    sign_decisive: np.ndarray  # (3,) bool: the steady end is clearly steadier than the other

    @property
    def axis(self) -> int:
        return int(np.argmin(self.score))

    @property
    def axis_decisive(self) -> bool:
        best, second = np.sort(self.score)[:2]
        return bool(second > 0 and second >= _DECISIVE_RATIO * best)  # all-zero scores decide nothing


def _floor_evidence(points_m: np.ndarray) -> _FloorEvidence | None:
    """Floor-likeness of each axis, or None when too little is visible to judge."""
    points = points_m[:: max(1, len(points_m) // _MAX_FRAMES_FOR_HEURISTIC)]
    seen = np.isfinite(points[..., 0])  # (F, N)
    points = points[:, seen.any(axis=0)]
    if points.shape[1] == 0:
        return None
    travel = np.nanmax(points, axis=0) - np.nanmin(points, axis=0)  # (N, 3)
    points = points[:, travel.max(axis=1) >= _STATIC_RANGE_M]  # static reflections would fake a floor
    points = points[np.isfinite(points[..., 0]).sum(axis=1) >= _MIN_POINTS_PER_FRAME]
    if len(points) < 2:
        return None
    # The 5th percentile rather than the minimum: one ghost or spike per frame must not set the level.
    low, high = _nan_percentiles_per_frame(points, 5), _nan_percentiles_per_frame(points, 95)  # (F, 3)
    extent = np.median(np.nanmax(points, axis=1) - np.nanmin(points, axis=1), axis=0)
    low_spread = np.subtract(*np.percentile(low, [90, 10], axis=0))  # (3,) how far the low end wanders
    high_spread = np.subtract(*np.percentile(high, [90, 10], axis=0))
    score = low_spread / np.maximum(extent, 1e-9)
    sign = np.where(low_spread <= high_spread, 1, -1)
    steady, other = np.minimum(low_spread, high_spread), np.maximum(low_spread, high_spread)
    return _FloorEvidence(score=score, sign=sign, sign_decisive=other >= _DECISIVE_RATIO * np.maximum(steady, 1e-9))


def _nan_percentiles_per_frame(points: np.ndarray, percent: float) -> np.ndarray:
    """(F, N, 3) -> (F, 3): nearest-rank percentile over each frame's visible points.

    Hand-written because np.nanpercentile loops over frames in Python (~1 s for a 4000-frame take);
    sorting puts NaN last, so the rank only has to be taken among each frame's visible count.
    """
    ordered = np.sort(points, axis=1)
    n_visible = np.isfinite(points).sum(axis=1)  # (F, 3)
    rank = np.rint(percent / 100.0 * (n_visible - 1)).astype(int)
    return np.take_along_axis(ordered, rank[:, np.newaxis, :], axis=1)[:, 0, :]


def _resolve_up_axis(points_m: np.ndarray, params: dict) -> str:
    """Signed up axis from the data where they are decisive, else POINT:Y_SCREEN, else z up."""
    evidence = _floor_evidence(points_m)
    hint = _screen_up(params)
    if evidence is not None and evidence.axis_decisive:
        axis = "xyz"[evidence.axis]
    elif hint is not None:
        axis = hint[1]
    elif evidence is not None:
        axis = "xyz"[evidence.axis]
    else:
        axis = "z"
    i = "xyz".index(axis)
    if evidence is not None and evidence.sign_decisive[i]:
        sign = "+" if evidence.sign[i] > 0 else "-"
    elif hint is not None and hint[1] == axis:
        sign = hint[0]
    else:
        # Labs put the origin on the floor, so the body lies on the positive side of the up axis.
        median = np.nanmedian(points_m[..., i]) if np.isfinite(points_m[..., i]).any() else 0.0
        sign = "-" if median < 0 else "+"
    up = sign + axis
    if hint is not None and hint != up:
        logger.info("POINT:Y_SCREEN says %s but the floor in the data says %s; using %s", hint, up, up)
    return up
