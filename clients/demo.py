"""The demo: the whole system on this machine, then how well it did.

    python3 -m clients.demo [--duration S] [--seed N] [--level L0..L3] [--seeded] [--out DIR]

It starts the daemon (`mocap-service serve` on free loopback ports with a temporary state directory), the
recorder (`mocap-record`) and the replay of the synthetic performer (`mocap-replay`, corruption L2:
occlusions, noise and ghosts), each as its own process talking over ZeroMQ exactly as real tools would.
Seedless first: the performer starts in a T-pose and the engine must find them with no label given. If
that fails, it runs again seeded (ground-truth labels in the first 2 s) and says so.

Then it scores the recorded labels against the performer's ground truth (`benchmarks.score`: accuracy,
precision, ghost false-label rate) and reports the end-to-end latency (replay's send time to the
recorder's receipt, through the daemon), and where the files are. Every process is stopped cleanly at the
end, on an error and on Ctrl-C.

The helpers (`Children`, `start_daemon`, `start_recorder`, `given_labels`, ...) are what `tests/test_e2e.py`
uses to run the same pipeline.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
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

from clients.record import SubjectLabels, load_labels
from clients.replay import _Parser, _positive, control_request, load_truth
from recordings.corruption import LEVELS, CorruptedSequence

REPO = Path(__file__).resolve().parents[1]
#: cold start compiles the solve; on a busy 2-core machine that can take a while [s]
DAEMON_READY_TIMEOUT_S = 300.0
#: a seedless run scoring below this accuracy counts as "the engine did not find the performer"
SEEDLESS_MIN_ACCURACY = 0.5


def free_ports(n: int) -> list[int]:
    """n distinct free TCP ports on loopback (held open together so they differ, then released)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def module_command(module: str, *args) -> list[str]:
    """Run a project module with this interpreter (the console scripts may not be installed)."""
    return [sys.executable, "-m", module, *map(str, args)]


def child_env() -> dict[str, str]:
    """The environment for children: the repository importable whatever their working directory."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH", "")]))
    return env


class Children:
    """The processes we started; `stop_all` ends each (SIGINT, then SIGKILL after a grace period), newest
    first so the recorder writes its files before the daemon goes. Use as a context manager."""

    def __init__(self) -> None:
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, command: list[str], **popen) -> subprocess.Popen:
        popen.setdefault("cwd", REPO)
        popen.setdefault("env", child_env())
        proc = subprocess.Popen(command, **popen)
        self.procs.append((name, proc))
        return proc

    @staticmethod
    def stop(proc: subprocess.Popen, grace_s: float = 30.0) -> int:
        """SIGINT (every project process stops cleanly on it), SIGKILL if it has not exited after grace_s."""
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return proc.returncode

    def stop_all(self) -> None:
        """Stop every child; a Ctrl-C meanwhile is ignored (the clean-up must finish, and is bounded)."""
        in_main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if in_main else None
        try:
            for _, proc in reversed(self.procs):
                self.stop(proc)
                if proc.stdout and not proc.stdout.closed:  # stderr pipes are closed by their reader thread
                    proc.stdout.close()
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)

    def __enter__(self) -> Children:
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


@dataclasses.dataclass(frozen=True)
class Endpoints:
    frames: str
    publish: str
    control: str


class DemoError(Exception):
    """Something did not start or finish; the message says what and where to look."""


def start_daemon(children: Children, state_dir: Path, log_path: Path, *extra: str) -> Endpoints:
    """Start `mocap-service serve` on free loopback ports; return once it answers on its control socket."""
    ports = free_ports(3)
    eps = Endpoints(*(f"tcp://127.0.0.1:{p}" for p in ports))
    log = open(log_path, "w")
    proc = children.start(
        "daemon",
        module_command("service.cli", "serve", "--frames", eps.frames, "--publish", eps.publish,
                       "--control", eps.control, "--state-dir", state_dir, *extra),
        stdout=log, stderr=subprocess.STDOUT,
    )
    log.close()  # the child holds its own copy
    context = zmq.Context()
    try:
        deadline = time.monotonic() + DAEMON_READY_TIMEOUT_S
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise DemoError(f"the daemon exited with status {proc.returncode}; see {log_path}")
            reply = control_request(context, eps.control, {"cmd": "ping"}, timeout_s=1.0)
            if reply is not None and reply.get("ok"):
                return eps
        raise DemoError(f"the daemon did not answer within {DAEMON_READY_TIMEOUT_S:g} s; see {log_path}")
    finally:
        context.destroy(linger=0)


def start_recorder(children: Children, eps: Endpoints, base: Path, log_path: Path, *extra: str,
                   timeout_s: float = 60.0) -> subprocess.Popen:
    """Start `mocap-record`; return once it has received its first message (so it misses no result).

    Its stderr goes to log_path (a thread copies it, watching for the "receiving" line).
    """
    proc = children.start(
        "recorder",
        module_command("clients.record", "--endpoint", eps.publish, "--control", eps.control, "-o", base,
                       "--idle", "0", *extra),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    receiving = threading.Event()

    def copy():
        with proc.stderr, open(log_path, "w") as log:
            for line in proc.stderr:
                log.write(line)
                log.flush()
                if "receiving from" in line:
                    receiving.set()

    threading.Thread(target=copy, daemon=True).start()
    deadline = time.monotonic() + timeout_s
    while not receiving.wait(0.1):
        if proc.poll() is not None or time.monotonic() > deadline:
            raise DemoError(f"the recorder did not start receiving; see {log_path}")
    return proc


def finish_recorder(proc: subprocess.Popen, settle_s: float = 1.0) -> str:
    """Let the last results arrive, stop the recorder (it writes its files on SIGINT), return its stdout."""
    time.sleep(settle_s)
    Children.stop(proc, grace_s=120.0)
    with proc.stdout:
        out = proc.stdout.read()
    if proc.returncode not in (0, 1):  # 1: no result arrived, nothing written (scored as all unlabeled)
        raise DemoError(f"the recorder exited with status {proc.returncode}: {out.strip()}")
    return out


def given_labels(labels: dict[str, SubjectLabels], seq: CorruptedSequence) -> list[list[str] | None]:
    """`benchmarks.score`'s `given`: per sequence frame, the label ("Subject:Marker") each sent point got.

    Result frame numbers are sequence indices (mod n_frames when the replay looped); a frame no labels
    message answered is None.
    """
    given: list[list[str] | None] = [None] * seq.n_frames
    for subject, log in labels.items():
        for frame, index in zip(log.frames, log.point_index):
            f = int(frame) % seq.n_frames
            points = seq.points_m[f]
            if points is None:
                continue
            if given[f] is None:
                given[f] = [""] * len(points)
            for marker, i in zip(log.markers, index):
                if 0 <= i < len(points):
                    given[f][i] = f"{subject}:{marker}"
    return given


def latencies_ms(labels: dict[str, SubjectLabels]) -> np.ndarray:
    """Receive time - t_ns of every labels message [ms] (end to end when the replay stamped send times)."""
    parts = [(log.recv_ns - log.t_ns) * 1e-6 for log in labels.values()]
    return np.concatenate(parts) if parts else np.zeros(0)


@dataclasses.dataclass(frozen=True)
class Session:
    """One replay through the daemon, recorded and scored."""

    mode: str  # "tpose" or "seeded"
    score: object  # benchmarks.score.Score
    latency_ms: np.ndarray
    subjects: tuple[str, ...]
    first_labeled_frame: int | None
    outputs: tuple[Path, ...]
    rate_hz: float


def run_session(children: Children, eps: Endpoints, out_dir: Path, name: str, *, seeded: bool, seed: int,
                duration_s: float, level: str, quiet: bool = False) -> Session:
    """Record while replaying the synthetic performer once; score the result."""
    from benchmarks.score import score

    base = out_dir / name
    truth_path = out_dir / f"{name}_truth.npz"
    recorder = start_recorder(children, eps, base, out_dir / f"{name}_recorder.log")
    replay = children.start(
        "replay",
        module_command("clients.replay", "--endpoint", eps.frames, "--control", eps.control, "--seed", seed,
                       "--duration", duration_s, "--level", level, "--stamp-send-time", "--truth-out",
                       truth_path, *(["--seed-seconds", "2"] if seeded else []), *(["--quiet"] if quiet else [])),
    )
    if replay.wait() != 0:
        raise DemoError(f"the replay exited with status {replay.returncode}")
    finish_recorder(recorder)

    seq, labeled_frames = load_truth(truth_path)
    labels_path = base.with_name(base.name + "_labels.npz")
    labels = load_labels(labels_path) if labels_path.is_file() else {}
    given = given_labels(labels, seq)
    mode = "seeded" if seeded else "tpose"
    result = score(seq, given, mode, labeled_frames if seeded else 0)
    answered = [f for f, g in enumerate(given) if g is not None and any(g)]
    outputs = tuple(sorted(p for p in out_dir.glob(f"{name}*") if p.suffix in (".c3d", ".bvh", ".ndjson")))
    return Session(mode, result, latencies_ms(labels), tuple(labels), answered[0] if answered else None,
                   outputs, seq.rate_hz)


def _pct(x: float) -> str:
    return "n/a" if np.isnan(x) else f"{x:.1%}"


def report(session: Session, rate_hz: float) -> str:
    s = session.score
    lines = []
    if session.first_labeled_frame is not None:
        lines.append(f"  subjects: {', '.join(session.subjects)}; first labels at frame "
                     f"{session.first_labeled_frame} ({session.first_labeled_frame / rate_hz:.2f} s)")
    else:
        lines.append("  no subject was found: nothing was labeled")
    lines.append(f"  accuracy {_pct(s.accuracy)}   precision {_pct(s.precision)}   ghost false-label rate "
                 f"{_pct(s.ghost_rate)}   ({s.n_true_points} marker points scored from frame "
                 f"{s.first_scored_frame}, mode {session.mode})")
    lat = session.latency_ms
    if len(lat):
        lines.append(f"  end-to-end latency (replay send -> recorder receipt, loopback TCP): p50 "
                     f"{np.percentile(lat, 50):.1f} ms   p99 {np.percentile(lat, 99):.1f} ms   max "
                     f"{lat.max():.1f} ms   over {len(lat)} labels messages")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python3 -m clients.demo", description="Daemon + recorder + synthetic performer, scored.")
    p.add_argument("--duration", type=_positive, default=20.0, metavar="S", help="performance length (20)")
    p.add_argument("--seed", type=int, default=0, help="performer and corruption seed (0)")
    p.add_argument("--level", choices=sorted(LEVELS), default="L2", help="corruption level (L2)")
    p.add_argument("--seeded", action="store_true", help="skip the seedless attempt: labels in the first 2 s")
    p.add_argument("--out", default="out/demo", metavar="DIR", help="where the outputs go (out/demo)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    out_dir = Path(args.out).resolve()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(f"demo: cannot create the output directory {out_dir}: {e.strerror}", file=sys.stderr)
        return 2
    for signum in (signal.SIGINT, signal.SIGTERM):  # explicit: we may have been started with SIGINT ignored
        signal.signal(signum, _raise_interrupt)
    print(f"demo: synthetic performer (seed {args.seed}), {args.duration:g} s, corruption {args.level}; "
          f"outputs in {out_dir}", flush=True)
    try:
        with tempfile.TemporaryDirectory(prefix="mocap-demo-state-") as state, Children() as children:
            print("demo: starting the daemon (the first start compiles the solver; later ones use the cache)",
                  flush=True)
            started = time.monotonic()
            eps = start_daemon(children, Path(state), out_dir / "daemon.log")
            print(f"demo: daemon ready in {time.monotonic() - started:.1f} s on {eps.frames} (frames), "
                  f"{eps.publish} (results), {eps.control} (control)", flush=True)
            kwargs = dict(seed=args.seed, duration_s=args.duration, level=args.level, quiet=args.quiet)
            if not args.seeded:
                print("demo: seedless run: no labels given, the engine must find the performer's T-pose",
                      flush=True)
                session = run_session(children, eps, out_dir, "demo", seeded=False, **kwargs)
                accuracy = session.score.accuracy
                if session.first_labeled_frame is None or not accuracy >= SEEDLESS_MIN_ACCURACY:
                    print(f"demo: seedless initialisation FAILED (accuracy {accuracy:.1%}):\n"
                          f"{report(session, session.rate_hz)}\n"
                          "demo: running again SEEDED: ground-truth labels in the first 2 s", flush=True)
                    reply = control_request(zmq.Context.instance(), eps.control, {"cmd": "reset"}, 5.0)
                    if not (reply and reply.get("ok")):
                        raise DemoError("the daemon did not accept the reset before the seeded run")
                    session = run_session(children, eps, out_dir, "demo_seeded", seeded=True, **kwargs)
            else:
                session = run_session(children, eps, out_dir, "demo_seeded", seeded=True, **kwargs)
            print(f"demo: results ({'seedless, from the T-pose' if session.mode == 'tpose' else 'seeded'}):")
            print(report(session, session.rate_hz))
            print("  outputs: " + ", ".join(str(p.relative_to(out_dir)) for p in session.outputs)
                  + f", daemon.log (in {out_dir})")
            print("demo: stopping", flush=True)
    except KeyboardInterrupt:
        print("demo: interrupted; every process stopped", file=sys.stderr)
        return 130
    except DemoError as e:
        print(f"demo: {e}", file=sys.stderr)
        return 1
    finally:
        zmq.Context.instance().term()
    return 0


if __name__ == "__main__":
    sys.exit(main())
