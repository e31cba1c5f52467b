"""Speed figures that need the real programs (EVALUATION.md "Speed"): `mocap-service label` throughput,
daemon start-up (cold and warm compile cache), online latency through the daemon over loopback TCP, and
how many subjects, and how many markers per subject, the daemon sustains at 120 Hz.

Throughput, start-up and latency run `REPEATS` times (once with --quick) and are reported as medians,
because one run on a shared 2-core machine is at the mercy of whatever else it does at that moment. The
two scale scans run once: each already covers several hundred frames per row.

Each measurement launches the program as a subprocess (`python -m service.cli ...`, exactly what the
console script runs), on free loopback ports and a fresh state directory, and reads its peak resident
memory from `os.wait4` when it exits. The client side speaks the wire contract through
`protocol.messages`, as any third-party tool would. A measurement that fails is reported with its reason
in the table instead of stopping the benchmark.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zmq

from protocol import messages as pm
from recordings.corruption import corrupt
from recordings.recording import is_marker_label, split_label

REPO = Path(__file__).resolve().parents[1]
THROUGHPUT_FILE = "hdm05/HDM_mm_01-02_03_120.c3d"  # whole recording, 3990 frames, seeded from 2 s
QUICK_THROUGHPUT_FILE = "hdm05/HDM_dg_06-03_03_120.c3d"
LATENCY_FILE = "cmu/135_02.c3d"  # one 41-marker subject, replayed at L2 at its own rate
SCALE_FILE = "cmu/135_02.c3d"
SCALE_RATE_HZ = 120.0
SCALE_COUNTS = (1, 2, 3, 4, 6, 8, 10, 12, 16)  # on past 8 (the target) to show where it breaks
SCALE_SPACING_M = 4.0  # copies stand this far apart along x, so their clouds never mix
MARKER_COUNTS = (41, 62, 96)  # markers on one subject; 96 is EngineConfig.max_markers
MARKER_BASE_SET = "cmu41"  # the synthetic performer's marker set the larger sets are built from
# Where the extra markers sit: copy c of the base set is shifted by MARKER_COPY_SHIFTS_M[c - 1] in each
# marker's segment frame, so every copy is rigidly carried by the same segment as its original (a shift
# in world coordinates would not be, and would measure a mis-fitting skeleton instead of a large one).
MARKER_COPY_SHIFTS_M = ((0.03, 0.025, 0.02), (-0.025, -0.03, 0.025))
COST_S = 20.0  # seconds of frames for the per-frame engine cost (after the seed)
REPEATS = 3  # runs per throughput, start-up and latency figure (1 with --quick); the median is reported
LATENCY_S = 20.0  # seconds of frames per latency run (after the 2 s seed); 3 runs of 20 s keep the suite short
SEED_S = 2.0
BUSY_POLL_S = 0.02  # the daemon's --busy-poll for the latency variant that trades a core for latency
START_TIMEOUT_S = 300.0
STOP_TIMEOUT_S = 30.0


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _python_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop("XLA_FLAGS", None)  # the programs run as a user runs them, with XLA's default threading
    return env


def _wait_rusage(proc: subprocess.Popen, timeout_s: float) -> tuple[int, float]:
    """Wait for `proc` with os.wait4 (Popen.wait discards the child's rusage); (status, peak RSS MiB)."""
    deadline = time.monotonic() + timeout_s
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return proc.returncode, usage.ru_maxrss / 1024
        if time.monotonic() > deadline:
            proc.kill()
            deadline = time.monotonic() + 10
        time.sleep(0.02)


class DaemonProcess:
    """`mocap-service serve` on free loopback ports, with a client context; stopped by SIGTERM on exit."""

    def __init__(self, cache_dir: str, max_skip_frames: int | None = None, busy_poll_s: float | None = None):
        self.cache_dir = cache_dir
        self.max_skip_frames = max_skip_frames
        self.busy_poll_s = busy_poll_s
        self.peak_rss_mb = float("nan")
        self.exit_code: int | None = None

    def __enter__(self) -> DaemonProcess:
        ports = [_free_port() for _ in range(3)]
        self.frames_ep, self.publish_ep, self.control_ep = (f"tcp://127.0.0.1:{p}" for p in ports)
        self._state = tempfile.mkdtemp(prefix="mocap-bench-state-")
        self._log = tempfile.TemporaryFile()
        cmd = [sys.executable, "-m", "service.cli", "serve", "--frames", self.frames_ep, "--publish",
               self.publish_ep, "--control", self.control_ep, "--state-dir", self._state, "--cache-dir",
               self.cache_dir, "--log-level", "WARNING"]
        if self.max_skip_frames is not None:
            cmd += ["--max-skip-frames", str(self.max_skip_frames)]
        if self.busy_poll_s is not None:
            cmd += ["--busy-poll", str(self.busy_poll_s)]
        self.ctx = zmq.Context()
        self.launched_s = time.perf_counter()
        self.proc = subprocess.Popen(cmd, cwd=REPO, env=_python_env(), stdout=subprocess.DEVNULL, stderr=self._log)
        return self

    def __exit__(self, *exc) -> None:
        if self.proc.poll() is None and self.proc.returncode is None:
            self.proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(ChildProcessError):
            self.exit_code, self.peak_rss_mb = _wait_rusage(self.proc, STOP_TIMEOUT_S)
        self.ctx.destroy(linger=0)
        self._log.close()
        shutil.rmtree(self._state, ignore_errors=True)

    def log_tail(self) -> str:
        """The daemon's last stderr line (why it failed), or ""."""
        self._log.seek(0)
        lines = self._log.read().decode(errors="replace").strip().splitlines()
        return lines[-1] if lines else ""

    def request(self, cmd: dict, timeout_s: float = 5.0) -> dict | None:
        """One control request on a fresh REQ socket (a REQ that timed out cannot be reused)."""
        sock = self.ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(self.control_ep)
        try:
            sock.send(pm.encode_request(cmd))
            if sock.poll(int(timeout_s * 1000)):
                return pm.decode_reply(sock.recv())
            return None
        finally:
            sock.close()

    def wait_ready(self) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while self.request({"cmd": "ping"}, timeout_s=1.0) is None:
            if self.proc.poll() is not None:
                raise RuntimeError(f"daemon exited with status {self.proc.returncode}: {self.log_tail()}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"daemon not ready after {START_TIMEOUT_S:g} s")


class Receiver(threading.Thread):
    """Collects, per frame number, the receipt time of each labels/<subject> message."""

    def __init__(self, ctx: zmq.Context, endpoint: str):
        super().__init__(daemon=True)
        self.sock = ctx.socket(zmq.SUB)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.SUBSCRIBE, pm.TOPIC_LABELS)
        self.sock.connect(endpoint)
        self.received: dict[int, list[int]] = {}  # frame -> receipt times [perf_counter ns]
        self.labeled: dict[int, int] = {}  # frame -> labeled markers (summed over subjects)
        self.first_ns: int | None = None  # receipt time of the first labels message
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            if not self.sock.poll(50):
                continue
            while True:
                try:
                    parts = self.sock.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                now = time.perf_counter_ns()
                try:
                    msg = pm.decode(parts)
                except pm.ProtocolError:
                    continue
                if self.first_ns is None:
                    self.first_ns = now
                self.received.setdefault(msg.frame, []).append(now)
                self.labeled[msg.frame] = self.labeled.get(msg.frame, 0) + int(np.count_nonzero(msg.point_index >= 0))
        self.sock.close()


def replay(daemon: DaemonProcess, frames: list, rate_hz: float, first_frame: int, n_subjects: int,
           scored_from: int) -> dict:
    """Send `frames` [(points (N,3), labels | None)] paced drift-free at `rate_hz`; latency per frame is
    send -> receipt of the last of its `n_subjects` labels messages. Frames before `scored_from` (the
    seed) are sent but not counted."""
    receiver = Receiver(daemon.ctx, daemon.publish_ep)
    receiver.start()
    pub = daemon.ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.connect(daemon.frames_ep)
    time.sleep(0.5)  # let both subscriptions reach their publishers (PUB/SUB drops before that)
    sent: dict[int, int] = {}
    t0 = time.perf_counter()
    for k, (points, labels) in enumerate(frames):
        target = t0 + k / rate_hz
        delay = target - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        number = first_frame + k
        msg = pm.Frame(stream="default", frame=number, t_ns=int(round(number * 1e9 / rate_hz)),
                       points=np.asarray(points, np.float32), labels=labels)
        parts = pm.encode(msg)  # before the clock starts: the latency is from the send
        sent[number] = time.perf_counter_ns()
        pub.send_multipart(parts)
    time.sleep(0.5)
    receiver.stop.set()
    receiver.join()
    pub.close()
    latency_ms, unanswered, missing = [], 0, []
    for number, t_send in sent.items():
        if number - first_frame < scored_from:
            continue
        got = receiver.received.get(number, [])
        if len(got) < n_subjects:
            unanswered += 1
            missing.append(number - first_frame)
        else:
            latency_ms.append((sorted(got)[n_subjects - 1] - t_send) * 1e-6)
    lat = np.array(latency_ms) if latency_ms else np.array([np.nan])
    scored = len(sent) - scored_from
    labeled = [receiver.labeled.get(n, 0) for n in sent if n - first_frame >= scored_from]
    return {
        "frames": scored,
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "max_ms": float(np.max(lat)),
        "unanswered": unanswered,
        "unanswered_fraction": unanswered / max(scored, 1),
        "labeled_mean": float(np.mean(labeled)) if labeled else float("nan"),
        "unanswered_frames": _spans(missing),
    }


def _spans(numbers: list[int]) -> str:
    """[3, 4, 5, 9] -> "3-5, 9": which frames went unanswered, compactly (where a loss comes from)."""
    spans: list[list[int]] = []
    for n in numbers:
        if spans and n == spans[-1][1] + 1:
            spans[-1][1] = n
        else:
            spans.append([n, n])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in spans)


# ---------------------------------------------------------------------------------------------- measures


def label_throughput(data_dir: Path, file: str, max_skip_frames: int | None) -> dict:
    """`mocap-service label` on a whole recording (seeded from its first 2 s); wall time includes start-up."""
    from recordings.c3d import read_c3d

    rec = read_c3d(data_dir / file)
    seed = int(round(SEED_S * rec.rate_hz))
    with tempfile.TemporaryDirectory(prefix="mocap-bench-label-") as tmp:
        cmd = [sys.executable, "-m", "service.cli", "label", str(data_dir / file), "-o", f"{tmp}/out.c3d",
               "--seed-frames", str(seed), "--no-progress"]
        if max_skip_frames is not None:
            cmd += ["--max-skip-frames", str(max_skip_frames)]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=REPO, env=_python_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        err = proc.stderr.read().decode(errors="replace")  # small: one sentence at most
        code, rss = _wait_rusage(proc, 3600)
        wall = time.perf_counter() - t0
    if code != 0:
        return {"error": f"exit {code}: {err.strip()[-200:]}"}
    return {"file": file, "frames": rec.n_frames, "wall_s": wall, "fps": rec.n_frames / wall, "peak_rss_mb": rss}


def engine_cost(data_dir: Path, cache_dir: str, seconds: float = COST_S) -> dict:
    """Per-frame engine cost (issue: one 41-marker subject at L2), in a fresh process with default XLA
    threading: `Engine.step(defer=True)`, `Engine.complete` and `Engine.between_frames` called as the
    daemon calls them, on the same frames three times, each time with a fresh engine:

    - paced at the recording's rate, like a live stream. Reports the labels path (`step`: the frame's
      labels known, which the daemon publishes then), the pose path (`step` + `complete`: its pose known
      too), the whole frame (+ `between_frames`: the bookkeeping is done and the engine waits for the next
      frame) and the CPU time per frame (the process's threads: the frame loop, XLA's solves; and the
      helper process: calibration and refinement).
    - back to back: the next frame as soon as the last one's pose is known, and the helper's jobs (which
      a live stream gives their stream time in wall time) waited for between frames, untimed. It shows
      the engine's own cost with warm caches.
    - paced, spinning: paced, but waiting for each frame in a busy loop instead of sleeping, as the
      daemon does with `--busy-poll` (one core kept busy).

    Why three: on this shared virtual machine, code that ran a few milliseconds ago is slow the first time
    it runs again (`idle_penalty`: the first call of a small numpy computation after an 8 ms sleep,
    relative to the same call right after; 1.0 on a machine that keeps its caches), and a paced frame
    is ~100 numpy calls that each pay it once. A core that spins instead of sleeping pays little of it."""
    cmd = [sys.executable, "-m", "benchmarks.speed", "engine-cost", str(data_dir), cache_dir, str(seconds)]
    env = {**_python_env(), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}  # as `mocap-service` sets them
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = proc.communicate(timeout=600)
    if proc.returncode != 0:
        return {"error": f"exit {proc.returncode}: {err.decode(errors='replace').strip()[-200:]}"}
    import json

    return json.loads(out.decode().strip().splitlines()[-1])


def _engine_cost_here(data_dir: Path, cache_dir: str, seconds: float) -> dict:
    import resource

    from recordings.c3d import read_c3d
    from service.daemon import enable_compilation_cache

    enable_compilation_cache(cache_dir)
    rec = read_c3d(data_dir / LATENCY_FILE)
    seq = corrupt(rec, "L2", 1)
    paced = _cost_run(seq, seconds, paced=True)
    b2b = _cost_run(seq, seconds, paced=False)
    spin = _cost_run(seq, seconds, paced=True, spin=True)
    return {"file": f"{LATENCY_FILE} L2", "markers": len(seq.marker_names), **paced,
            **{f"b2b_{k}": v for k, v in b2b.items()}, **{f"spin_{k}": v for k, v in spin.items()}, "idle_penalty": _idle_penalty(),
            "idle_penalty_spin": _idle_penalty(spin=True),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _cost_run(seq, seconds: float, paced: bool, spin: bool = False) -> dict:
    """One pass of `engine_cost` over `seq` (seeded for SEED_S, then `seconds` of frames timed); `spin`:
    paced frames are waited for in a busy loop."""
    from service import worker
    from service.engine import Engine, FrameInput

    n_seed = int(round(SEED_S * seq.rate_hz))
    n = min(len(seq.points_m), n_seed + int(seconds * seq.rate_hz))
    engine = Engine()
    engine.warm_up()
    helper = worker.shared()  # started by warm_up
    period_s = 1.0 / seq.rate_hz
    step_ms, pose_ms, frame_ms, solved = [], [], [], 0
    cpu0 = start = None
    for f in range(n):
        pts = seq.points_m[f]
        if pts is None:
            continue
        labels = [seq.marker_names[t] if t >= 0 else "" for t in seq.truth[f]] if f < n_seed else None
        frame = FrameInput("bench", f, int(f * 1e9 * period_s), pts, labels)
        if f == n_seed:
            cpu0, start = time.process_time() + helper.cpu_s(), time.perf_counter() - f * period_s
        if start is not None and paced:
            while time.perf_counter() < start + f * period_s:  # paced like a live stream
                if not spin:
                    time.sleep(max(0.0, start + f * period_s - time.perf_counter() - 0.0005))
        elif not paced:
            helper.wait_idle()
        t0 = time.perf_counter()
        outputs, _ = engine.step(frame, defer=True)  # (the daemon's calls, in its order)
        t1 = time.perf_counter()
        outputs = engine.complete(outputs)
        t2 = time.perf_counter()
        engine.between_frames()
        t3 = time.perf_counter()
        if f >= n_seed:
            step_ms.append(1e3 * (t1 - t0))
            pose_ms.append(1e3 * (t2 - t0))
            frame_ms.append(1e3 * (t3 - t0))
            solved += any(o.solved for o in outputs)
    cpu_ms = 1e3 * (time.process_time() + helper.cpu_s() - cpu0) / max(len(step_ms), 1)
    out = {"frames": len(step_ms), "cpu_ms_per_frame": cpu_ms, "solved_fraction": solved / max(len(step_ms), 1)}
    for name, ms in (("labels", step_ms), ("pose", pose_ms), ("frame", frame_ms)):
        a = np.array(ms)
        out.update({f"{name}_mean_ms": float(a.mean()), f"{name}_p50_ms": float(np.median(a)),
                    f"{name}_p99_ms": float(np.percentile(a, 99))})
    return out


def _idle_penalty(calls: int = 200, spin: bool = False) -> float:
    """Median over `calls` of: the time of a small numpy computation (41 x 41 marker distances) run first
    after an 8 ms sleep (`spin`: 8 ms of a busy loop), over the same computation's time run right after it."""
    pts = np.random.default_rng(0).normal(size=(41, 3))
    ratios = []
    for _ in range(calls):
        if spin:
            end = time.perf_counter() + 0.008
            while time.perf_counter() < end:
                pass
        else:
            time.sleep(0.008)
        t0 = time.perf_counter()
        np.linalg.norm(pts[:, None] - pts[None], axis=2).sum()
        t1 = time.perf_counter()
        np.linalg.norm(pts[:, None] - pts[None], axis=2).sum()
        t2 = time.perf_counter()
        ratios.append((t1 - t0) / max(t2 - t1, 1e-9))
    return float(np.median(ratios))


def startup(data_dir: Path, cache_dir: str) -> dict:
    """Seconds from launching the daemon to receiving labels for its first frame; frames (seeded with
    their true labels) are offered every 10 ms from launch on, as a live capture system would."""
    from recordings.c3d import read_c3d

    rec = read_c3d(data_dir / QUICK_THROUGHPUT_FILE)
    points = rec.points_m[0]
    keep = np.all(np.isfinite(points), axis=1)
    labels = [label if is_marker_label(label) else "" for label in np.array(rec.labels)[keep]]
    with DaemonProcess(cache_dir) as daemon:
        receiver = Receiver(daemon.ctx, daemon.publish_ep)
        receiver.start()
        pub = daemon.ctx.socket(zmq.PUB)
        pub.setsockopt(zmq.LINGER, 0)
        pub.connect(daemon.frames_ep)
        number, first_s = 0, None
        while first_s is None and time.perf_counter() - daemon.launched_s < START_TIMEOUT_S:
            if daemon.proc.poll() is not None:
                break
            pub.send_multipart(pm.encode(pm.Frame("default", number, number * 10_000_000, points[keep].astype(np.float32), labels)))
            number += 1
            time.sleep(0.01)
            if receiver.first_ns is not None:
                first_s = receiver.first_ns * 1e-9 - daemon.launched_s
        receiver.stop.set()
        receiver.join()
        pub.close()
        failure = "" if first_s is not None else f"no labels within {START_TIMEOUT_S:g} s: {daemon.log_tail()}"
    if failure:
        return {"error": failure}
    return {"seconds": first_s, "peak_rss_mb": daemon.peak_rss_mb}


def latency(data_dir: Path, cache_dir: str, seconds: float, max_skip_frames: int | None = None,
            busy_poll_s: float | None = None) -> dict:
    """One subject (LATENCY_FILE at L2, seeded for 2 s) replayed at its rate through the daemon (with
    `--busy-poll busy_poll_s` if given)."""
    from recordings.c3d import read_c3d
    import dataclasses

    rec = read_c3d(data_dir / LATENCY_FILE)
    n = min(rec.n_frames, int(round((seconds + SEED_S) * rec.rate_hz)))
    seq = corrupt(dataclasses.replace(rec, points_m=rec.points_m[:n]), "L2", 1)
    frames = [(p, seq.true_labels(f) if f < seq.seed_frames else None)
              for f, p in enumerate(seq.points_m) if p is not None]
    with DaemonProcess(cache_dir, max_skip_frames, busy_poll_s) as daemon:
        daemon.wait_ready()
        result = replay(daemon, frames, seq.rate_hz, 0, 1, seq.seed_frames)
        status = daemon.request({"cmd": "status"}) or {}
    # the daemon's own processing time per frame (engine + publishing, its last 1024 frames)
    result["processing_ms"] = status.get("latency_ms", {})
    result["peak_rss_mb"] = daemon.peak_rss_mb
    result["file"] = f"{LATENCY_FILE} L2"
    return result


# A stand-in daemon that answers every frame at once with a labels message of 41 markers and does no
# labeling: what the same client, sockets and protocol cost on this machine (the floor under `latency`).
_ECHO_DAEMON = """
import sys
import numpy as np, zmq
from protocol import messages as pm
ctx = zmq.Context()
sub = ctx.socket(zmq.SUB); sub.setsockopt(zmq.SUBSCRIBE, pm.TOPIC_FRAME); sub.bind(sys.argv[1])
pub = ctx.socket(zmq.PUB); pub.bind(sys.argv[2])
m = 41
names, index, xyz = [f"M{i}" for i in range(m)], np.arange(m, dtype=np.int32), np.zeros((m, 3), np.float32)
while True:
    f = pm.decode(sub.recv_multipart())
    pub.send_multipart(pm.encode(pm.Labels(subject="S", stream=f.stream, frame=f.frame, t_ns=f.t_ns, markers=names,
                                           point_index=index, positions=xyz, solved=False, predicted=xyz,
                                           iterations=0, residual_m=0.0)))
"""


def latency_floor(data_dir: Path, seconds: float) -> dict:
    """`latency`'s replay against `_ECHO_DAEMON` (same frames, rate, client and protocol, no labeling)."""
    from recordings.c3d import read_c3d

    rec = read_c3d(data_dir / LATENCY_FILE)
    n = min(rec.n_frames, int(round(seconds * rec.rate_hz)))
    seq = corrupt(rec, "L2", 1)
    frames = [(p, None) for p in seq.points_m[:n] if p is not None]
    frames_ep, publish_ep = f"tcp://127.0.0.1:{_free_port()}", f"tcp://127.0.0.1:{_free_port()}"
    proc = subprocess.Popen([sys.executable, "-c", _ECHO_DAEMON, frames_ep, publish_ep], cwd=REPO, env=_python_env())
    ctx = zmq.Context()
    try:
        time.sleep(1.0)  # bound and listening
        target = type("EchoDaemon", (), {"ctx": ctx, "frames_ep": frames_ep, "publish_ep": publish_ep})()
        result = replay(target, frames, rec.rate_hz, 0, 1, 0)
    finally:
        proc.kill()
        proc.wait()
        ctx.term()
    return {**result, "file": f"{LATENCY_FILE} L2"}


def scale(data_dir: Path, cache_dir: str, seconds: float, counts=SCALE_COUNTS) -> dict:
    """N shifted copies of SCALE_FILE as N subjects at 120 Hz; per N the latency until the last subject's
    labels. Sustained: p99 under one frame period and at most 1 % of frames unanswered. Goes on past the
    first N that is not sustained (to show the trend) until the daemon clearly saturates."""
    from recordings.c3d import read_c3d

    rec = read_c3d(data_dir / SCALE_FILE)
    names = [split_label(label)[1] for label in rec.labels]
    true = np.array([is_marker_label(label) for label in rec.labels])
    period_ms = 1000 / SCALE_RATE_HZ
    seed_frames = int(round(SEED_S * SCALE_RATE_HZ))
    n_frames = seed_frames + int(round(seconds * SCALE_RATE_HZ))
    rng = np.random.default_rng(0)
    rows, sustained, first_frame = [], 0, 0
    with DaemonProcess(cache_dir) as daemon:
        daemon.wait_ready()
        for n_subjects in counts:
            daemon.request({"cmd": "reset"})
            frames = []
            for f in range(n_frames):
                points, labels = [], []
                for k in range(n_subjects):
                    src = (f + k * 600) % rec.n_frames  # each copy runs 5 s apart in time
                    p = rec.points_m[src] + [SCALE_SPACING_M * k, 0.0, 0.0]
                    ok = np.all(np.isfinite(p), axis=1) & true
                    points.append(p[ok])
                    labels += [f"P{k}:{names[i]}" for i in np.flatnonzero(ok)]
                cloud = np.concatenate(points)
                order = rng.permutation(len(cloud))
                frames.append((cloud[order], [labels[i] for i in order] if f < seed_frames else None))
            r = replay(daemon, frames, SCALE_RATE_HZ, first_frame, n_subjects, seed_frames)
            first_frame += n_frames + 10
            r["subjects"] = n_subjects
            r["sustained"] = bool(r["p99_ms"] < period_ms and r["unanswered_fraction"] <= 0.01)
            rows.append(r)
            if r["unanswered_fraction"] > 0.05 or r["p50_ms"] > period_ms:
                break
    for r in rows:  # the largest count such that it and every smaller one were sustained
        if not r["sustained"]:
            break
        sustained = r["subjects"]
    return {"rows": rows, "sustained_subjects": sustained, "period_ms": period_ms, "peak_rss_mb": daemon.peak_rss_mb}


def marker_frames(n_markers: int, seconds: float) -> tuple[list, int]:
    """One synthetic performer at 120 Hz wearing `n_markers` markers: the MARKER_BASE_SET markers plus
    shifted copies of them (MARKER_COPY_SHIFTS_M, in the segment frame), as frames [(points, labels |
    None)] in random order, labeled during the seed; also the number of seed frames. The performer starts
    with a T-pose, which the seed covers, as a real session would."""
    from recordings import synthetic

    seed_frames = int(round(SEED_S * SCALE_RATE_HZ))
    perf = synthetic.perform(0, marker_set=MARKER_BASE_SET, duration_s=SEED_S + seconds, rate_hz=SCALE_RATE_HZ,
                             subject="P0")
    n_base = len(perf.marker_names)
    if not n_base <= n_markers <= n_base * (1 + len(MARKER_COPY_SHIFTS_M)):
        raise ValueError(f"{n_markers} markers cannot be built from {n_base} base markers and "
                         f"{len(MARKER_COPY_SHIFTS_M)} copies")
    extra = np.arange(n_markers - n_base)
    base = extra % n_base  # copy the base markers in order, a whole set per copy
    copy = extra // n_base
    segment = np.concatenate([perf.marker_segment, perf.marker_segment[base]])
    offsets_m = np.concatenate([perf.marker_offsets_m,
                                perf.marker_offsets_m[base] + np.asarray(MARKER_COPY_SHIFTS_M)[copy]])
    names = list(perf.marker_names) + [f"{perf.marker_names[b]}_{c + 2}" for b, c in zip(base, copy)]
    R_world_segment, p_world_segment = synthetic.forward_kinematics(perf.root_position_m, perf.rotations_xyzw,
                                                                    perf.joint_offsets_m)
    points_m = synthetic.marker_positions(R_world_segment, p_world_segment, segment, offsets_m)
    rng = np.random.default_rng(0)
    frames = []
    for f, cloud in enumerate(points_m):
        order = rng.permutation(n_markers)
        frames.append((cloud[order], [f"P0:{names[i]}" for i in order] if f < seed_frames else None))
    return frames, seed_frames


def marker_scale(cache_dir: str, seconds: float, counts=MARKER_COUNTS) -> dict:
    """One subject wearing more and more markers (`marker_frames`) at 120 Hz, through one daemon, reset
    between counts. Sustained as in `scale`: p99 under one frame period, at most 1 % unanswered."""
    period_ms = 1000 / SCALE_RATE_HZ
    rows, sustained, first_frame = [], 0, 0
    with DaemonProcess(cache_dir) as daemon:
        daemon.wait_ready()
        for n_markers in counts:
            daemon.request({"cmd": "reset"})
            frames, seed_frames = marker_frames(n_markers, seconds)
            r = replay(daemon, frames, SCALE_RATE_HZ, first_frame, 1, seed_frames)
            first_frame += len(frames) + 10
            r["markers"] = n_markers
            r["sustained"] = bool(r["p99_ms"] < period_ms and r["unanswered_fraction"] <= 0.01)
            rows.append(r)  # every count runs (there are only a few): the trend matters more than the cut
    for r in rows:  # the largest count such that it and every smaller one were sustained
        if not r["sustained"]:
            break
        sustained = r["markers"]
    return {"rows": rows, "sustained_markers": sustained, "period_ms": period_ms, "peak_rss_mb": daemon.peak_rss_mb}


def _guarded(name: str, fn, *args, **kwargs) -> dict:
    print(f"speed: {name} ...", file=sys.stderr, end=" ", flush=True)
    t0 = time.perf_counter()
    try:
        result = fn(*args, **kwargs)
    except Exception as e:  # noqa: BLE001 - a failed measurement is reported, the others still run
        result = {"error": f"{type(e).__name__}: {e}"}
    print(f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return result


def _median(runs: list) -> object:
    """The median of each number across `runs` (dicts are taken key by key; other values from the first
    run). Each figure is the median on its own, so p99 and max may come from different runs."""
    first = runs[0]
    if isinstance(first, dict):
        return {k: _median([r[k] for r in runs if k in r]) for k in first}
    if isinstance(first, (int, float)) and not isinstance(first, bool):
        m = float(np.median(runs))
        return int(round(m)) if all(isinstance(x, int) for x in runs) else m
    return first


def _repeated(name: str, runs: int, fn, *args, **kwargs) -> dict:
    """`fn` run `runs` times (each `_guarded`); the medians of the runs that succeeded, with "runs" (how
    many succeeded), "repeats" (how many were tried) and "values" (each run's result, for the spread).
    Fails only if every run failed."""
    results = [_guarded(f"{name} [{k + 1}/{runs}]", fn, *args, **kwargs) for k in range(runs)]
    ok = [r for r in results if "error" not in r]
    if not ok:
        return results[0]
    return {**_median(ok), "runs": len(ok), "repeats": runs, "values": results}


def _startup_cold(data_dir: Path) -> dict:
    """Start-up with a compile cache that is empty for this run only."""
    with tempfile.TemporaryDirectory(prefix="mocap-bench-jax-") as empty_cache:
        return startup(data_dir, empty_cache)


def measure(data_dir: Path, quick: bool, cache_dir: str) -> dict:
    """Every measurement, alone on the machine (run after the accuracy pool has finished). `quick` keeps
    the short ones (small file, warm start only, short replays, 1-2 subjects) and runs each once."""
    file = QUICK_THROUGHPUT_FILE if quick else THROUGHPUT_FILE
    runs = 1 if quick else REPEATS
    skipped = {"error": "skipped in --quick"}
    out: dict = {}
    if not quick:  # warm the compile cache for the CLI's own XLA flags (the workers ran single-threaded)
        _guarded("label warm-up", label_throughput, data_dir, QUICK_THROUGHPUT_FILE, None)
    out["label_adaptive"] = _repeated("label (adaptive)", runs, label_throughput, data_dir, file, None)
    out["label_every_frame"] = _repeated("label (solve every frame)", runs, label_throughput, data_dir, file, 0)
    out["engine_cost"] = _repeated("per-frame engine cost", runs, engine_cost, data_dir, cache_dir, 8.0 if quick else COST_S)
    out["startup_cold"] = skipped if quick else _repeated("start-up (cold cache)", runs, _startup_cold, data_dir)
    out["startup_warm"] = _repeated("start-up (warm cache)", runs, startup, data_dir, cache_dir)
    seconds = 6.0 if quick else LATENCY_S
    out["latency"] = _repeated("online latency", runs, latency, data_dir, cache_dir, seconds)
    out["latency_floor"] = _repeated("latency floor (echo daemon)", runs, latency_floor, data_dir, seconds)
    out["latency_every_frame"] = skipped if quick else _repeated(
        "online latency (solve every frame)", runs, latency, data_dir, cache_dir, seconds, 0)
    out["latency_busy_poll"] = _repeated("online latency (busy polling)", runs, latency, data_dir, cache_dir, seconds,
                                         None, BUSY_POLL_S)
    out["scale"] = _guarded("scale", scale, data_dir, cache_dir, 3.0 if quick else 8.0,
                            SCALE_COUNTS[:2] if quick else SCALE_COUNTS)
    out["marker_scale"] = _guarded("scale (markers per subject)", marker_scale, cache_dir, 3.0 if quick else 8.0)
    return out


# ---------------------------------------------------------------------------------------------- report


def _f(x, fmt="{:.1f}") -> str:
    return "–" if x is None or (isinstance(x, float) and x != x) else fmt.format(x)


def _scan_cells(r: dict) -> str:
    """p50 | p99 | max | unanswered cells of one row of a scale scan."""
    return (f"{_f(r['p50_ms'], '{:.2f}')} | {_f(r['p99_ms'], '{:.2f}')} | {_f(r['max_ms'], '{:.1f}')} | "
            f"{r['unanswered']} / {r['frames']}")


def report_lines(inproc: dict, speed: dict) -> list[str]:
    lines = [
        "In-process (the accuracy runs above, 2 worker processes with single-threaded XLA; step time only):",
        "",
        "| variant | frames | frames/s | per-frame cost mean / p99, 41 markers at L2 [ms] | frames with a solve | peak RSS [MiB] |",
        "|---|---|---|---|---|---|",
    ] if inproc else []
    for v, s in inproc.items():
        lines.append(f"| {v} | {s['frames']} | {_f(s['fps'], '{:.0f}')} | {_f(s['l2_mean_ms'], '{:.2f}')} / "
                     f"{_f(s['l2_p99_ms'], '{:.2f}')} | {_f(100 * s['solved_fraction'], '{:.0f} %')} | "
                     f"{_f(s['peak_rss_mb'], '{:.0f}')} |")
    if "adaptive" in inproc and "nnt" in inproc:
        lines += ["", f"Engine (adaptive) cost relative to the NNT baseline: "
                  f"{inproc['nnt']['fps'] / inproc['adaptive']['fps']:.1f}x per frame."]
    if inproc:
        lines.append("")
    if not speed:
        return lines + ["Daemon and CLI measurements skipped (`--no-speed`)."]

    def err(d: dict) -> str:
        return f"failed: {d['error']}" if "error" in d else ""

    def runs(d: dict, key: str, fmt: str) -> str:
        """"median of 3: a, b, c" for the figure `key` of a repeated measurement (failed runs as such)."""
        values = d.get("values", [])
        if len(values) <= 1:
            return "one run"
        each = ", ".join("failed" if "error" in v else _f(v.get(key), fmt) for v in values)
        return f"median of {d['repeats']}: {each}"

    lines += ["Programs (subprocesses, alone on the machine, default XLA threading). Each figure is the median "
              "over repeated runs (a fresh process each), taken figure by figure; the brackets list every run's "
              "value of the headline figure:", "",
              "| measurement | result | peak RSS [MiB] |", "|---|---|---|"]
    for key, title in (("label_adaptive", "`mocap-service label`, adaptive"),
                       ("label_every_frame", "`mocap-service label --max-skip-frames 0`")):
        d = speed.get(key, {})
        res = err(d) or (f"{d['fps']:.0f} frames/s ({runs(d, 'fps', '{:.0f}')}; {d['frames']} frames of {d['file']} "
                         f"in {d['wall_s']:.1f} s, start-up included)")
        lines.append(f"| {title} | {res} | {_f(d.get('peak_rss_mb'), '{:.0f}')} |")
    d = speed.get("engine_cost", {})
    res = err(d) or (f"paced at its rate: labels {d['labels_mean_ms']:.2f} / {d['labels_p50_ms']:.2f} / {d['labels_p99_ms']:.2f} ms, "
                     f"labels + pose {d['pose_mean_ms']:.2f} / {d['pose_p50_ms']:.2f} / {d['pose_p99_ms']:.2f} ms, "
                     f"whole frame (+ between frames) {_f(d.get('frame_mean_ms'), '{:.2f}')} / {_f(d.get('frame_p50_ms'), '{:.2f}')} / "
                     f"{_f(d.get('frame_p99_ms'), '{:.2f}')} ms "
                     f"(mean / p50 / p99; labels mean {runs(d, 'labels_mean_ms', '{:.2f}')}); CPU time (all threads, and the helper process) "
                     f"{d['cpu_ms_per_frame']:.2f} ms per frame. Back to back (the helper's jobs waited for between "
                     f"frames, untimed): labels {_f(d.get('b2b_labels_mean_ms'), '{:.2f}')} / {_f(d.get('b2b_labels_p50_ms'), '{:.2f}')} / "
                     f"{_f(d.get('b2b_labels_p99_ms'), '{:.2f}')} ms (labels mean {runs(d, 'b2b_labels_mean_ms', '{:.2f}')}), whole frame "
                     f"{_f(d.get('b2b_frame_mean_ms'), '{:.2f}')} / {_f(d.get('b2b_frame_p50_ms'), '{:.2f}')} / {_f(d.get('b2b_frame_p99_ms'), '{:.2f}')} ms. "
                     f"Paced, spinning between frames instead of sleeping (as `serve --busy-poll` waits): labels "
                     f"{_f(d.get('spin_labels_mean_ms'), '{:.2f}')} / {_f(d.get('spin_labels_p50_ms'), '{:.2f}')} / "
                     f"{_f(d.get('spin_labels_p99_ms'), '{:.2f}')} ms (labels mean {runs(d, 'spin_labels_mean_ms', '{:.2f}')}). "
                     f"{d['frames']} frames of {d['file']} ({d['markers']} markers), a solve launched on "
                     f"{100 * d['solved_fraction']:.0f} % of them. This machine's idle penalty: a small numpy "
                     f"computation run first after an 8 ms sleep takes {_f(d.get('idle_penalty'), '{:.1f}')}x as long as right after "
                     f"({_f(d.get('idle_penalty_spin'), '{:.1f}')}x after 8 ms of spinning)")
    lines.append(f"| per-frame engine cost, one subject (`Engine.step(defer=True)`; `+ complete` for the pose; `+ between_frames` for the whole frame) | {res} | "
                 f"{_f(d.get('peak_rss_mb'), '{:.0f}')} |")
    for key, title in (("startup_cold", "start-up to first labeled frame, empty compile cache"),
                       ("startup_warm", "start-up to first labeled frame, warm compile cache")):
        d = speed.get(key, {})
        res = err(d) or f"{_f(d.get('seconds'), '{:.1f} s')} ({runs(d, 'seconds', '{:.1f}')})"
        lines.append(f"| {title} | {res} | {_f(d.get('peak_rss_mb'), '{:.0f}')} |")
    for key, title in (("latency", "online latency p50 / p99 / max, adaptive"),
                       ("latency_every_frame", "online latency p50 / p99 / max, solve every frame"),
                       ("latency_busy_poll", f"online latency p50 / p99 / max, adaptive, `--busy-poll {BUSY_POLL_S:g}`")):
        d = speed.get(key, {})
        proc = d.get("processing_ms") or {}
        res = err(d) or (f"{d['p50_ms']:.2f} / {d['p99_ms']:.2f} / {d['max_ms']:.1f} ms (p99 {runs(d, 'p99_ms', '{:.2f}')}) "
                         f"over {d['frames']} frames of {d['file']} at its rate per run, {d['unanswered']} "
                         f"unanswered; the daemon's own processing p50 / p99 / max {_f(proc.get('p50'), '{:.2f}')} / "
                         f"{_f(proc.get('p99'), '{:.2f}')} / {_f(proc.get('max'), '{:.1f}')} ms")
        lines.append(f"| {title} | {res} | {_f(d.get('peak_rss_mb'), '{:.0f}')} |")
    d = speed.get("latency_floor", {})
    res = err(d) or (f"{d['p50_ms']:.2f} / {d['p99_ms']:.2f} / {d['max_ms']:.1f} ms (p99 {runs(d, 'p99_ms', '{:.2f}')}) "
                     f"over {d['frames']} frames of {d['file']}: a stand-in daemon that answers each frame with a "
                     "41-marker labels message at once, no labeling (the client, sockets and protocol alone)")
    lines.append(f"| latency floor p50 / p99 / max (echo daemon) | {res} | |")
    d = speed.get("scale", {})
    scale_rows: list[str] = []  # the scans' own tables go below the summary table
    if "error" in d:
        lines.append(f"| scale | {err(d)} | |")
    else:
        broke = [r["subjects"] for r in d["rows"] if not r["sustained"]]
        where = f"first not sustained: {broke[0]}" if broke else f"every count tried, up to {d['rows'][-1]['subjects']}"
        lines.append(f"| subjects sustained at 120 Hz (one run; p99 < {d['period_ms']:.1f} ms, ≤ 1 % unanswered) | "
                     f"{d['sustained_subjects']} ({where}) | {_f(d.get('peak_rss_mb'), '{:.0f}')} |")
        scale_rows += ["", f"Subjects scan, one run (N copies of {SCALE_FILE}, 41 markers each, {SCALE_SPACING_M:g} m "
                       "apart, one daemon reset between counts):", "",
                       "| subjects | p50 [ms] | p99 [ms] | max [ms] | unanswered |", "|---|---|---|---|---|"]
        for r in d["rows"]:
            scale_rows.append(f"| {r['subjects']} | {_scan_cells(r)} |")
    d = speed.get("marker_scale", {})
    if "error" in d:
        lines.append(f"| markers per subject | {err(d)} | |")
    else:
        lines.append(f"| markers on one subject sustained at 120 Hz (one run; p99 < {d['period_ms']:.1f} ms, ≤ 1 % unanswered; "
                     f"at most {MARKER_COUNTS[-1]} tried) | {d['sustained_markers']} | {_f(d.get('peak_rss_mb'), '{:.0f}')} |")
        scale_rows += ["", f"Markers-per-subject scan, one run (one synthetic performer, seed 0, at 120 Hz without "
                       f"occlusion: the {MARKER_BASE_SET} set plus copies of its markers shifted 3-4 cm in their "
                       "segment's frame, so they move rigidly with it; seeded for 2 s in its T-pose):", "",
                       "| markers | p50 [ms] | p99 [ms] | max [ms] | unanswered | labeled per frame (mean) |",
                       "|---|---|---|---|---|---|"]
        for r in d["rows"]:
            scale_rows.append(f"| {r['markers']} | {_scan_cells(r)} | {_f(r.get('labeled_mean'), '{:.1f}')} |")
    lines += scale_rows
    lines += ["", "Latency is measured by the benchmark client: from just before a frame is sent to the receipt "
              "of its (last subject's) labels message, over loopback TCP, seed frames excluded. "
              f"Repeated runs: {REPEATS} in the full benchmark, 1 with `--quick`; a latency run replays "
              f"{LATENCY_S:g} s of frames after the seed in the full benchmark (6 s with `--quick`)."]
    return lines


if __name__ == "__main__":  # the per-frame cost measurement's own process (see engine_cost)
    import json

    if len(sys.argv) == 5 and sys.argv[1] == "engine-cost":
        print(json.dumps(_engine_cost_here(Path(sys.argv[2]), sys.argv[3], float(sys.argv[4]))))
    else:
        sys.exit("usage: python3 -m benchmarks.speed engine-cost DATA_DIR CACHE_DIR SECONDS (run by benchmarks.run)")
