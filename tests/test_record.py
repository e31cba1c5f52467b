"""clients.record: from a stream of result messages published by the test (a fake daemon), the recorder
writes a labeled C3D, one BVH per subject, NDJSON poses and the labels file; it asks the control endpoint
for a skeleton it missed; it stops by --frames, --idle and --duration."""

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
from scipy.spatial.transform import Rotation

from clients.record import Recorder, bvh_motion, load_labels, pose_json, skeleton_from_reply
from protocol.messages import Labels, Pose, Skeleton, Status, decode, encode, encode_reply
from protocol.skeleton import PARENTS, SEGMENTS
from recordings.bvh import read_bvh
from recordings.c3d import read_c3d

REPO = Path(__file__).resolve().parents[1]
MARKERS = ["M0", "M1", "M2", "M3"]
RATE_HZ = 100.0
T0_NS = 1_700_000_000_000_000_000


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _skeleton(subject: str) -> Skeleton:
    joint_offsets = np.zeros((14, 3), np.float32)
    joint_offsets[1:] = np.arange(13 * 3).reshape(13, 3) * 0.01
    return Skeleton(subject=subject, stream="default", segments=list(SEGMENTS), parents=list(PARENTS),
                    markers=MARKERS, marker_segment=np.array([0, 3, 5, 10], np.int32),
                    marker_offsets=np.full((4, 3), 0.05, np.float32), joint_offsets=joint_offsets)


def _positions(subject: str, frame: int) -> np.ndarray:
    base = 0.0 if subject == "A" else 2.0
    return (np.arange(12, dtype=np.float32).reshape(4, 3) * 0.1 + base + frame * 0.001 + 0.5).astype(np.float32)


def _point_index(subject: str, frame: int) -> np.ndarray:
    index = np.arange(4, dtype=np.int32) + (4 if subject == "B" else 0)
    if frame % 3 == 0:
        index[1] = -1  # M1 unobserved every third frame
    return index


def _rotations(subject: str, frame: int) -> np.ndarray:
    seed = frame * 2 + (subject == "B")
    return Rotation.random(14, random_state=seed).as_quat().astype(np.float32)


def _results(subject: str, frame: int) -> list[list[bytes]]:
    index = _point_index(subject, frame)
    positions = _positions(subject, frame)
    positions[index < 0] = np.nan
    t_ns = T0_NS + round(frame * 1e9 / RATE_HZ)
    rotations = _rotations(subject, frame)
    labels = Labels(subject=subject, stream="default", frame=frame, t_ns=t_ns, markers=MARKERS,
                    point_index=index, positions=positions, solved=True)
    pose = Pose(subject=subject, stream="default", frame=frame, t_ns=t_ns, segments=list(SEGMENTS),
                parents=list(PARENTS), root_position=np.array([frame * 0.01, 0, 1], np.float32),
                rotations=rotations, joint_angles=np.zeros((13, 3), np.float32))
    return [encode(labels), encode(pose)]


class FakeDaemon:
    """An XPUB results socket (so the test knows when the recorder subscribed) and a control REP."""

    def __init__(self):
        self.ctx = zmq.Context()
        self.publish_ep = f"tcp://127.0.0.1:{free_port()}"
        self.control_ep = f"tcp://127.0.0.1:{free_port()}"
        self.pub = self.ctx.socket(zmq.XPUB)
        self.pub.bind(self.publish_ep)
        self.rep = self.ctx.socket(zmq.REP)
        self.rep.bind(self.control_ep)
        self.requests = []

    def wait_for_subscriber(self, timeout_s=60.0):
        assert self.pub.poll(int(timeout_s * 1000)), "the recorder never subscribed"
        time.sleep(0.05)  # its other topic subscriptions follow the first at once
        while self.pub.poll(0):
            self.pub.recv()

    def serve(self):
        """Answer waiting control requests: a skeleton command gets the description inline, and the
        skeleton message is republished, as the real daemon does."""
        while self.rep.poll(0):
            request = msgpack.unpackb(self.rep.recv())
            self.requests.append(request)
            skeleton = _skeleton(request["subject"])
            description = {"subject": skeleton.subject, "stream": "default", "segments": skeleton.segments,
                           "parents": skeleton.parents, "markers": skeleton.markers,
                           "marker_segment": skeleton.marker_segment.tolist(),
                           "marker_offsets_m": skeleton.marker_offsets.tolist(),
                           "joint_offsets_m": skeleton.joint_offsets.tolist()}
            self.rep.send(encode_reply({"ok": True, "skeleton": description}))
            self.pub.send_multipart(encode(skeleton))

    def close(self):
        self.ctx.destroy(linger=0)


@pytest.fixture
def daemon():
    d = FakeDaemon()
    yield d
    d.close()


def _record(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "clients.record", *map(str, args)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_records_a_stream_to_c3d_bvh_and_ndjson(tmp_path, daemon):
    """Subject A from frame 0 (its skeleton only on request), B in frames 10-19 (skeleton published),
    frame 25 never answered; --frames 40 stops after frames 0..40."""
    out = tmp_path / "take"
    proc = _record("--endpoint", daemon.publish_ep, "--control", daemon.control_ep, "-o", out,
                   "--frames", "40", "--quiet")
    try:
        daemon.wait_for_subscriber()
        daemon.pub.send_multipart(encode(_skeleton("B")))
        daemon.pub.send_multipart([b"labels/A", b"\x93garbage"])  # malformed: counted, not fatal
        for frame in range(60):
            if frame != 25:
                for subject in ["A"] + (["B"] if 10 <= frame < 20 else []):
                    for parts in _results(subject, frame):
                        daemon.pub.send_multipart(parts)
            if frame % 10 == 0:
                daemon.pub.send_multipart(encode(Status(t_ns=time.time_ns(), frames_received=frame,
                                                        frames_processed=frame, frames_dropped=1, rejected={},
                                                        subjects=["A"], latency_ms={"p50": 1.0})))
            daemon.serve()
            time.sleep(0.01)
        deadline = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < deadline:
            daemon.serve()
            time.sleep(0.01)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    assert "recorded 40 frames of 2 subject(s) (A, B), stopped by frames" in stdout
    assert "1 malformed messages dropped" in stdout
    assert any(r == {"v": 1, "cmd": "skeleton", "subject": "A"} for r in daemon.requests)

    recording = read_c3d(tmp_path / "take.c3d", up_axis="z")
    assert recording.labels == ("A:M0", "A:M1", "A:M2", "A:M3", "B:M0", "B:M1", "B:M2", "B:M3")
    assert recording.n_frames == 41 and recording.rate_hz == pytest.approx(RATE_HZ)
    points = recording.points_m
    assert np.isnan(points[25]).all()
    for frame in (0, 1, 12, 40):
        for s, subject in enumerate("AB"):
            block = points[frame, 4 * s:4 * s + 4]
            if subject == "B" and not 10 <= frame < 20:
                assert np.isnan(block).all()
                continue
            expected = _positions(subject, frame).astype(float)
            expected[_point_index(subject, frame) < 0] = np.nan
            np.testing.assert_allclose(block, expected, atol=1e-5)

    motion = read_bvh(tmp_path / "take_A.bvh")
    assert motion.segments == SEGMENTS and motion.parents == PARENTS and motion.n_frames == 41
    np.testing.assert_allclose(motion.offsets_m, _skeleton("A").joint_offsets, atol=1e-6)
    for row, frame in [(0, 0), (24, 24), (25, 24), (40, 40)]:  # frame 25 holds frame 24's pose
        angle = (Rotation.from_quat(motion.rotations_xyzw[row]).inv()
                 * Rotation.from_quat(_rotations("A", frame))).magnitude()
        assert angle.max() < 1e-4
    assert read_bvh(tmp_path / "take_B.bvh").n_frames == 10

    lines = (tmp_path / "take.ndjson").read_text().splitlines()
    assert len(lines) == 40 + 10
    first = json.loads(lines[0])
    assert first["subject"] == "A" and first["frame"] == 0 and len(first["rotations_xyzw"]) == 14

    labels = load_labels(tmp_path / "take_labels.npz")
    assert set(labels) == {"A", "B"}
    assert labels["A"].frames.tolist() == [f for f in range(41) if f != 25]
    assert labels["B"].point_index[0].tolist() == [4, 5, 6, 7]
    assert labels["A"].point_index[0].tolist() == [0, -1, 2, 3]


def test_stops_when_the_stream_goes_idle(tmp_path, daemon):
    proc = _record("--endpoint", daemon.publish_ep, "--control", daemon.control_ep, "-o",
                   tmp_path / "idle.c3d", "--idle", "0.5", "--quiet")
    try:
        daemon.wait_for_subscriber()
        daemon.pub.send_multipart(encode(_skeleton("A")))
        for frame in range(5):
            for parts in _results("A", frame):
                daemon.pub.send_multipart(parts)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    assert "stopped by idle" in stdout
    assert read_c3d(tmp_path / "idle.c3d", up_axis="z").n_frames == 5
    assert (tmp_path / "idle_A.bvh").is_file()


def test_nothing_received_writes_nothing(tmp_path, daemon):
    proc = _record("--endpoint", daemon.publish_ep, "--control", daemon.control_ep, "-o",
                   tmp_path / "none", "--duration", "0.5", "--quiet")
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 1
    assert "no results arrived" in stderr and len(stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_bad_output_directory_is_one_sentence(tmp_path):
    proc = _record("-o", tmp_path / "no" / "such" / "dir" / "x")
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert "does not exist" in stderr and len(stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------- in process


def test_rate_inferred_from_t_ns_and_frame_gaps():
    rec = Recorder()
    for frame in (0, 1, 2, 5, 6):  # a gap of 3 frames is still one frame per 1 / 100 s
        for parts in _results("A", frame):
            rec.add(decode(parts), 0)
    assert rec.rate_hz() == pytest.approx(RATE_HZ)
    points, labels, first = rec.labeled_points()
    assert points.shape == (7, 4, 3) and first == 0 and labels == [f"A:{m}" for m in MARKERS]
    assert np.isnan(points[3:5]).all()


def test_bvh_not_written_without_skeleton(tmp_path):
    rec = Recorder()
    for parts in _results("A", 0):
        rec.add(decode(parts), 0)
    said = []
    written = rec.write(tmp_path / "x", say=said.append)
    assert [p.name for p in written] == ["x.c3d", "x_labels.npz"]
    assert "no skeleton description arrived for A" in said[0]
    rec.add(_skeleton("A"), 0)
    motion = bvh_motion(rec.subjects["A"], 100.0)
    assert motion.n_frames == 1 and set(motion.end_sites_m) == {3, 5, 7, 10, 13}
    np.testing.assert_allclose(motion.end_sites_m[3], [0.05] * 3, atol=1e-6)  # mean of its marker


def test_skeleton_from_reply_validates():
    s = _skeleton("A")
    description = {"subject": "A", "stream": "default", "segments": s.segments, "parents": s.parents,
                   "markers": s.markers, "marker_segment": s.marker_segment.tolist(),
                   "marker_offsets_m": s.marker_offsets.tolist(), "joint_offsets_m": s.joint_offsets.tolist()}
    assert skeleton_from_reply({"ok": True, "skeleton": description}).markers == MARKERS
    assert skeleton_from_reply({"ok": True, "skeleton": {**description, "marker_segment": [0, 99, 0, 0]}}) is None
    assert skeleton_from_reply({"ok": False, "error": "unknown subject"}) is None
    assert skeleton_from_reply(None) is None


def test_pose_json_is_plain_json():
    pose = decode(_results("A", 3)[1])
    line = json.loads(pose_json(pose, 123))
    assert line["frame"] == 3 and line["recv_ns"] == 123
    np.testing.assert_allclose(line["rotations_xyzw"], _rotations("A", 3), atol=1e-6)
