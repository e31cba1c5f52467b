"""`mocap-replay`: play a recording (or the built-in synthetic performer) into the daemon as `frame` messages,
the way a capture system would stream it: one unordered cloud per frame, paced at the recording's rate.

    mocap-replay [FILE.c3d] [--endpoint EP] [--rate HZ] [--speed X] [--loop] [--keep-labels]
                 [--level L0..L3 | L2-...] [--seed N] [--seed-seconds S] [--truth-out FILE.npz] [--quiet]

What a capture system does, and so what this does:
- **Pacing on an absolute schedule** (frame k leaves at t0 + k / (rate * speed)): sleeping one period per
  frame would add every send's own cost and drift; a frame that leaves more than one period behind its
  slot is counted late, and the ones after it catch up instead of shifting the whole stream.
- **Labels stripped** (the daemon must find them); ``--keep-labels`` streams the file's labels in every frame,
  ``--seed-seconds S`` only in the first S seconds (EVALUATION.md's seeded mode).
- **Unordered clouds**: missing (NaN) samples are left out and every frame is shuffled, so an index carries
  no identity (`recordings.corruption`, level L0 for a file unless ``--level`` says otherwise).
- **No lost first frame**: PUB/SUB drops messages sent before the subscription reaches the publisher, so
  we ping the daemon's control endpoint until it is ready, then wait until its subscription has arrived on
  our socket (an XPUB socket, which is a PUB that also reports subscriptions).

``t_ns`` is the frame's capture time on the wall clock (start time + k / rate, so the recorder infers the
recording's rate whatever ``--speed``); ``--stamp-send-time`` stamps the actual send time instead, so a
subscriber's ``now - t_ns`` is the end-to-end latency.

Without FILE it plays `recordings.synthetic.perform` (a performer who starts in a T-pose) at level L2
(occlusions, noise and ghosts). ``--truth-out`` writes what was sent and the ground truth of every point
(`load_truth` reads it back as a `CorruptedSequence` for `benchmarks.score`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zmq

from protocol.messages import Frame, ProtocolError, decode_reply, encode, encode_request
from recordings.corruption import ALL_LEVELS, CorruptedSequence, corrupt

DEFAULT_ENDPOINT = "tcp://127.0.0.1:7701"
DEFAULT_CONTROL = "tcp://127.0.0.1:7703"
#: how long a closing socket may keep flushing queued frames to the daemon [ms]
LINGER_MS = 2000


class UsageError(Exception):
    """A bad file or flag: main prints the message as one sentence and exits 2."""


# ------------------------------------------------------------------------------------------------ control


def control_request(
    context: zmq.Context, endpoint: str, cmd: dict, timeout_s: float = 1.0
) -> dict | None:
    """One request/reply on the daemon's control endpoint; None if no valid reply came within timeout_s.

    A fresh REQ socket per request: a REQ socket whose reply never came is stuck in its send/recv state
    machine, so it is simply thrown away (ZeroMQ's "lazy pirate" pattern, without the bookkeeping).
    """
    sock = context.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(endpoint)
        sock.send(encode_request(cmd))
        if not sock.poll(int(timeout_s * 1000), zmq.POLLIN):
            return None
        try:
            return decode_reply(sock.recv())
        except ProtocolError:
            return None
    finally:
        sock.close()


def wait_until_ready(context: zmq.Context, control: str, timeout_s: float, say=lambda s: None) -> bool:
    """Ping `control` until the daemon answers ready (warm-up can take seconds); False on timeout."""
    deadline = time.monotonic() + timeout_s
    said = False
    while time.monotonic() < deadline:
        reply = control_request(context, control, {"cmd": "ping"}, timeout_s=min(1.0, timeout_s))
        if reply is not None and reply.get("ok") and reply.get("ready", True):
            return True
        if not said:
            say(f"waiting for the daemon on {control} to be ready...")
            said = True
        time.sleep(0.1)
    return False


def wait_for_subscriber(sock: zmq.Socket, timeout_s: float) -> bool:
    """On an XPUB socket, wait until some subscriber's subscription has arrived (then nothing is lost)."""
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        if sock.poll(int(left * 1000) + 1, zmq.POLLIN):
            message = sock.recv()
            if message[:1] == b"\x01":  # subscribe (b"\x00" would be an unsubscribe)
                return True
    return False


# ------------------------------------------------------------------------------------------------- pacing


class Pacer:
    """Absolute schedule: frame k is due at t0 + k * period; `wait(k)` sleeps until then.

    Returns how late [s] frame k is when it leaves. A late frame does not shift later ones: they keep their
    slots, so the stream's mean rate stays the target rate (no drift) and jitter does not accumulate.
    """

    def __init__(self, rate_hz: float, clock: Callable[[], float] = time.monotonic, sleep=time.sleep):
        self.period_s = 1.0 / rate_hz
        self.clock = clock
        self.sleep = sleep
        self.t0_s: float | None = None

    def wait(self, k: int) -> float:
        now = self.clock()
        if self.t0_s is None:
            self.t0_s = now
        due = self.t0_s + k * self.period_s
        if due > now:
            self.sleep(due - now)
            return 0.0
        return now - due


@dataclasses.dataclass
class ReplayStats:
    """What `stream` did: for the summary line and the tests."""

    frames_sent: int = 0
    frames_late: int = 0  # left more than one period after their slot
    frames_skipped: int = 0  # dropped by the corruption level (L3) and so never sent
    max_late_s: float = 0.0
    elapsed_s: float = 0.0  # first send to last send
    rate_target_hz: float = 0.0

    @property
    def mean_rate_hz(self) -> float:
        """Frames per second over the run (send k=0 to the last send)."""
        if self.frames_sent < 2 or self.elapsed_s <= 0:
            return math.nan
        return (self.frames_sent - 1) / self.elapsed_s

    def summary(self) -> str:
        return (
            f"sent {self.frames_sent} frames in {self.elapsed_s:.2f} s "
            f"(mean {self.mean_rate_hz:.1f} Hz, target {self.rate_target_hz:.1f} Hz), "
            f"{self.frames_late} late (max {self.max_late_s * 1000:.1f} ms)"
            + (f", {self.frames_skipped} dropped by the corruption level" if self.frames_skipped else "")
        )


@dataclasses.dataclass(frozen=True)
class Plan:
    """What to send: the sequence, which frames carry labels, and the timing."""

    seq: CorruptedSequence
    rate_hz: float  # capture rate: t_ns steps of 1 / rate_hz
    speed: float = 1.0  # playback speed factor: frames leave at rate_hz * speed
    labeled_frames: int = 0  # frames at the start of the first pass that carry labels (seeded mode)
    loop: bool = False
    stream: str = "default"
    stamp_send_time: bool = False


def frame_message(plan: Plan, k: int, t0_ns: int) -> Frame | None:
    """The k-th frame of the playback (k counts across loops), or None if the corruption dropped it.

    Frame numbers keep increasing across loops (the contract wants them increasing); the sequence index is
    k mod n_frames.
    """
    n = plan.seq.n_frames
    f = k % n
    points = plan.seq.points_m[f]
    if points is None:
        return None
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1)  # the corruption already leaves NaN out; be sure
    labels = None
    if k < plan.labeled_frames:
        labels = [label for label, ok in zip(plan.seq.true_labels(f), finite) if ok]
    t_ns = t0_ns + round(k * 1e9 / plan.rate_hz)
    return Frame(stream=plan.stream, frame=k, t_ns=t_ns, points=points[finite], labels=labels)


def stream(
    send: Callable[[list[bytes]], None],
    plan: Plan,
    *,
    progress=None,
    clock: Callable[[], float] = time.monotonic,
    sleep=time.sleep,
) -> ReplayStats:
    """Send the plan's frames through `send`, paced by a `Pacer`; stops after one pass unless plan.loop.

    KeyboardInterrupt (Ctrl-C, and SIGTERM in `main`) ends the stream; the stats so far are kept in the
    exception's ``stats`` attribute.
    """
    pacer = Pacer(plan.rate_hz * plan.speed, clock=clock, sleep=sleep)
    stats = ReplayStats(rate_target_hz=plan.rate_hz * plan.speed)
    t0_ns = time.time_ns()
    first_s = last_s = None
    k = 0
    try:
        while plan.loop or k < plan.seq.n_frames:
            message = frame_message(plan, k, t0_ns)
            if message is None:
                stats.frames_skipped += 1
            else:
                late_s = pacer.wait(k)
                if plan.stamp_send_time:
                    message = dataclasses.replace(message, t_ns=time.time_ns())
                send(encode(message))
                last_s = clock()
                first_s = last_s if first_s is None else first_s
                stats.frames_sent += 1
                stats.frames_late += late_s > pacer.period_s
                stats.max_late_s = max(stats.max_late_s, late_s)
            if progress is not None:
                progress.update(1)
            k += 1
    except KeyboardInterrupt as interrupt:
        interrupt.stats = stats
        raise
    finally:
        stats.elapsed_s = (last_s - first_s) if first_s is not None else 0.0
    return stats


# ------------------------------------------------------------------------------------------- the sources


def load_sequence(
    path: str | None,
    *,
    level: str | None,
    seed: int,
    rate_hz: float | None,
    duration_s: float | None,
    up_axis: str | None = None,
) -> CorruptedSequence:
    """The cloud sequence to play: FILE (level L0 by default) or the synthetic performer (level L2).

    Raises UsageError for a file that cannot be read. `duration_s` keeps only the first seconds.
    """
    if path is None:
        from recordings.synthetic import perform

        recording = perform(seed, duration_s=duration_s or 20.0, rate_hz=rate_hz or 120.0).recording
        level = level or "L2"
    else:
        from recordings.c3d import C3DError, read_c3d

        if not Path(path).is_file():
            raise UsageError(f"{path} is not a file")
        try:
            recording = read_c3d(path, up_axis=up_axis)
        except (C3DError, OSError, ValueError, RuntimeError) as e:
            raise UsageError(f"cannot read {path} as C3D: {e}") from None
        if rate_hz:
            recording = dataclasses.replace(recording, rate_hz=rate_hz)
        if duration_s:
            n = max(1, int(round(duration_s * recording.rate_hz)))
            recording = dataclasses.replace(recording, points_m=recording.points_m[:n])
        level = level or "L0"
    if recording.n_frames == 0:
        raise UsageError(f"{path or 'the synthetic performance'} has no frames")
    return corrupt(recording, level, seed)


def save_truth(path: str | Path, plan: Plan, stats: ReplayStats) -> None:
    """Write the sent clouds and their ground truth (ragged per-frame arrays stored flat + offsets).

    Frame numbers on the wire are sequence indices (plus n_frames per loop), so a scorer maps a result's
    frame f to sequence frame f % n_frames.
    """
    seq = plan.seq
    counts = [0 if p is None else len(p) for p in seq.points_m]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    present = [p for p in seq.points_m if p is not None]
    truths = [t for t in seq.truth if t is not None]
    np.savez_compressed(
        path,
        offsets=offsets,
        points_m=np.concatenate(present).reshape(-1, 3) if present else np.zeros((0, 3)),
        truth=np.concatenate(truths).astype(np.int32) if truths else np.zeros(0, np.int32),
        dropped=np.array([p is None for p in seq.points_m]),
        marker_names=np.array(seq.marker_names, dtype=str),
        rate_hz=plan.rate_hz,
        level=seq.level,
        seed=seq.seed,
        source=seq.source,
        labeled_frames=min(plan.labeled_frames, seq.n_frames),
        frames_sent=stats.frames_sent,
    )


def load_truth(path: str | Path) -> tuple[CorruptedSequence, int]:
    """Read `save_truth`'s file: (the sequence as sent, number of leading frames that carried labels)."""
    with np.load(path) as z:
        offsets, dropped = z["offsets"], z["dropped"]
        points, truth = z["points_m"], z["truth"]
        slices = [slice(offsets[f], offsets[f + 1]) for f in range(len(dropped))]
        seq = CorruptedSequence(
            points_m=[None if d else points[s] for d, s in zip(dropped, slices)],
            truth=[None if d else truth[s].astype(np.int64) for d, s in zip(dropped, slices)],
            marker_names=tuple(str(n) for n in z["marker_names"]),
            rate_hz=float(z["rate_hz"]),
            level=str(z["level"]),
            seed=int(z["seed"]),
            source=str(z["source"]),
        )
        return seq, int(z["labeled_frames"])


# ---------------------------------------------------------------------------------------------------- CLI


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad flag as one sentence (no usage dump) and exits 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (see --help)\n")


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="mocap-replay",
        description="Publish a C3D recording (or the synthetic performer) to the daemon as frame messages.",
    )
    p.add_argument("file", nargs="?", metavar="FILE.c3d", help="recording to play (default: synthetic performer)")
    p.add_argument("--endpoint", default=DEFAULT_ENDPOINT, metavar="EP", help=f"daemon's frames endpoint ({DEFAULT_ENDPOINT})")
    p.add_argument("--control", default=DEFAULT_CONTROL, metavar="EP", help=f"daemon's control endpoint ({DEFAULT_CONTROL})")
    p.add_argument("--rate", type=_positive, metavar="HZ", help="capture rate (default: the recording's)")
    p.add_argument("--speed", type=_positive, default=1.0, metavar="X", help="playback speed factor (1)")
    p.add_argument("--loop", action="store_true", help="play again and again until interrupted")
    p.add_argument("--keep-labels", action="store_true", help="send the file's labels with every frame")
    p.add_argument("--seed-seconds", type=_non_negative, default=0.0, metavar="S",
                   help="send labels only in the first S seconds (seeded mode)")
    p.add_argument("--level", choices=list(ALL_LEVELS),
                   help="corruption (default: L0 for a file, L2 synthetic; the L2-... ones are harsher than EVALUATION.md's)")
    p.add_argument("--seed", type=int, default=0, help="random seed of corruption and performer (0)")
    p.add_argument("--duration", type=_positive, metavar="S", help="play only the first S seconds "
                   "(synthetic: its length, default 20)")
    p.add_argument("--up-axis", choices=("x", "y", "z", "-x", "-y", "-z"),
                   help="the file's vertical axis (default: read off the data)")
    p.add_argument("--stream", default="default", help="capture volume id (default)")
    p.add_argument("--stamp-send-time", action="store_true",
                   help="t_ns = send time, so subscribers measure end-to-end latency")
    p.add_argument("--truth-out", metavar="FILE.npz", help="write the sent clouds and their ground truth")
    p.add_argument("--no-wait", action="store_true", help="do not ping the control endpoint first")
    p.add_argument("--wait", type=_positive, default=120.0, metavar="S",
                   help="how long to wait for the daemon to be ready (120)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages, only the summary")
    return p


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    say = (lambda s: None) if args.quiet else (lambda s: print(f"mocap-replay: {s}", file=sys.stderr))
    # Ctrl-C and SIGTERM stop cleanly (explicit: a launcher may have started us with SIGINT ignored).
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _raise_interrupt)
    try:
        seq = load_sequence(args.file, level=args.level, seed=args.seed, rate_hz=args.rate,
                            duration_s=args.duration, up_axis=args.up_axis)
        if args.truth_out and not Path(args.truth_out).resolve().parent.is_dir():
            raise UsageError(f"the directory of --truth-out {args.truth_out} does not exist")
    except UsageError as e:
        print(f"mocap-replay: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # while loading or generating the recording: nothing sent yet
        print("mocap-replay: interrupted before sending", file=sys.stderr)
        return 130
    labeled = seq.n_frames if args.keep_labels else int(round(args.seed_seconds * seq.rate_hz))
    plan = Plan(seq=seq, rate_hz=seq.rate_hz, speed=args.speed, labeled_frames=labeled, loop=args.loop,
                stream=args.stream, stamp_send_time=args.stamp_send_time)

    context = zmq.Context()
    sock = context.socket(zmq.XPUB)
    sock.setsockopt(zmq.LINGER, LINGER_MS)
    stats = ReplayStats()
    interrupted = False
    try:
        try:
            sock.connect(args.endpoint)
        except zmq.ZMQError as e:
            print(f"mocap-replay: cannot connect to {args.endpoint}: {e}", file=sys.stderr)
            return 2
        if not args.no_wait and not wait_until_ready(context, args.control, args.wait, say):
            print(f"mocap-replay: no daemon answered ready on {args.control} within {args.wait:g} s "
                  "(start mocap-service, or pass --no-wait)", file=sys.stderr)
            return 1
        if not wait_for_subscriber(sock, 5.0):
            say(f"nobody subscribed on {args.endpoint} after 5 s; sending anyway")
        source = args.file or f"synthetic performer (seed {args.seed})"
        say(f"playing {source}, {seq.n_frames} frames at {seq.rate_hz:g} Hz x{args.speed:g}, level {seq.level}"
            + (f", labels in the first {labeled} frames" if labeled and not args.keep_labels else "")
            + (", labels kept" if args.keep_labels else ""))
        from tqdm import tqdm

        with tqdm(total=None if args.loop else seq.n_frames, unit="frame", disable=args.quiet,
                  file=sys.stderr, mininterval=0.5, dynamic_ncols=True) as bar:
            stats = stream(sock.send_multipart, plan, progress=bar)
    except KeyboardInterrupt as e:
        stats = getattr(e, "stats", stats)
        interrupted = True
    finally:
        for signum in (signal.SIGINT, signal.SIGTERM):  # a second Ctrl-C must not abandon the clean-up
            signal.signal(signum, signal.SIG_IGN)
        # On a normal end, linger up to LINGER_MS so the last queued frames still reach the daemon.
        context.destroy(linger=0 if interrupted else LINGER_MS)
    print(f"mocap-replay: {stats.summary()}" + (" (interrupted)" if interrupted else ""))
    if args.truth_out:
        save_truth(args.truth_out, plan, stats)
        say(f"ground truth written to {args.truth_out}")
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
