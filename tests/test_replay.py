"""clients.replay: drift-free pacing, labels stripped/kept/seeded, NaN removed, and the CLI against a fake
daemon (a SUB socket and a REP control socket bound by the test)."""

import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq

from clients.replay import Pacer, Plan, frame_message, load_truth, save_truth, stream, ReplayStats
from protocol.messages import Frame, decode, encode_reply
from recordings.c3d import read_c3d, write_c3d
from recordings.corruption import CorruptedSequence

REPO = Path(__file__).resolve().parents[1]


def _sequence(n_frames=20, n_points=5, seed=0) -> CorruptedSequence:
    rng = np.random.default_rng(seed)
    points = [rng.normal(size=(n_points, 3)) for _ in range(n_frames)]
    truth = [rng.permutation(n_points) - 1 for _ in range(n_frames)]  # one ghost (-1) per frame
    names = tuple(f"S:M{i}" for i in range(n_points - 1))
    return CorruptedSequence(points, truth, names, rate_hz=100.0)


class FakeClock:
    """Virtual time: sleeping advances it, and each send costs `cost_s` (one send costs `slow_s`)."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t

    def sleep(self, seconds):
        assert seconds > 0
        self.t += seconds


def test_pacer_absolute_schedule_catches_up_after_a_hiccup():
    """Frame 10's send takes 5 periods: frames 11-15 leave late, then the stream is back on its slots, so
    the whole run lasts exactly (n - 1) periods (a sleep(period) loop would last 5 periods longer)."""
    clock = FakeClock()
    period = 0.01
    sent_at = []

    def send(parts):
        sent_at.append(clock.t)
        clock.t += 5 * period if len(sent_at) == 11 else 0.3 * period

    stats = stream(send, Plan(seq=_sequence(100), rate_hz=100.0), clock=clock, sleep=clock.sleep)
    assert stats.frames_sent == 100
    assert stats.frames_late == 5
    assert stats.max_late_s == pytest.approx(4 * period)
    assert stats.elapsed_s == pytest.approx(99 * period)
    assert stats.mean_rate_hz == pytest.approx(100.0)
    np.testing.assert_allclose(sent_at[20:], np.arange(20, 100) * period)  # back on schedule


def test_pacer_speed_scales_the_schedule():
    clock = FakeClock()
    sent_at = []
    stats = stream(lambda parts: sent_at.append(clock.t), Plan(seq=_sequence(10), rate_hz=100.0, speed=4.0),
                   clock=clock, sleep=clock.sleep)
    np.testing.assert_allclose(sent_at, np.arange(10) * 0.0025)
    assert stats.frames_late == 0


def test_real_clock_pacing_does_not_drift():
    """On the real clock, with one send stalling for 20 periods, the run still lasts ~(n - 1) periods:
    measured / expected stays near 1 (a sleep-per-frame pacer would give >= 1.1)."""
    n, rate = 200, 200.0
    sends = []

    def send(parts):
        sends.append(time.monotonic())
        if len(sends) == 50:
            time.sleep(20 / rate)

    stats = stream(send, Plan(seq=_sequence(n), rate_hz=rate))
    ratio = (sends[-1] - sends[0]) / ((n - 1) / rate)
    assert 0.99 < ratio < 1.08, ratio
    assert stats.frames_late >= 10


def test_pacer_returns_lateness():
    clock = FakeClock()
    pacer = Pacer(10.0, clock=clock, sleep=clock.sleep)
    assert pacer.wait(0) == 0.0
    clock.t = 0.35
    assert pacer.wait(2) == pytest.approx(0.15)  # due at 0.2
    assert pacer.wait(5) == 0.0 and clock.t == pytest.approx(0.5)


def test_labels_stripped_kept_and_seeded():
    seq = _sequence(10)
    stripped = [frame_message(Plan(seq=seq, rate_hz=100.0), k, 0) for k in range(10)]
    assert all(m.labels is None for m in stripped)
    seeded = [frame_message(Plan(seq=seq, rate_hz=100.0, labeled_frames=3), k, 0) for k in range(10)]
    assert [m.labels is not None for m in seeded] == [True] * 3 + [False] * 7
    for k in range(3):
        expected = ["" if t < 0 else f"S:M{t}" for t in seq.truth[k]]
        assert seeded[k].labels == expected
        np.testing.assert_array_equal(seeded[k].points, seq.points_m[k].astype(np.float32))
    assert seeded[4].frame == 4 and seeded[4].t_ns == 40_000_000  # k / rate on the capture clock


def test_nan_points_removed_with_their_labels():
    seq = _sequence(2, n_points=5)
    seq.points_m[0][1] = np.nan
    message = frame_message(Plan(seq=seq, rate_hz=100.0, labeled_frames=1), 0, 0)
    assert message.points.shape == (4, 3) and np.isfinite(message.points).all()
    expected = ["" if t < 0 else f"S:M{t}" for i, t in enumerate(seq.truth[0]) if i != 1]
    assert message.labels == expected


def test_dropped_frames_are_skipped_and_loop_keeps_numbering():
    seq = _sequence(4)
    seq.points_m[2] = None
    seq.truth[2] = None
    assert frame_message(Plan(seq=seq, rate_hz=100.0), 2, 0) is None
    looped = frame_message(Plan(seq=seq, rate_hz=100.0, loop=True), 5, 0)
    assert looped.frame == 5
    np.testing.assert_array_equal(looped.points, seq.points_m[1].astype(np.float32))


def test_truth_file_round_trip(tmp_path):
    seq = _sequence(6)
    seq.points_m[3] = None
    seq.truth[3] = None
    save_truth(tmp_path / "t.npz", Plan(seq=seq, rate_hz=100.0, labeled_frames=2), ReplayStats(frames_sent=5))
    back, labeled = load_truth(tmp_path / "t.npz")
    assert labeled == 2 and back.marker_names == seq.marker_names and back.rate_hz == 100.0
    assert back.points_m[3] is None and back.truth[3] is None
    for f in (0, 1, 2, 4, 5):
        np.testing.assert_array_equal(back.points_m[f], seq.points_m[f])
        np.testing.assert_array_equal(back.truth[f], seq.truth[f])


# ------------------------------------------------------------------------------- the CLI, fake daemon


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class FakeDaemon:
    """Binds a frames SUB and a control REP; answers ping (not ready for the first `not_ready` pings)."""

    def __init__(self, not_ready: int = 2):
        self.ctx = zmq.Context()
        self.frames_ep = f"tcp://127.0.0.1:{free_port()}"
        self.control_ep = f"tcp://127.0.0.1:{free_port()}"
        self.sub = self.ctx.socket(zmq.SUB)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"frame")
        self.sub.setsockopt(zmq.RCVHWM, 0)
        self.sub.bind(self.frames_ep)
        self.rep = self.ctx.socket(zmq.REP)
        self.rep.bind(self.control_ep)
        self.not_ready = not_ready
        self.frames: list[Frame] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        poller = zmq.Poller()
        poller.register(self.sub, zmq.POLLIN)
        poller.register(self.rep, zmq.POLLIN)
        while not self.stop.is_set():
            events = dict(poller.poll(50))
            if self.rep in events:
                request = msgpack.unpackb(self.rep.recv())
                assert request["cmd"] == "ping"
                self.not_ready -= 1
                self.rep.send(encode_reply({"ok": True, "ready": self.not_ready < 0}))
            if self.sub in events:
                self.frames.append(decode(self.sub.recv_multipart()))

    def close(self):
        self.stop.set()
        self.thread.join()
        self.ctx.destroy(linger=0)


@pytest.fixture
def daemon():
    d = FakeDaemon()
    yield d
    d.close()


def _c3d(tmp_path, n_frames=30) -> tuple[Path, np.ndarray]:
    rng = np.random.default_rng(1)
    points = rng.uniform(-1, 1, (n_frames, 6, 3)) + [0, 0, 1.5]
    points[5, 2] = np.nan  # a gap
    points[7:9, 4] = np.nan
    path = tmp_path / "small.c3d"
    write_c3d(path, points, [f"Bob:M{i}" for i in range(6)], 100.0)
    # as the replay reads it (random points have no floor, so the reader may pick another up axis)
    return path, read_c3d(path).points_m


def _run(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "clients.replay", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def _wait_for(daemon, n, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while len(daemon.frames) < n and time.monotonic() < deadline:
        time.sleep(0.02)


def test_cli_streams_every_frame_unlabeled_without_nan(tmp_path, daemon):
    path, points = _c3d(tmp_path)
    result = _run(path, "--endpoint", daemon.frames_ep, "--control", daemon.control_ep, "--speed", "4",
                  "--quiet", "--truth-out", tmp_path / "truth.npz")
    assert result.returncode == 0, result.stderr
    assert "sent 30 frames" in result.stdout and result.stderr == ""
    _wait_for(daemon, 30)
    frames = daemon.frames
    assert [f.frame for f in frames] == list(range(30))  # frame 0 not lost to the slow joiner
    assert all(f.labels is None for f in frames)
    assert [len(f.points) for f in frames][4:10] == [6, 5, 6, 5, 5, 6]
    assert all(np.isfinite(f.points).all() for f in frames)
    # capture clock: t_ns steps of 1 / 100 Hz whatever the speed
    assert np.diff([f.t_ns for f in frames]).tolist() == [10_000_000] * 29
    # shuffled, but the same cloud: each sent point is a point of the file
    orders = []
    for f in frames:
        d = np.linalg.norm(f.points[:, None] - points[f.frame][None].astype(np.float32), axis=2)
        assert np.nanmin(d, axis=1).max() < 1e-6
        orders.append(tuple(np.nanargmin(d, axis=1)))
    assert len(set(orders)) > 1
    seq, labeled = load_truth(tmp_path / "truth.npz")
    assert labeled == 0 and seq.n_frames == 30 and seq.marker_names == tuple(f"Bob:M{i}" for i in range(6))
    for f in frames:  # the truth file names each sent point
        np.testing.assert_allclose(seq.points_m[f.frame], f.points, atol=1e-6)
        np.testing.assert_allclose(points[f.frame][seq.truth[f.frame]], f.points, atol=1e-6)


def test_cli_keep_labels_and_seed_seconds(tmp_path, daemon):
    path, points = _c3d(tmp_path)
    result = _run(path, "--endpoint", daemon.frames_ep, "--control", daemon.control_ep, "--speed", "4",
                  "--quiet", "--seed-seconds", "0.1")
    assert result.returncode == 0, result.stderr
    _wait_for(daemon, 30)
    assert [f.labels is not None for f in daemon.frames] == [True] * 10 + [False] * 20
    for f in daemon.frames[:10]:
        for label, point in zip(f.labels, f.points):
            np.testing.assert_allclose(point, points[f.frame, int(label[len("Bob:M"):])], atol=1e-6)
    daemon.frames.clear()
    result = _run(path, "--endpoint", daemon.frames_ep, "--control", daemon.control_ep, "--speed", "4",
                  "--quiet", "--keep-labels")
    assert result.returncode == 0, result.stderr
    _wait_for(daemon, 30)
    assert len(daemon.frames) == 30 and all(f.labels is not None for f in daemon.frames)


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing.c3d"], "missing.c3d is not a file"),
        (["--level", "L9"], "invalid choice"),
        (["--speed", "0"], "expected a number > 0"),
        (["--rate", "abc"], "expected a number"),
    ],
)
def test_cli_bad_file_or_flag_is_one_sentence(tmp_path, args, message):
    result = _run(*args, "--no-wait", timeout=60)
    assert result.returncode == 2
    assert message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_cli_not_a_c3d(tmp_path):
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"not a c3d file at all" * 10)
    result = _run(bad, "--no-wait", timeout=60)
    assert result.returncode == 2 and result.stderr.startswith("mocap-replay: cannot read")
    assert len(result.stderr.strip().splitlines()) == 1


def test_cli_no_daemon_exits_1(tmp_path):
    path, _ = _c3d(tmp_path)
    result = _run(path, "--endpoint", f"tcp://127.0.0.1:{free_port()}", "--control",
                  f"tcp://127.0.0.1:{free_port()}", "--wait", "1.5", "--quiet", timeout=60)
    assert result.returncode == 1
    assert "no daemon answered ready" in result.stderr


def test_a_stress_level_corrupts_the_synthetic_performer_harder_than_l2():
    from clients.replay import load_sequence

    l2 = load_sequence(None, level="L2", seed=3, rate_hz=120.0, duration_s=10.0)
    lasting = load_sequence(None, level="L2-lasting-ghosts", seed=3, rate_hz=120.0, duration_s=10.0)
    assert lasting.level == "L2-lasting-ghosts"
    ghosts = [np.mean([np.count_nonzero(t < 0) for t in seq.truth if t is not None]) for seq in (l2, lasting)]
    assert ghosts[1] > 3 * ghosts[0]  # ghosts living 0.5 s instead of 0.08 s: about six times as many at a time
