"""protocol.messages: every message survives a round trip bit for bit, and every malformed input is
rejected with its reason (never another exception)."""

import math

import msgpack
import numpy as np
import pytest

from protocol import messages as pm
from protocol.skeleton import PARENTS, SEGMENTS

RNG = np.random.default_rng(0)


def _frame(n=5, labels=True) -> pm.Frame:
    points = RNG.normal(size=(n, 3)).astype(np.float32)
    points[1] = np.nan  # NaN points are allowed on the wire
    return pm.Frame("volA", 42, 1_700_000_000_123_456_789, points, [f"S:M{i}" if i % 2 else "" for i in range(n)] if labels else None)


def _labels() -> pm.Labels:
    positions = RNG.normal(size=(3, 3)).astype(np.float32)
    positions[2] = np.nan
    return pm.Labels(
        "Alice", "volA", 7, 123, ["LFHD", "RFHD", "C7"], np.array([4, 0, -1], np.int32), positions, True,
        predicted=RNG.normal(size=(3, 3)).astype(np.float32), iterations=5, residual_m=0.0021,
    )


def _pose() -> pm.Pose:
    rotations = RNG.normal(size=(14, 4)).astype(np.float32)
    return pm.Pose(
        "Alice", "volA", 7, 123, list(SEGMENTS), list(PARENTS), np.array([1.0, 2.0, 0.9], np.float32),
        rotations / np.linalg.norm(rotations, axis=1, keepdims=True), RNG.normal(size=(13, 3)).astype(np.float32),
    )


def _skeleton() -> pm.Skeleton:
    return pm.Skeleton(
        "Alice", "volA", list(SEGMENTS), list(PARENTS), ["LFHD", "C7"], np.array([3, 2], np.int32),
        np.array([[0.1, 0.05, 0.1], [0.0, 0.0, 0.3]], np.float32), RNG.normal(size=(14, 3)).astype(np.float32),
        has_skeleton=False,
    )


def _status() -> pm.Status:
    return pm.Status(
        t_ns=5, frames_received=10, frames_processed=8, frames_dropped=1, rejected={"bad_msgpack": 1},
        subjects=["Alice"], latency_ms={"p50": 1.5, "p99": 3.0, "max": 4.25}, ready=True, uptime_s=12.5,
        catching_up=True, points_received=400, points_invalid=3, points_labeled=380, points_merged=2,
    )


def _same(a, b) -> None:
    """Field-by-field equality, arrays compared bit for bit (NaN == NaN)."""
    assert type(a) is type(b)
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray) and y.dtype == x.dtype and y.shape == x.shape, name
            np.testing.assert_array_equal(x, y, err_msg=name)
        elif isinstance(x, float) and math.isnan(x):
            assert math.isnan(y), name
        else:
            assert x == y, name


@pytest.mark.parametrize("make", [_frame, lambda: _frame(labels=False), _labels, _pose, _skeleton, _status])
def test_round_trip(make):
    msg = make()
    parts = pm.encode(msg)
    assert len(parts) == 2 and all(isinstance(p, bytes) for p in parts)
    _same(msg, pm.decode(parts))


def test_topics_and_wire_layout():
    assert pm.encode(_frame())[0] == b"frame"
    assert pm.encode(_labels())[0] == b"labels/Alice"
    assert pm.encode(_pose())[0] == b"pose/Alice"
    assert pm.encode(_skeleton())[0] == b"skeleton/Alice"
    assert pm.encode(_status())[0] == b"status"
    # Arrays are raw little-endian bytes, readable without this module.
    frame = _frame()
    payload = msgpack.unpackb(pm.encode(frame)[1])
    assert payload["v"] == 1
    np.testing.assert_array_equal(np.frombuffer(payload["points"], "<f4").reshape(-1, 3), frame.points)
    payload = msgpack.unpackb(pm.encode(_labels())[1])
    assert np.frombuffer(payload["point_index"], "<i4").tolist() == [4, 0, -1]


def test_decoded_arrays_are_writable_native_copies():
    frame = pm.decode(pm.encode(_frame()))
    assert frame.points.flags.writeable and frame.points.dtype == np.float32
    frame.points[0] = 0.0


def test_empty_frame_and_contract_minimal_frame():
    empty = pm.decode(pm.encode(pm.Frame("default", 0, 0, np.zeros((0, 3)))))
    assert empty.points.shape == (0, 3)
    # A frame exactly as CONTRACT.md lists it, built by hand by a foreign tool: "stream" is optional.
    raw = msgpack.packb({"v": 1, "frame": 3, "t_ns": 9, "points": np.ones((2, 3), "<f4").tobytes()})
    frame = pm.decode([b"frame", raw])
    assert frame.stream == "default" and frame.frame == 3 and frame.points.shape == (2, 3)


def test_unknown_keys_are_ignored():
    """New keys are how the protocol grows without a version bump."""
    payload = msgpack.unpackb(pm.encode(_frame())[1])
    payload["future_key"] = [1, 2]
    assert pm.decode([b"frame", msgpack.packb(payload)]).frame == 42


def _frame_payload(**changes) -> bytes:
    payload = msgpack.unpackb(pm.encode(_frame())[1])
    for key, value in changes.items():
        if value is KeyError:
            del payload[key]
        else:
            payload[key] = value
    return msgpack.packb(payload)


@pytest.mark.parametrize(
    "parts, reason",
    [
        ([b"frame", b"\xc1"], "bad_msgpack"),  # 0xc1 is never used in msgpack
        ([b"frame", b"\x93\x01"], "bad_msgpack"),  # truncated array
        ([b"frame", msgpack.packb({"v": 1}) + b"\x01"], "bad_msgpack"),  # trailing bytes
        ([b"frame", msgpack.packb([1, 2, 3])], "not_a_map"),
        ([b"frame", msgpack.packb("hello")], "not_a_map"),
        ([b"frame", _frame_payload(v=2)], "bad_version"),
        ([b"frame", _frame_payload(v="1")], "bad_version"),
        ([b"frame", _frame_payload(v=KeyError)], "missing_key:v"),
        ([b"frame", _frame_payload(points=KeyError)], "missing_key:points"),
        ([b"frame", _frame_payload(frame=KeyError)], "missing_key:frame"),
        ([b"frame", _frame_payload(t_ns=KeyError)], "missing_key:t_ns"),
        ([b"frame", _frame_payload(frame="42")], "bad_type:frame"),
        ([b"frame", _frame_payload(frame=4.2)], "bad_type:frame"),
        ([b"frame", _frame_payload(frame=True)], "bad_type:frame"),
        ([b"frame", _frame_payload(stream=3)], "bad_type:stream"),
        ([b"frame", _frame_payload(points=[[0.0, 0.0, 0.0]])], "bad_type:points"),
        ([b"frame", _frame_payload(labels="S:M")], "bad_type:labels"),
        ([b"frame", _frame_payload(labels=[1, 2, 3, 4, 5])], "bad_type:labels"),
        ([b"frame", _frame_payload(points=b"\x00" * 13)], "bad_shape:points"),
        ([b"frame", _frame_payload(labels=["a"] * 4)], "bad_shape:labels"),
        ([b"frame", _frame_payload(points=b"\x00" * 12 * (pm.MAX_POINTS + 1), labels=None)], "too_many_points"),
        ([b"frames", _frame_payload()], "unknown_topic"),
        ([b"labels/Alice", _frame_payload()], "missing_key:markers"),
        ([b"labels/Bob", pm.encode(_labels())[1]], "topic_mismatch"),
        ([b"pose/Bob", pm.encode(_pose())[1]], "topic_mismatch"),
        ([b"skeleton/", pm.encode(_skeleton())[1]], "topic_mismatch"),
        ([b"status", pm.encode(_pose())[1]], "missing_key:frames_received"),
        ([b"frame"], "bad_parts"),
        ([b"frame", b"", b""], "bad_parts"),
        (["frame", _frame_payload()], "bad_parts"),
        ([b"frame", b"\x00" * (pm.MAX_PAYLOAD_BYTES + 1)], "too_large"),
    ],
)
def test_malformed_frames_are_rejected_with_reason(parts, reason):
    with pytest.raises(pm.ProtocolError) as info:
        pm.decode(parts)
    assert info.value.reason == reason


def test_labels_none_is_accepted_as_absent():
    assert pm.decode([b"frame", _frame_payload(labels=None)]).labels is None


def test_max_points_is_configurable():
    parts = pm.encode(_frame(n=10))
    assert len(pm.decode(parts, max_points=10).points) == 10
    with pytest.raises(pm.ProtocolError, match="too_many_points"):
        pm.decode(parts, max_points=9)


def _replace(parts, **changes) -> list[bytes]:
    payload = msgpack.unpackb(parts[1])
    payload.update(changes)
    return [parts[0], msgpack.packb(payload)]


@pytest.mark.parametrize(
    "parts, reason",
    [
        (_replace(pm.encode(_labels()), point_index=b"\x00" * 8), "bad_shape:point_index"),
        (_replace(pm.encode(_labels()), positions=b"\x00" * 12), "bad_shape:positions"),
        (_replace(pm.encode(_labels()), predicted=b"\x00" * 12), "bad_shape:predicted"),
        (_replace(pm.encode(_labels()), solved=1), "bad_type:solved"),
        (_replace(pm.encode(_pose()), rotations=b"\x00" * 16 * 13), "bad_shape:rotations"),
        (_replace(pm.encode(_pose()), joint_angles=b"\x00" * 12 * 14), "bad_shape:joint_angles"),
        (_replace(pm.encode(_pose()), root_position=b"\x00" * 8), "bad_shape:root_position"),
        (_replace(pm.encode(_pose()), parents=[-1] * 13), "bad_shape:parents"),
        (_replace(pm.encode(_pose()), parents=[-1, 2] + list(PARENTS[2:])), "bad_value:parents"),
        (_replace(pm.encode(_skeleton()), marker_segment=np.array([0, 14], "<i4").tobytes()), "bad_value:marker_segment"),
        (_replace(pm.encode(_skeleton()), joint_offsets=b"\x00" * 12), "bad_shape:joint_offsets"),
        (_replace(pm.encode(_status()), rejected={"x": "1"}), "bad_type:rejected"),
        (_replace(pm.encode(_status()), subjects="Alice"), "bad_type:subjects"),
    ],
)
def test_malformed_results_are_rejected_with_reason(parts, reason):
    with pytest.raises(pm.ProtocolError) as info:
        pm.decode(parts)
    assert info.value.reason == reason


def test_encode_checks_shapes():
    with pytest.raises(pm.ProtocolError, match="bad_shape:points"):
        pm.encode(pm.Frame("default", 0, 0, np.zeros((4, 2))))
    with pytest.raises(pm.ProtocolError, match="bad_shape:labels"):
        pm.encode(pm.Frame("default", 0, 0, np.zeros((4, 3)), ["a"]))
    with pytest.raises(TypeError):
        pm.encode({"frame": 1})


def test_control_round_trip_and_errors():
    assert pm.decode_request(pm.encode_request({"cmd": "reset", "subject": "A"})) == {"v": 1, "cmd": "reset", "subject": "A"}
    # A bare request from a foreign tool, without "v", is valid (CONTRACT.md's {"cmd": "ping"}).
    assert pm.decode_request(msgpack.packb({"cmd": "ping"}))["cmd"] == "ping"
    reply = pm.decode_reply(pm.encode_reply({"ok": True, "offsets": np.zeros((2, 3)), "n": np.int64(3)}))
    assert reply == {"ok": True, "v": 1, "offsets": [[0.0] * 3] * 2, "n": 3}
    for raw, reason in [
        (b"\xc1", "bad_msgpack"),
        (msgpack.packb(["ping"]), "not_a_map"),
        (msgpack.packb({"command": "ping"}), "missing_key:cmd"),
        (msgpack.packb({"cmd": 1}), "bad_type:cmd"),
        (msgpack.packb({"cmd": "ping", "v": 2}), "bad_version"),
    ]:
        with pytest.raises(pm.ProtocolError) as info:
            pm.decode_request(raw)
        assert info.value.reason == reason
    with pytest.raises(pm.ProtocolError, match="missing_key:ok"):
        pm.decode_reply(msgpack.packb({"v": 1}))
    with pytest.raises(pm.ProtocolError, match="missing_key:cmd"):
        pm.encode_request({"subject": "A"})


def test_decode_raises_only_protocol_error_on_random_damage():
    """The daemon needs one `except ProtocolError`: truncations, bit flips and random bytes of valid
    messages of every kind must never raise anything else."""
    rng = np.random.default_rng(1)
    originals = [pm.encode(make()) for make in (_frame, _labels, _pose, _skeleton, _status)]
    outcomes = {"ok": 0, "rejected": 0}
    for _ in range(3000):
        topic, payload = originals[rng.integers(len(originals))]
        data = bytearray(payload)
        kind = rng.integers(3)
        if kind == 0:
            data = data[: rng.integers(len(data))]
        elif kind == 1:
            for i in rng.integers(len(data), size=rng.integers(1, 4)):
                data[i] ^= 1 << int(rng.integers(8))
        else:
            data = bytearray(rng.bytes(int(rng.integers(1, 64))))
        try:
            pm.decode([topic, bytes(data)])
            outcomes["ok"] += 1
        except pm.ProtocolError:
            outcomes["rejected"] += 1
    assert outcomes["rejected"] > 1000  # the damage was real
