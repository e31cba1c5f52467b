"""The wire format: every message the daemon and its clients exchange, and the one place that checks them.

Frame layout (see PROTOCOL.md): a ZeroMQ multipart message ``[topic, payload]``. ``topic`` is ASCII/UTF-8
bytes (``b"frame"``, ``b"labels/<subject>"``, ``b"pose/<subject>"``, ``b"skeleton/<subject>"``,
``b"status"``) so subscribers can filter by prefix; ``payload`` is a msgpack map with ``"v": 1``.
Arrays travel as raw little-endian bytes (float32 coordinates, int32 indices): no pickle, no per-element
msgpack overhead, and any language can read them with one ``frombuffer``.

`decode` validates everything (types, shapes, version, topic against payload, size limits) and raises
`ProtocolError` whose ``reason`` is a short machine-readable string the daemon counts per reason, so a bad
message is reported and dropped, never fatal. Unknown keys are ignored: adding keys is how the protocol
grows without bumping ``v``.

Control requests/replies (REQ/REP) are plain msgpack maps; see `encode_request` and `encode_reply`.

Imports: stdlib, numpy and msgpack only (no zmq, no jax), so every tool can speak the protocol.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import msgpack
import numpy as np

VERSION = 1

#: Frames with more points are rejected ("too_many_points"); a capture volume never sees that many, and
#: a bound keeps one bad sender from stalling the daemon. Matches EngineConfig.max_points.
MAX_POINTS = 4096
#: Payloads larger than this are rejected before unpacking ("too_large") [bytes].
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024

TOPIC_FRAME = b"frame"
TOPIC_STATUS = b"status"
TOPIC_LABELS = b"labels/"
TOPIC_POSE = b"pose/"
TOPIC_SKELETON = b"skeleton/"

_F32 = np.dtype("<f4")
_I32 = np.dtype("<i4")


class ProtocolError(ValueError):
    """A message or request that does not follow the protocol.

    ``reason`` is short and machine-readable ("bad_msgpack", "missing_key:points", "bad_shape:labels",
    ...): the daemon counts rejections by it. The message text says what was expected.
    """

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


# ----------------------------------------------------------------------------------------------- messages
# eq=False: the fields hold numpy arrays, whose == is elementwise, so a generated __eq__ would raise.


@dataclasses.dataclass(frozen=True, eq=False)
class Frame:
    """One unordered point cloud from a capture system (source -> daemon), topic ``frame``."""

    stream: str
    frame: int
    t_ns: int
    points: np.ndarray  # (N, 3) float32 [m], NaN allowed (the engine drops and counts them)
    labels: list[str] | None = None  # N labels "Subject:Marker", "" = unlabeled; seed or correct


@dataclasses.dataclass(frozen=True, eq=False)
class Labels:
    """One subject's labeled markers for one processed frame, topic ``labels/<subject>``."""

    subject: str
    stream: str
    frame: int
    t_ns: int
    markers: list[str]  # M marker names, stable while the subject lives
    point_index: np.ndarray  # (M,) int32, index into that frame's points, -1 = not observed
    positions: np.ndarray  # (M, 3) float32 [m], observed positions, NaN where -1
    solved: bool  # whether the pose optimisation ran this frame
    predicted: np.ndarray | None = None  # (M, 3) float32 [m], model position of every marker
    iterations: int = 0  # Gauss-Newton iterations (0 when skipped)
    residual_m: float = math.nan  # RMS marker residual of the fit [m], NaN when skipped


@dataclasses.dataclass(frozen=True, eq=False)
class Pose:
    """One subject's skeleton pose for one processed frame, topic ``pose/<subject>``."""

    subject: str
    stream: str
    frame: int
    t_ns: int
    segments: list[str]  # S segment names (protocol.skeleton.SEGMENTS)
    parents: list[int]  # S parent indices, -1 for the root
    root_position: np.ndarray  # (3,) float32 [m], root segment origin in world
    rotations: np.ndarray  # (S, 4) float32 quaternions x,y,z,w: root in world, others relative to parent
    joint_angles: np.ndarray  # (S-1, 3) float32 [rad], protocol.skeleton.JOINT_ANGLE_CONVENTION


@dataclasses.dataclass(frozen=True, eq=False)
class Skeleton:
    """A subject's static description (calibration), topic ``skeleton/<subject>``.

    Published when the subject appears and on request, so a consumer that joins late can interpret the
    labels and pose messages.
    """

    subject: str
    stream: str
    segments: list[str]  # S segment names
    parents: list[int]  # S parent indices, -1 for the root
    markers: list[str]  # M marker names, same order as the labels message
    marker_segment: np.ndarray  # (M,) int32, segment each marker rides on
    marker_offsets: np.ndarray  # (M, 3) float32 [m], marker position in its segment's frame
    joint_offsets: np.ndarray  # (S, 3) float32 [m], segment origin in its parent's frame (root: zeros)
    has_skeleton: bool = True  # False while only labels exist (offsets zero); republished once calibrated


@dataclasses.dataclass(frozen=True, eq=False)
class Status:
    """The daemon's health, topic ``status``, published at least once a second (also the reply to the
    ``status`` control command, as a map with the same keys)."""

    t_ns: int  # wall-clock time of the report [ns since the epoch]
    frames_received: int  # frame messages received (valid or not)
    frames_processed: int  # frames run through the engine
    frames_dropped: int  # valid frames skipped because the daemon fell behind (it processes the newest)
    rejected: dict[str, int]  # frames rejected, by reason (bad message, out of order, ...)
    subjects: list[str]  # subjects currently tracked
    latency_ms: dict[str, float]  # processing time per frame [ms]: "p50", "p99", "max" (recent window)
    ready: bool = True  # warmed up and processing
    uptime_s: float = 0.0  # seconds since the daemon started
    catching_up: bool = False  # frames were dropped since the last status to catch up with the source
    points_received: int = 0  # points in processed frames
    points_invalid: int = 0  # NaN/inf points dropped by the engine
    points_labeled: int = 0  # points given a label
    points_merged: int = 0  # points left unlabeled as a repeat of another within the engine's merge radius

    def as_dict(self) -> dict[str, Any]:
        """The status as a plain map (the payload without "v"; also the ``status`` command's reply)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


Message = Frame | Labels | Pose | Skeleton | Status


# ----------------------------------------------------------------------------------------------- encoding


def _f32(array, shape: tuple[int, ...], name: str) -> bytes:
    a = np.asarray(array, dtype=_F32)
    if a.shape != shape:
        raise ProtocolError(f"bad_shape:{name}", f"expected {shape}, got {a.shape}")
    return a.tobytes()


def _i32(array, shape: tuple[int, ...], name: str) -> bytes:
    a = np.asarray(array)
    if a.shape != shape or not np.issubdtype(a.dtype, np.integer):
        raise ProtocolError(f"bad_shape:{name}", f"expected int {shape}, got {a.dtype} {a.shape}")
    return a.astype(_I32).tobytes()


def _pack(payload: dict) -> bytes:
    return msgpack.packb({"v": VERSION, **payload}, use_bin_type=True)


def encode(msg: Message) -> list[bytes]:
    """Message -> ``[topic, payload]`` ready for ``socket.send_multipart``.

    Raises ProtocolError (a ValueError) when an array has the wrong shape.
    """
    if isinstance(msg, Frame):
        points = np.asarray(msg.points, dtype=_F32)
        if points.size == 0:
            points = points.reshape(0, 3)  # an empty frame is valid: nobody in the volume
        n = len(points) if points.ndim == 2 else -1
        payload = {
            "stream": msg.stream,
            "frame": int(msg.frame),
            "t_ns": int(msg.t_ns),
            "points": _f32(points, (n, 3), "points"),
        }
        if msg.labels is not None:
            if len(msg.labels) != n:
                raise ProtocolError("bad_shape:labels", f"{len(msg.labels)} labels for {n} points")
            payload["labels"] = list(msg.labels)
        return [TOPIC_FRAME, _pack(payload)]
    if isinstance(msg, Labels):
        m = len(msg.markers)
        payload = {
            "subject": msg.subject,
            "stream": msg.stream,
            "frame": int(msg.frame),
            "t_ns": int(msg.t_ns),
            "markers": list(msg.markers),
            "point_index": _i32(msg.point_index, (m,), "point_index"),
            "positions": _f32(msg.positions, (m, 3), "positions"),
            "solved": bool(msg.solved),
            "iterations": int(msg.iterations),
            "residual_m": float(msg.residual_m),
        }
        if msg.predicted is not None:
            payload["predicted"] = _f32(msg.predicted, (m, 3), "predicted")
        return [TOPIC_LABELS + msg.subject.encode(), _pack(payload)]
    if isinstance(msg, Pose):
        s = len(msg.segments)
        payload = {
            "subject": msg.subject,
            "stream": msg.stream,
            "frame": int(msg.frame),
            "t_ns": int(msg.t_ns),
            "segments": list(msg.segments),
            "parents": [int(p) for p in msg.parents],
            "root_position": _f32(msg.root_position, (3,), "root_position"),
            "rotations": _f32(msg.rotations, (s, 4), "rotations"),
            "joint_angles": _f32(msg.joint_angles, (s - 1, 3), "joint_angles"),
        }
        return [TOPIC_POSE + msg.subject.encode(), _pack(payload)]
    if isinstance(msg, Skeleton):
        s, m = len(msg.segments), len(msg.markers)
        payload = {
            "subject": msg.subject,
            "stream": msg.stream,
            "segments": list(msg.segments),
            "parents": [int(p) for p in msg.parents],
            "markers": list(msg.markers),
            "marker_segment": _i32(msg.marker_segment, (m,), "marker_segment"),
            "marker_offsets": _f32(msg.marker_offsets, (m, 3), "marker_offsets"),
            "joint_offsets": _f32(msg.joint_offsets, (s, 3), "joint_offsets"),
            "has_skeleton": bool(msg.has_skeleton),
        }
        return [TOPIC_SKELETON + msg.subject.encode(), _pack(payload)]
    if isinstance(msg, Status):
        d = msg.as_dict()
        d["rejected"] = {str(k): int(v) for k, v in msg.rejected.items()}
        d["latency_ms"] = {str(k): float(v) for k, v in msg.latency_ms.items()}
        d["subjects"] = list(msg.subjects)
        return [TOPIC_STATUS, _pack(d)]
    raise TypeError(f"cannot encode {type(msg).__name__}; expected Frame, Labels, Pose, Skeleton or Status")


# ----------------------------------------------------------------------------------------------- decoding

_MISSING = object()


def _unpack(raw: bytes) -> dict:
    """msgpack bytes -> map, or ProtocolError. Never raises anything else."""
    if not isinstance(raw, (bytes, bytearray, memoryview)):
        raise ProtocolError("bad_parts", f"payload must be bytes, got {type(raw).__name__}")
    if len(raw) > MAX_PAYLOAD_BYTES:
        raise ProtocolError("too_large", f"{len(raw)} bytes > {MAX_PAYLOAD_BYTES}")
    try:
        # strict_map_key=False: keys are checked below; raw=False decodes str as UTF-8 (bin stays bytes).
        obj = msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as e:  # msgpack raises several unrelated types (ValueError, ExtraData, FormatError...)
        raise ProtocolError("bad_msgpack", str(e) or type(e).__name__) from None
    if not isinstance(obj, dict):
        raise ProtocolError("not_a_map", f"payload is a msgpack {type(obj).__name__}, expected a map")
    return obj


def _check_version(m: dict, required: bool = True) -> None:
    v = m.get("v", _MISSING)
    if v is _MISSING:
        if required:
            raise ProtocolError("missing_key:v", 'every payload carries "v": 1')
        return
    if type(v) is not int or v != VERSION:
        raise ProtocolError("bad_version", f"v={v!r}, this side speaks v={VERSION}")


def _key(m: dict, key: str, kind: type | tuple[type, ...], default=_MISSING):
    """m[key] checked against kind (bool is not an int here, an int is a valid float)."""
    value = m.get(key, _MISSING)
    if value is _MISSING or (value is None and default is not _MISSING):  # nil = absent for optional keys
        if default is _MISSING:
            raise ProtocolError(f"missing_key:{key}")
        return default
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if float in kinds:
        kinds = (*kinds, int)
    if (isinstance(value, bool) and bool not in kinds) or not isinstance(value, kinds):
        names = "/".join(k.__name__ for k in kinds)
        raise ProtocolError(f"bad_type:{key}", f"expected {names}, got {type(value).__name__}")
    return value


def _str_list(m: dict, key: str, default=_MISSING) -> list[str] | None:
    value = _key(m, key, list, default)
    if value is None:
        return None
    if not all(isinstance(x, str) for x in value):
        raise ProtocolError(f"bad_type:{key}", "expected a list of str")
    return value


def _int_list(m: dict, key: str) -> list[int]:
    value = _key(m, key, list)
    if not all(type(x) is int for x in value):
        raise ProtocolError(f"bad_type:{key}", "expected a list of int")
    return value


def _array(m: dict, key: str, dtype: np.dtype, cols: int | None, rows: int | None, default=_MISSING):
    """Raw little-endian bytes -> native array of shape (rows, cols) (or (rows,) when cols is None).

    rows=None accepts any count (a frame's N) but then the byte length must be a multiple of one row.
    The result is a fresh writable copy in native byte order.
    """
    raw = _key(m, key, bytes, default)
    if raw is None:
        return None
    row_bytes = dtype.itemsize * (cols or 1)
    if rows is None:
        if len(raw) % row_bytes:
            raise ProtocolError(f"bad_shape:{key}", f"{len(raw)} bytes is not a multiple of {row_bytes}")
        rows = len(raw) // row_bytes
    elif len(raw) != rows * row_bytes:
        raise ProtocolError(f"bad_shape:{key}", f"expected {rows * row_bytes} bytes, got {len(raw)}")
    a = np.frombuffer(raw, dtype=dtype).astype(dtype.newbyteorder("="))
    return a.reshape((rows, cols) if cols else (rows,))


def _check_parents(parents: list[int], n_segments: int) -> None:
    if len(parents) != n_segments:
        raise ProtocolError("bad_shape:parents", f"{len(parents)} parents for {n_segments} segments")
    if n_segments == 0 or not all(-1 <= p < i for i, p in enumerate(parents)) or parents[0] != -1:
        raise ProtocolError("bad_value:parents", "parents must precede children and the root must be -1")


def _decode_frame(m: dict, max_points: int) -> Frame:
    stream = _key(m, "stream", str, "default")
    frame = _key(m, "frame", int)
    t_ns = _key(m, "t_ns", int)
    raw = _key(m, "points", bytes)
    if len(raw) > 12 * max_points:
        raise ProtocolError("too_many_points", f"{len(raw) // 12} points > limit {max_points}")
    points = _array(m, "points", _F32, 3, None)
    labels = _str_list(m, "labels", None)
    if labels is not None and len(labels) != len(points):
        raise ProtocolError("bad_shape:labels", f"{len(labels)} labels for {len(points)} points")
    return Frame(stream=stream, frame=frame, t_ns=t_ns, points=points, labels=labels)


def _decode_labels(m: dict) -> Labels:
    markers = _str_list(m, "markers")
    n = len(markers)
    return Labels(
        subject=_key(m, "subject", str),
        stream=_key(m, "stream", str),
        frame=_key(m, "frame", int),
        t_ns=_key(m, "t_ns", int),
        markers=markers,
        point_index=_array(m, "point_index", _I32, None, n),
        positions=_array(m, "positions", _F32, 3, n),
        solved=_key(m, "solved", bool),
        predicted=_array(m, "predicted", _F32, 3, n, None),
        iterations=_key(m, "iterations", int, 0),
        residual_m=float(_key(m, "residual_m", float, math.nan)),
    )


def _decode_pose(m: dict) -> Pose:
    segments = _str_list(m, "segments")
    parents = _int_list(m, "parents")
    _check_parents(parents, len(segments))
    s = len(segments)
    return Pose(
        subject=_key(m, "subject", str),
        stream=_key(m, "stream", str, "default"),  # CONTRACT's pose has no stream; ours always sends it
        frame=_key(m, "frame", int),
        t_ns=_key(m, "t_ns", int),
        segments=segments,
        parents=parents,
        root_position=_array(m, "root_position", _F32, None, 3),
        rotations=_array(m, "rotations", _F32, 4, s),
        joint_angles=_array(m, "joint_angles", _F32, 3, s - 1),
    )


def _decode_skeleton(m: dict) -> Skeleton:
    segments = _str_list(m, "segments")
    parents = _int_list(m, "parents")
    _check_parents(parents, len(segments))
    markers = _str_list(m, "markers")
    marker_segment = _array(m, "marker_segment", _I32, None, len(markers))
    if np.any((marker_segment < 0) | (marker_segment >= len(segments))):
        raise ProtocolError("bad_value:marker_segment", f"segment indices must be in [0, {len(segments)})")
    return Skeleton(
        subject=_key(m, "subject", str),
        stream=_key(m, "stream", str, "default"),
        segments=segments,
        parents=parents,
        markers=markers,
        marker_segment=marker_segment,
        marker_offsets=_array(m, "marker_offsets", _F32, 3, len(markers)),
        joint_offsets=_array(m, "joint_offsets", _F32, 3, len(segments)),
        has_skeleton=_key(m, "has_skeleton", bool, True),
    )


def _decode_status(m: dict) -> Status:
    t_ns = _key(m, "t_ns", int)
    counters = {k: _key(m, k, int) for k in ("frames_received", "frames_processed", "frames_dropped")}
    rejected = _key(m, "rejected", dict)
    if not all(isinstance(k, str) and type(v) is int for k, v in rejected.items()):
        raise ProtocolError("bad_type:rejected", "expected a map str -> int")
    latency = _key(m, "latency_ms", dict)
    if not all(isinstance(k, str) and type(v) in (int, float) for k, v in latency.items()):
        raise ProtocolError("bad_type:latency_ms", "expected a map str -> float")
    return Status(
        t_ns=t_ns,
        **counters,
        rejected=rejected,
        subjects=_str_list(m, "subjects"),
        latency_ms={k: float(v) for k, v in latency.items()},
        ready=_key(m, "ready", bool, True),
        uptime_s=float(_key(m, "uptime_s", float, 0.0)),
        catching_up=_key(m, "catching_up", bool, False),
        points_received=_key(m, "points_received", int, 0),
        points_invalid=_key(m, "points_invalid", int, 0),
        points_labeled=_key(m, "points_labeled", int, 0),
        points_merged=_key(m, "points_merged", int, 0),
    )


_SUBJECT_TOPICS = {TOPIC_LABELS: _decode_labels, TOPIC_POSE: _decode_pose, TOPIC_SKELETON: _decode_skeleton}


def decode(parts: list[bytes], max_points: int = MAX_POINTS) -> Message:
    """``[topic, payload]`` -> Frame | Labels | Pose | Skeleton | Status, validated.

    Raises ProtocolError(reason) for anything that does not follow the protocol; never another exception,
    so a receiver needs one ``except ProtocolError`` to count and drop a bad message.
    """
    if not isinstance(parts, (list, tuple)) or len(parts) != 2:
        n = len(parts) if isinstance(parts, (list, tuple)) else type(parts).__name__
        raise ProtocolError("bad_parts", f"expected [topic, payload], got {n} parts")
    if not isinstance(parts[0], (bytes, bytearray, memoryview)):
        raise ProtocolError("bad_parts", "topic must be bytes")
    topic, payload = bytes(parts[0]), parts[1]
    if topic == TOPIC_FRAME:
        m = _unpack(payload)
        _check_version(m)
        return _decode_frame(m, max_points)
    if topic == TOPIC_STATUS:
        m = _unpack(payload)
        _check_version(m)
        return _decode_status(m)
    for prefix, decoder in _SUBJECT_TOPICS.items():
        if topic.startswith(prefix):
            m = _unpack(payload)
            _check_version(m)
            msg = decoder(m)
            if msg.subject.encode() != topic[len(prefix):] or not msg.subject:
                raise ProtocolError("topic_mismatch", f"topic {topic!r} carries subject {msg.subject!r}")
            return msg
    raise ProtocolError(
        "unknown_topic", f"{topic[:64]!r}; expected frame, status, labels/<subject>, pose/<subject>, skeleton/<subject>"
    )


# ------------------------------------------------------------------------------------------------ control


def _plain(obj):
    """msgpack default hook: numpy scalars and arrays become Python numbers and lists."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (tuple, set, frozenset)):
        return list(obj)
    raise TypeError(f"cannot send {type(obj).__name__} in a control message")


def encode_request(cmd: dict) -> bytes:
    """A control command map, e.g. ``{"cmd": "reset", "subject": "A"}`` -> bytes for a REQ socket."""
    if not isinstance(cmd, dict) or not isinstance(cmd.get("cmd"), str):
        raise ProtocolError("missing_key:cmd", 'a request is a map with a "cmd" string')
    return msgpack.packb({"v": VERSION, **cmd}, use_bin_type=True, default=_plain)


def decode_request(raw: bytes) -> dict:
    """Bytes from a REQ socket -> the command map (with "cmd": str). "v" is optional in requests (a bare
    ``{"cmd": "ping"}`` is valid, as in CONTRACT.md) but must be 1 when present."""
    m = _unpack(raw)
    _check_version(m, required=False)
    _key(m, "cmd", str)
    return m


def encode_reply(d: dict) -> bytes:
    """A reply map (``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``) -> bytes; adds "v": 1."""
    if not isinstance(d, dict) or not isinstance(d.get("ok"), bool):
        raise ProtocolError("missing_key:ok", 'a reply is a map with an "ok" bool')
    return msgpack.packb({"v": VERSION, **d}, use_bin_type=True, default=_plain)


def decode_reply(raw: bytes) -> dict:
    """Bytes from a REP socket -> the reply map (with "ok": bool and "v": 1)."""
    m = _unpack(raw)
    _check_version(m)
    _key(m, "ok", bool)
    return m
