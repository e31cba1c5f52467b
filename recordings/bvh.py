"""BVH (Biovision hierarchy) files: write a tracked skeleton's motion so Blender, MotionBuilder or any
animation tool can import it, and read one back (used by the tests and by anyone checking an export).

What we write, and why:
- **Y up**, body facing +Z, its left at +X: BVH has no axis field and the importers (Blender's default
  ``axis_up="Y", axis_forward="-Z"``, MotionBuilder) assume y-up, so a z-up file would lie on its back.
  The change of basis is a proper rotation (x, y, z)_ours -> (y, z, x)_bvh, applied to offsets, positions
  and (by conjugation) to every rotation; ``up_axis="z"`` writes our frame unchanged.
- **Centimetres** by default (MotionBuilder's and most BVH libraries' unit); ``unit="m"`` writes metres.
  BVH does not record its unit, so a reader must be told (``read_bvh(..., unit=...)``).
- **Euler channels ``Zrotation Xrotation Yrotation``** in degrees on every joint (the root also has
  ``Xposition Yposition Zposition`` first): R = Rz(a) Rx(b) Ry(c), the order every importer understands.
- In the rest pose (all rotations identity) every segment frame is aligned with the world, which is what
  BVH assumes: a joint's OFFSET is its origin in its parent's frame, exactly our ``joint_offsets_m``.

Hand-written rather than a dependency: the format is ~100 lines either way, and the BVH packages on PyPI
are readers only or pull in a scene graph.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

_UNIT_SCALE = {"cm": 100.0, "m": 1.0}
#: rows map our z-up body frame (x forward, y left, z up) to BVH's y-up frame (z forward, x left, y up).
_C_BVH_OURS = {
    "y": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    "z": np.eye(3),
}
_ROT_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")
_POS_CHANNELS = ("Xposition", "Yposition", "Zposition")


class BvhError(ValueError):
    """A BVH file is malformed or its options are invalid; the message says where or what is valid."""


@dataclasses.dataclass(frozen=True)
class BvhMotion:
    """A skeleton's hierarchy and motion in *our* convention: metres, z up, rotations xyzw.

    rotations_xyzw[f, 0] is the root's rotation in the world; every other one is relative to its parent.
    """

    segments: tuple[str, ...]  # (J,)
    parents: tuple[int, ...]  # (J,), -1 for the root; parents precede children
    offsets_m: np.ndarray  # (J, 3) segment origin in its parent's frame [m]; root: zeros
    root_positions_m: np.ndarray  # (F, 3) [m]
    rotations_xyzw: np.ndarray  # (F, J, 4)
    rate_hz: float
    end_sites_m: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)
    """Leaf segment index -> End Site offset in that segment's frame [m] (display only)."""

    def __post_init__(self) -> None:
        n = len(self.segments)
        if len(self.parents) != n or np.shape(self.offsets_m) != (n, 3):
            raise BvhError(f"{n} segments need {n} parents and ({n}, 3) offsets")
        if any(not (-1 <= p < i) for i, p in enumerate(self.parents)) or self.parents[0] != -1:
            raise BvhError("the first segment must be the only root and parents must precede children")
        f = np.shape(self.root_positions_m)[0]
        if np.shape(self.root_positions_m) != (f, 3) or np.shape(self.rotations_xyzw) != (f, n, 4):
            raise BvhError(f"need (F, 3) root positions and (F, {n}, 4) rotations")
        if not self.rate_hz > 0:
            raise BvhError(f"rate_hz must be > 0, got {self.rate_hz}")

    @property
    def n_frames(self) -> int:
        return self.root_positions_m.shape[0]


def _check_options(unit: str, up_axis: str) -> tuple[float, np.ndarray]:
    if unit not in _UNIT_SCALE:
        raise BvhError(f"unit must be one of {sorted(_UNIT_SCALE)}, got {unit!r}")
    if up_axis not in _C_BVH_OURS:
        raise BvhError(f"up_axis must be one of {sorted(_C_BVH_OURS)}, got {up_axis!r}")
    return _UNIT_SCALE[unit], _C_BVH_OURS[up_axis]


def end_sites_from_markers(
    n_segments: int, parents, marker_segment, marker_offsets_m
) -> dict[int, np.ndarray]:
    """End Site of each leaf segment = mean of its markers' offsets, so the leaf bone (head, hands, feet)
    has a visible length in a viewer; a leaf without markers gets none (a zero offset)."""
    marker_segment = np.asarray(marker_segment, dtype=int)
    marker_offsets_m = np.asarray(marker_offsets_m, dtype=float).reshape(-1, 3)
    leaves = set(range(n_segments)) - set(int(p) for p in parents)
    sites = {}
    for leaf in sorted(leaves):
        on_leaf = marker_offsets_m[marker_segment == leaf]
        sites[leaf] = on_leaf.mean(axis=0) if len(on_leaf) else np.zeros(3)
    return sites


def _fmt(values) -> str:
    return " ".join(f"{v:.6f}" for v in values)


def write_bvh(path: str | Path, motion: BvhMotion, *, unit: str = "cm", up_axis: str = "y") -> None:
    """Write `motion` to `path` as BVH (see the module docstring for the conventions)."""
    scale, C = _check_options(unit, up_axis)
    children: dict[int, list[int]] = {i: [] for i in range(len(motion.segments))}
    for i, p in enumerate(motion.parents):
        if p >= 0:
            children[p].append(i)

    lines = ["HIERARCHY"]

    def emit(i: int, depth: int) -> None:
        pad = "\t" * depth
        kind = "ROOT" if motion.parents[i] < 0 else "JOINT"
        channels = (_POS_CHANNELS + _ROT_CHANNELS) if motion.parents[i] < 0 else _ROT_CHANNELS
        lines.append(f"{pad}{kind} {motion.segments[i]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {_fmt(C @ motion.offsets_m[i] * scale)}")
        lines.append(f"{pad}\tCHANNELS {len(channels)} {' '.join(channels)}")
        for c in children[i]:
            emit(c, depth + 1)
        if not children[i]:
            site = motion.end_sites_m.get(i, np.zeros(3))
            lines.append(f"{pad}\tEnd Site")
            lines.append(f"{pad}\t{{")
            lines.append(f"{pad}\t\tOFFSET {_fmt(C @ np.asarray(site, float) * scale)}")
            lines.append(f"{pad}\t}}")
        lines.append(f"{pad}}}")

    emit(0, 0)
    order = _depth_first(motion.parents)

    f, j = motion.n_frames, len(motion.segments)
    rot = Rotation.from_quat(np.asarray(motion.rotations_xyzw, float).reshape(-1, 4)).as_matrix()
    rot_bvh = C @ rot @ C.T  # the same rotations seen in BVH axes (C is orthonormal)
    euler_deg = Rotation.from_matrix(rot_bvh).as_euler("ZXY", degrees=True).reshape(f, j, 3)
    root_bvh = np.asarray(motion.root_positions_m, float) @ C.T * scale
    columns = [root_bvh] + [euler_deg[:, i] for i in order]
    table = np.concatenate(columns, axis=1)

    lines.append("MOTION")
    lines.append(f"Frames: {f}")
    lines.append(f"Frame Time: {1.0 / motion.rate_hz:.8f}")
    lines.extend(_fmt(row) for row in table)
    Path(path).write_text("\n".join(lines) + "\n")


def _depth_first(parents) -> list[int]:
    """Joint order of the channels in MOTION: the depth-first order in which HIERARCHY lists them."""
    children: dict[int, list[int]] = {i: [] for i in range(len(parents))}
    for i, p in enumerate(parents):
        if p >= 0:
            children[p].append(i)
    order: list[int] = []

    def visit(i: int) -> None:
        order.append(i)
        for c in children[i]:
            visit(c)

    visit(0)
    return order


def read_bvh(path: str | Path, *, unit: str = "cm", up_axis: str = "y") -> BvhMotion:
    """Read a single-root BVH file (any channel order) into our convention (metres, z up, xyzw).

    `unit` and `up_axis` describe the file (BVH does not record them). Joints are returned in file order.
    """
    scale, C = _check_options(unit, up_axis)
    try:
        tokens = Path(path).read_text().split()
    except (OSError, UnicodeDecodeError) as e:
        raise BvhError(f"cannot read BVH file {path}: {e}") from None
    pos = 0

    def take() -> str:
        nonlocal pos
        if pos >= len(tokens):
            raise BvhError(f"{path}: unexpected end of file")
        pos += 1
        return tokens[pos - 1]

    def expect(word: str) -> None:
        got = take()
        if got != word:
            raise BvhError(f"{path}: expected {word!r}, found {got!r}")

    def numbers(n: int) -> list[float]:
        try:
            return [float(take()) for _ in range(n)]
        except ValueError:
            raise BvhError(f"{path}: expected {n} numbers near token {pos}") from None

    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []
    end_sites: dict[int, np.ndarray] = {}

    def joint(parent: int) -> None:
        index = len(names)
        names.append(take())
        parents.append(parent)
        expect("{")
        expect("OFFSET")
        offsets.append(numbers(3))
        expect("CHANNELS")
        try:
            n = int(take())
        except ValueError:
            raise BvhError(f"{path}: CHANNELS of {names[-1]} must give a count") from None
        channels.append([take() for _ in range(n)])
        while True:
            word = take()
            if word == "}":
                return
            if word == "JOINT":
                joint(index)
            elif word == "End":
                expect("Site")
                expect("{")
                expect("OFFSET")
                end_sites[index] = C.T @ np.array(numbers(3)) / scale
                expect("}")
            else:
                raise BvhError(f"{path}: unexpected {word!r} in joint {names[index]}")

    expect("HIERARCHY")
    expect("ROOT")
    joint(-1)
    expect("MOTION")
    expect("Frames:")
    try:
        n_frames = int(take())
    except ValueError:
        raise BvhError(f"{path}: 'Frames:' must give a count") from None
    expect("Frame")
    expect("Time:")
    frame_time_s = numbers(1)[0]
    if not frame_time_s > 0:
        raise BvhError(f"{path}: Frame Time must be > 0, got {frame_time_s}")
    width = sum(len(c) for c in channels)
    table = np.array(numbers(width * n_frames), dtype=float).reshape(n_frames, width)
    if pos != len(tokens):
        raise BvhError(f"{path}: {len(tokens) - pos} values after the {n_frames} frames it announces")

    # Channels in MOTION follow the order joints appear in HIERARCHY, which is file order here.
    j = len(names)
    root_bvh = np.zeros((n_frames, 3))
    rot_bvh = np.tile(np.eye(3), (n_frames, j, 1, 1))
    column = 0
    for i, chans in enumerate(channels):
        axes = ""
        angle_columns = []
        for name in chans:
            kind, axis = name[1:], name[0].upper()
            if kind == "position" and axis in "XYZ":
                if i == 0:
                    root_bvh[:, "XYZ".index(axis)] = table[:, column]
            elif kind == "rotation" and axis in "XYZ":
                axes += axis
                angle_columns.append(column)
            else:
                raise BvhError(f"{path}: unknown channel {name!r} of {names[i]}")
            column += 1
        if axes:  # channels listed left to right are applied intrinsically: R = R_1 R_2 R_3
            rot_bvh[:, i] = Rotation.from_euler(axes, table[:, angle_columns], degrees=True).as_matrix()

    rot = C.T @ rot_bvh @ C
    return BvhMotion(
        segments=tuple(names),
        parents=tuple(parents),
        offsets_m=np.array(offsets) @ C / scale,
        root_positions_m=root_bvh @ C / scale,
        rotations_xyzw=Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(n_frames, j, 4),
        rate_hz=1.0 / frame_time_s,
        end_sites_m=end_sites,
    )
