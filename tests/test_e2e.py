"""End to end: the real daemon (`python -m service.cli serve`) in its own process on free loopback ports,
`mocap-replay` and `mocap-record` as processes too, and what the recorder wrote checked against the truth.

Tests reading ../shared/data fail when CI=true and the file is missing, and skip otherwise.
"""

import json
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import data_path
import zmq

from benchmarks.score import score
from clients.demo import (
    Children,
    finish_recorder,
    given_labels,
    latencies_ms,
    module_command,
    start_daemon,
    start_recorder,
)
from clients.record import load_labels
from clients.replay import control_request, load_truth
from protocol.skeleton import PARENTS, SEGMENTS
from recordings.bvh import read_bvh
from recordings.c3d import read_c3d

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    """One daemon for the module (the first start compiles the solve); tests reset it before use."""
    state = tmp_path_factory.mktemp("state")
    log = tmp_path_factory.mktemp("log") / "daemon.log"
    with Children() as children:
        eps = start_daemon(children, state, log)
        yield children, eps, log
        # the module's last act: the daemon stops cleanly on SIGINT (Children.__exit__ sends it)
    assert children.procs[0][1].returncode == 0, log.read_text()[-2000:]


def _request(eps, command: str) -> dict:
    context = zmq.Context()
    try:
        reply = control_request(context, eps.control, {"cmd": command}, timeout_s=10.0)
    finally:
        context.destroy(linger=0)
    assert reply is not None and reply["ok"], reply
    return reply


def _session(daemon, tmp_path, name, *replay_args, freeze: tuple[int, float] | None = None) -> tuple[str, str]:
    """Record while replaying once; returns what the recorder and the replay printed, and the daemon's
    status after (frames dropped, latency: the first things to read when a test below fails).

    freeze=(frames, seconds): once the daemon has processed that many frames, the replay is stopped
    (SIGSTOP) for that long, as a loaded machine or a stalled capture PC does; it then sends the frames it
    owes in a burst."""
    children, eps, _ = daemon
    _request(eps, "reset")
    before = _request(eps, "status")["frames_processed"]  # the daemon's counters run over the module
    recorder = start_recorder(children, eps, tmp_path / name, tmp_path / f"{name}_recorder.log")
    replay = subprocess.Popen(
        module_command("clients.replay", *replay_args, "--endpoint", eps.frames, "--control", eps.control,
                       "--quiet", "--truth-out", tmp_path / f"{name}_truth.npz"),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        if freeze is not None:
            deadline = time.monotonic() + 120
            while _request(eps, "status")["frames_processed"] < before + freeze[0] and time.monotonic() < deadline:
                time.sleep(0.02)
            replay.send_signal(signal.SIGSTOP)
            time.sleep(freeze[1])
            replay.send_signal(signal.SIGCONT)
        out, err = replay.communicate(timeout=600)
    finally:
        if replay.poll() is None:
            replay.kill()
    assert replay.returncode == 0, err
    assert out.startswith("mocap-replay: sent")
    recorded = finish_recorder(recorder)
    status = _request(eps, "status")
    return recorded, f"{out.strip()}; daemon status {status}"


def _answered_accuracy(result, given) -> tuple[float, float]:
    """(accuracy over the frames the daemon answered, fraction of scored frames answered).

    A frame the daemon dropped to keep up (fast playback on a shared 2-core machine) is no labeling error.
    """
    scored = np.arange(result.first_scored_frame, len(given))
    answered = np.array([given[f] is not None for f in scored])
    status = result.status[scored[answered]]
    return float(np.mean(status[status != 0] == 1)), float(answered.mean())


def test_real_recording_seeded(daemon, tmp_path):
    """cmu/07_01 (walking, 41 markers), labels in the first 2 s, played at its own rate (2.6 s)."""
    path = data_path("cmu/07_01.c3d")
    stdout, run = _session(daemon, tmp_path, "walk", path, "--seed-seconds", "2")
    assert "recorded" in stdout

    original = read_c3d(path)
    recorded = read_c3d(tmp_path / "walk.c3d", up_axis="z")
    assert recorded.rate_hz == pytest.approx(original.rate_hz)  # t_ns is the capture clock at any speed
    assert set(recorded.labels) <= set(original.labels)
    assert len(recorded.labels) >= 38, recorded.labels

    # Every recorded sample sits where the file has that label at that frame (rows start at frame 0).
    column = {label: i for i, label in enumerate(original.labels)}
    mine = recorded.points_m
    theirs = original.points_m[: len(mine), [column[label] for label in recorded.labels]]
    seen = np.all(np.isfinite(mine), axis=2)
    correct = np.linalg.norm(mine - theirs, axis=2) < 1e-4
    assert seen.sum() > 0.25 * np.isfinite(theirs[..., 0]).sum()
    assert correct[seen].mean() > 0.97, correct[seen].mean()

    seq, labeled = load_truth(tmp_path / "walk_truth.npz")
    assert labeled == 240
    given = given_labels(load_labels(tmp_path / "walk_labels.npz"), seq)
    result = score(seq, given, "seeded", labeled)
    accuracy, answered = _answered_accuracy(result, given)
    # A busy shared machine may drop frames to keep up (answered < 1): the labels of the frames it did
    # answer are what this checks.
    assert answered > 0.25 and accuracy > 0.9, (accuracy, answered, run)
    assert result.precision > 0.97

    motion = read_bvh(tmp_path / "walk_liu.bvh")
    assert motion.segments == SEGMENTS and motion.parents == PARENTS and motion.n_frames > 0
    assert np.all(np.isfinite(motion.rotations_xyzw))
    poses = [json.loads(line) for line in (tmp_path / "walk.ndjson").read_text().splitlines()]
    assert poses and {p["subject"] for p in poses} == {"liu"}


def test_synthetic_performer_seeded(daemon, tmp_path):
    """The built-in performer at L2 (occlusions, noise, ghosts), seeded: no data needed."""
    _, run = _session(daemon, tmp_path, "synth", "--duration", "6", "--seed", "3", "--seed-seconds", "2",
                      "--stamp-send-time")
    seq, labeled = load_truth(tmp_path / "synth_truth.npz")
    assert seq.level == "L2" and labeled == 240
    labels = load_labels(tmp_path / "synth_labels.npz")
    assert set(labels) == {"Performer"}
    given = given_labels(labels, seq)
    result = score(seq, given, "seeded", labeled)
    accuracy, answered = _answered_accuracy(result, given)
    # Most labels given are right and most markers are labeled; the engine's own tests and the
    # benchmarks hold it to the paper's figures, this checks the pipeline carries its answers intact.
    assert answered > 0.5 and accuracy > 0.5, (accuracy, answered, run)
    # Pipeline check on a shared, loaded machine (the daemon may drop frames under load); the labeling
    # quality itself is held to its figures by test_engine.py and measured in BENCHMARK.md.
    assert result.precision > 0.85 and result.ghost_rate < 0.25, (result.precision, result.ghost_rate, run)
    latency = latencies_ms(labels)  # send time stamped: receipt - send is end to end, and positive
    assert len(latency) and latency.min() > 0

    recorded = read_c3d(tmp_path / "synth.c3d", up_axis="z")
    assert len(recorded.labels) == len(seq.marker_names)
    assert set(recorded.labels) == set(seq.marker_names)
    motion = read_bvh(tmp_path / "synth_Performer.bvh")
    assert motion.segments == SEGMENTS


def test_synthetic_performer_found_from_its_t_pose(daemon, tmp_path):
    """Seedless: nothing is given; the engine must find the performer standing in a T-pose."""
    _, run = _session(daemon, tmp_path, "tpose", "--duration", "6", "--seed", "4")
    seq, labeled = load_truth(tmp_path / "tpose_truth.npz")
    assert labeled == 0
    labels = load_labels(tmp_path / "tpose_labels.npz") if (tmp_path / "tpose_labels.npz").is_file() else {}
    assert labels, f"no subject was created from the T-pose ({run})"
    given = given_labels(labels, seq)
    result = score(seq, given, "tpose", int(seq.rate_hz))  # from 1 s (the engine's tests hold frame 0)
    accuracy, answered = _answered_accuracy(result, given)
    # Frames a loaded machine made the daemon drop are no labeling error (see _answered_accuracy); the
    # engine's own tests hold the T-pose start to >= 95 % in process.
    assert answered > 0.5 and accuracy > 0.8 and result.precision > 0.9, (accuracy, answered, result.precision, run)


def test_a_replay_that_stalls_then_bursts_is_tracked_through(daemon, tmp_path):
    """The replay is frozen for 2 s mid-session, then sends the ~240 frames it owes at once (what a CI
    machine's hiccup did to the T-pose test above). The daemon works through the burst, thinned if it
    must, so the tracker follows the motion: the frames after it are answered and labeled. Before the
    catch-up was thinned rather than skipped to the newest frame, this lost the performer for good
    (answered 40 %, accuracy 45 %)."""
    _, run = _session(daemon, tmp_path, "stall", "--duration", "6", "--seed", "4", freeze=(200, 2.0))
    late_ms = float(re.search(r"max ([0-9.]+) ms", run).group(1))
    assert late_ms > 1500, run  # the freeze happened mid-stream
    seq, _ = load_truth(tmp_path / "stall_truth.npz")
    labels = load_labels(tmp_path / "stall_labels.npz") if (tmp_path / "stall_labels.npz").is_file() else {}
    given = given_labels(labels, seq)
    result = score(seq, given, "tpose", int(seq.rate_hz))
    accuracy, answered = _answered_accuracy(result, given)
    last_second = [given[f] is not None for f in range(seq.n_frames - int(seq.rate_hz), seq.n_frames)]
    assert np.mean(last_second) > 0.9 and answered > 0.5 and accuracy > 0.8, (accuracy, answered, run)


def test_demo_runs(tmp_path):
    """`python -m clients.demo` (seeded, short) runs to its report and leaves its outputs."""
    out = tmp_path / "demo"
    result = subprocess.run(
        module_command("clients.demo", "--seeded", "--duration", "5", "--quiet", "--out", out),
        cwd=REPO, capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "accuracy" in result.stdout and "end-to-end latency" in result.stdout
    assert (out / "demo_seeded.c3d").is_file() and (out / "daemon.log").is_file()
