"""service.cli as a user runs it: subprocesses of `python -m service.cli` (the console script may not be
installed). `label` matches the in-process engine; bad flags and files get one line, no traceback; `serve`
stops cleanly on SIGINT/SIGTERM, saves its state and frees its ports."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zmq

from protocol import messages as pm

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 300  # a cold JAX compile on a loaded 2-core machine


def cli(*args, timeout=TIMEOUT_S) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    """One JAX compilation cache for the module's subprocesses (also keeps ~/.cache untouched)."""
    return tmp_path_factory.mktemp("jax-cache")


@pytest.fixture(scope="module")
def small_c3d(tmp_path_factory):
    """A 1.5 s synthetic performer written as C3D, and the performance."""
    from recordings.c3d import write_c3d
    from recordings.synthetic import perform

    performance = perform(seed=3, duration_s=1.5, rate_hz=120.0)
    path = tmp_path_factory.mktemp("c3d") / "performer.c3d"
    rec = performance.recording
    write_c3d(path, rec.points_m, rec.labels, rec.rate_hz)
    return path, performance


def assert_one_line_error(result: subprocess.CompletedProcess, *words: str, status: int = 2) -> None:
    assert result.returncode == status, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for word in words:
        assert word in lines[0], lines[0]


# ------------------------------------------------------------------------------------------------ label


def test_label_matches_the_in_process_engine(tmp_path, small_c3d, cache_dir):
    from recordings.c3d import read_c3d
    from service.config import ServiceConfig
    from service.offline import label_recording

    path, performance = small_c3d
    out = tmp_path / "labeled.c3d"
    result = cli("label", path, "-o", out, "--seed-frames", 30, "--cache-dir", cache_dir, "--no-progress")
    assert result.returncode == 0, result.stderr
    labeled = read_c3d(out)

    expected_m, expected_labels = label_recording(read_c3d(path), ServiceConfig(cache_dir=""), seed_frames=30,
                                                  progress=False)
    assert list(labeled.labels) == expected_labels
    # Identical up to the file's float32-in-millimetres storage.
    np.testing.assert_array_equal(np.isnan(labeled.points_m), np.isnan(expected_m))
    np.testing.assert_allclose(labeled.points_m, expected_m, atol=1e-6, equal_nan=True)

    # Known answer: the labeled output puts each marker's true trajectory under its name.
    truth = dict(zip(performance.recording.labels, np.moveaxis(performance.recording.points_m, 1, 0)))
    assert sorted(labeled.labels) == sorted(truth)
    correct = [np.nanmax(np.abs(labeled.points_m[30:, i] - truth[name][30:])) < 1e-5
               for i, name in enumerate(labeled.labels)]
    assert np.mean(correct) > 0.95
    assert np.mean(np.isfinite(labeled.points_m[30:, :, 0])) > 0.97


def test_label_a_real_recording_from_seeds(tmp_path, cache_dir):
    """HDM05 (Vicon, mm, "Daniel:" prefixes, 3 unnamed *N points): seeded for 1 s, every marker's output
    trajectory is that marker's true trajectory."""
    from recordings.c3d import read_c3d
    from tests.conftest import data_path

    path = data_path("hdm05/HDM_dg_06-03_03_120.c3d")
    out = tmp_path / "labeled.c3d"
    result = cli("label", path, "-o", out, "--seed-frames", 120, "--cache-dir", cache_dir, "--no-progress")
    assert result.returncode == 0, result.stderr
    source, labeled = read_c3d(path), read_c3d(out)
    truth = {label: source.points_m[:, i] for i, label in enumerate(source.labels)}
    assert len(labeled.labels) == 41 and set(labeled.labels) <= set(truth)
    right = [np.nanmax(np.abs(labeled.points_m[120:, i] - truth[label][120:])) < 1e-4
             for i, label in enumerate(labeled.labels)]
    assert np.mean(right) > 0.95


def test_label_bad_input_file(tmp_path):
    assert_one_line_error(cli("label", tmp_path / "missing.c3d", "-o", tmp_path / "out.c3d"), "missing.c3d")
    text = tmp_path / "notes.c3d"
    text.write_text("this is not a C3D file\n" * 50)
    assert_one_line_error(cli("label", text, "-o", tmp_path / "out.c3d"), "notes.c3d")
    assert not (tmp_path / "out.c3d").exists()


def test_label_finds_no_subject(tmp_path, cache_dir):
    """Points that are no person in a T-pose, and no seed labels: one sentence, status 1, no file (an
    empty C3D would pass for a result)."""
    from recordings.c3d import write_c3d

    rng = np.random.default_rng(0)
    path, out = tmp_path / "scatter.c3d", tmp_path / "out.c3d"
    write_c3d(path, rng.uniform(0.0, 3.0, (40, 30, 3)), [f"*{i}" for i in range(30)], 100.0)
    assert_one_line_error(cli("label", path, "-o", out, "--cache-dir", cache_dir, "--no-progress"),
                          "no subject found", "T-pose", status=1)
    assert_one_line_error(cli("label", path, "-o", out, "--seed-frames", 10, "--cache-dir", cache_dir,
                              "--no-progress"), "no subject found", "name no marker", status=1)
    assert not out.exists()


def test_label_bad_output_directory(tmp_path, small_c3d):
    path, _ = small_c3d
    assert_one_line_error(cli("label", path, "-o", tmp_path / "no" / "such" / "dir.c3d"), "does not exist")


@pytest.mark.parametrize(
    "args, words",
    [
        (["serve", "--bogus"], ["unrecognized arguments", "--bogus"]),
        (["label", "x.c3d"], ["-o"]),
        (["label", "x.c3d", "-o", "y.c3d", "--seed-frames", "many"], ["--seed-frames", "many"]),
        (["serve", "--max-skip-frames", "-1"], ["max_skip_frames"]),
        (["serve", "--busy-poll", "-0.5"], ["busy_poll_s"]),
        (["serve", "--busy-poll", "often"], ["--busy-poll", "often"]),
        (["serve", "--log-level", "LOUD"], ["--log-level"]),
        (["dance"], ["dance"]),
        ([], ["required"]),
    ],
)
def test_bad_flags_get_one_line(args, words):
    assert_one_line_error(cli(*args, timeout=60), *words)


@pytest.mark.parametrize("command", ["serve", "label"])
def test_an_unusable_cache_directory_gets_one_line(tmp_path, small_c3d, command):
    blocker = tmp_path / "file"
    blocker.write_text("")  # a file where the cache directory's parent should be
    args = ["label", small_c3d[0], "-o", tmp_path / "out.c3d"] if command == "label" else ["serve"]
    assert_one_line_error(cli(*args, "--cache-dir", blocker / "cache", timeout=60), "cache directory", "cache")


def test_bad_config_file(tmp_path):
    assert_one_line_error(cli("serve", "--config", tmp_path / "none.toml"), "does not exist")
    bad = tmp_path / "bad.toml"
    bad.write_text("max_queue_frames = [\n")
    assert_one_line_error(cli("serve", "--config", bad), "not valid TOML")
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("colour = 'blue'\n")
    assert_one_line_error(cli("serve", "--config", unknown), "colour", "valid keys")


# ------------------------------------------------------------------------------------------------ serve


def free_ports(n: int) -> list[int]:
    """Ports the OS reports free now (a tiny race with other processes, acceptable in a test)."""
    sockets = [socket.socket() for _ in range(n)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def ping(endpoint: str, timeout_s: float) -> dict:
    ctx = zmq.Context.instance()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
    req.connect(endpoint)
    try:
        req.send(pm.encode_request({"cmd": "ping"}))
        return pm.decode_reply(req.recv())
    finally:
        req.close()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_serve_stops_cleanly_on_signal(tmp_path, cache_dir, signum):
    ports = free_ports(3)
    endpoints = [f"tcp://127.0.0.1:{p}" for p in ports]
    state = tmp_path / "state"
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--frames", endpoints[0], "--publish", endpoints[1],
         "--control", endpoints[2], "--state-dir", state, "--cache-dir", cache_dir],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        reply = ping(endpoints[2], TIMEOUT_S)  # answered only once warmed up
        assert reply["ok"] is True and reply["ready"] is True and reply["v"] == 1
        proc.send_signal(signum)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr and "ready" in stderr and "stopped" in stderr
    assert state.is_dir()
    for port in ports:
        with socket.socket() as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # ignores TIME_WAIT, not a listener
            s.bind(("127.0.0.1", port))


def test_serve_port_in_use_is_one_line(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        endpoint = f"tcp://127.0.0.1:{taken.getsockname()[1]}"
        result = cli("serve", "--frames", endpoint, "--publish", "tcp://127.0.0.1:*", "--control",
                     "tcp://127.0.0.1:*", "--state-dir", tmp_path, "--cache-dir", "", timeout=120)
    assert_one_line_error(result, "frames endpoint", status=1)
