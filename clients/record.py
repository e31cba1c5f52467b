"""`mocap-record`: subscribe to the daemon's results and write them to files a mocap or animation tool opens.

    mocap-record [--endpoint EP] -o OUT [--duration S] [--frames N] [--idle S] [--quiet]

Writes, when it stops (Ctrl-C/SIGTERM, ``--duration``, ``--frames``, or the stream going quiet for
``--idle`` seconds after results came):
- ``OUT.c3d``: a labeled C3D, every subject's markers as ``Subject:Marker``, one row per frame number
  from the first to the last frame recorded, NaN where a marker was not observed. The rate is inferred
  from the frames' ``t_ns`` (``--rate`` overrides it).
- ``OUT_<subject>.bvh`` for every subject whose skeleton description arrived (`recordings.bvh`: y up,
  centimetres); frames the daemon did not answer hold the previous pose (BVH has no gaps).
- ``OUT.ndjson``: one JSON line per pose message, written as they arrive (a crash loses nothing).
- ``OUT_labels.npz``: per subject the raw labels messages (point indices, frame numbers, ``t_ns`` and
  receive time), so a scorer can map labels back to the points sent (`clients.demo`) and latency can be
  measured; `load_labels` reads it.

A recorder that joins late missed the ``skeleton/<subject>`` messages (published when a subject appears);
it asks the control endpoint to republish them. The live status line (a terminal only) shows subjects,
frame rate, dropped frames (from the daemon's status) and latency = receive time - ``t_ns``, meaningful when
the source stamps ``t_ns`` with this machine's clock (``mocap-replay`` does).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import signal
import sys
import time
from pathlib import Path

import numpy as np
import zmq

from clients.replay import DEFAULT_CONTROL, _non_negative, _Parser, _positive, control_request
from protocol.messages import (
    TOPIC_LABELS,
    TOPIC_POSE,
    TOPIC_SKELETON,
    TOPIC_STATUS,
    Labels,
    Pose,
    ProtocolError,
    Skeleton,
    Status,
    decode,
    encode,
)
from recordings.bvh import BvhMotion, end_sites_from_markers, write_bvh

DEFAULT_ENDPOINT = "tcp://127.0.0.1:7702"
#: a latency outside [0, this) means t_ns is not this machine's wall clock: do not show it [s]
PLAUSIBLE_LATENCY_S = 60.0
#: seconds between two requests for the same missing skeleton, and how many requests at most
SKELETON_RETRY_S = 1.0
SKELETON_MAX_REQUESTS = 10
#: messages taken in one go before the stop conditions are checked again
MAX_BATCH = 1000
#: after a stop by --frames, messages already queued for recorded frames are still taken for this long [s]
DRAIN_S = 0.2


@dataclasses.dataclass
class SubjectLog:
    """Everything recorded for one subject."""

    markers: list[str] = dataclasses.field(default_factory=list)  # union, in first-seen order
    frames: list[int] = dataclasses.field(default_factory=list)  # one entry per labels message
    t_ns: list[int] = dataclasses.field(default_factory=list)
    recv_ns: list[int] = dataclasses.field(default_factory=list)
    columns: list[np.ndarray] = dataclasses.field(default_factory=list)  # (M_k,) index into markers
    point_index: list[np.ndarray] = dataclasses.field(default_factory=list)  # (M_k,)
    positions_m: list[np.ndarray] = dataclasses.field(default_factory=list)  # (M_k, 3)
    poses: dict[int, Pose] = dataclasses.field(default_factory=dict)  # by frame number
    skeleton: Skeleton | None = None

    def add_labels(self, msg: Labels, recv_ns: int) -> None:
        known = {name: i for i, name in enumerate(self.markers)}
        for name in msg.markers:  # a subject re-created under the same name may bring new markers
            if name not in known:
                known[name] = len(self.markers)
                self.markers.append(name)
        self.frames.append(msg.frame)
        self.t_ns.append(msg.t_ns)
        self.recv_ns.append(recv_ns)
        self.columns.append(np.array([known[n] for n in msg.markers], dtype=np.int64))
        self.point_index.append(np.asarray(msg.point_index, dtype=np.int32))
        self.positions_m.append(np.asarray(msg.positions, dtype=np.float32))


class Recorder:
    """Collects decoded result messages; `write` turns them into files. Knows nothing of sockets."""

    def __init__(self) -> None:
        self.subjects: dict[str, SubjectLog] = {}
        self.status: Status | None = None
        self.frames: set[int] = set()  # frame numbers with any result
        self.messages = 0
        self.bad_messages = 0
        self.latencies_s: list[float] = []  # receive time - t_ns of every labels message

    def subject(self, name: str) -> SubjectLog:
        return self.subjects.setdefault(name, SubjectLog())

    def add(self, msg, recv_ns: int) -> None:
        """Take one decoded message received at recv_ns (wall clock)."""
        self.messages += 1
        if isinstance(msg, Labels):
            self.subject(msg.subject).add_labels(msg, recv_ns)
            self.frames.add(msg.frame)
            self.latencies_s.append((recv_ns - msg.t_ns) * 1e-9)
        elif isinstance(msg, Pose):
            self.subject(msg.subject).poses[msg.frame] = msg
            self.frames.add(msg.frame)
        elif isinstance(msg, Skeleton):
            self.subject(msg.subject).skeleton = msg
        elif isinstance(msg, Status):
            self.status = msg

    def missing_skeletons(self) -> list[str]:
        return [name for name, log in self.subjects.items() if log.skeleton is None]

    def rate_hz(self) -> float | None:
        """Capture rate from t_ns [Hz], rounded to 1 mHz.

        The median of (frame step / time step) over consecutive labels rows is robust to restarts and
        gaps; when the whole span agrees with it within 1 %, the span (frames / seconds, first to last) is
        used instead: send-time stamps jitter per frame, but not over the span.
        """
        ratios, spans = [], []
        for log in self.subjects.values():
            frames, t_ns = np.array(log.frames), np.array(log.t_ns, dtype=np.int64)
            order = np.argsort(frames, kind="stable")
            frames, t_ns = frames[order], t_ns[order]
            df, dt = np.diff(frames), np.diff(t_ns)
            ok = (df > 0) & (dt > 0)
            ratios.extend(df[ok] * 1e9 / dt[ok])
            if len(frames) > 1 and t_ns[-1] > t_ns[0]:
                spans.append((frames[-1] - frames[0]) * 1e9 / (t_ns[-1] - t_ns[0]))
        if not ratios:
            return None
        rate = float(np.median(ratios))
        agreeing = [s for s in spans if abs(s - rate) <= 0.01 * rate]
        if agreeing:
            rate = float(np.median(agreeing))
        return round(rate, 3)

    # ------------------------------------------------------------------------------------------ output

    def labeled_points(self) -> tuple[np.ndarray, list[str], int]:
        """(F, N, 3) positions of every subject's markers by frame row, their labels, first frame number."""
        first, last = min(self.frames), max(self.frames)
        labels: list[str] = []
        blocks = []
        for name, log in sorted(self.subjects.items()):
            if not log.frames:
                continue
            block = np.full((last - first + 1, len(log.markers), 3), np.nan, dtype=np.float64)
            for frame, cols, positions in zip(log.frames, log.columns, log.positions_m):
                block[frame - first, cols] = positions
            labels.extend(f"{name}:{marker}" for marker in log.markers)
            blocks.append(block)
        points = np.concatenate(blocks, axis=1) if blocks else np.zeros((last - first + 1, 0, 3))
        return points, labels, first

    def write(self, base: str | Path, rate_hz: float | None = None, say=print) -> list[Path]:
        """Write OUT.c3d, OUT_<subject>.bvh and OUT_labels.npz; returns the paths written."""
        from recordings.c3d import write_c3d

        base = Path(base)
        rate = rate_hz or self.rate_hz() or 120.0
        written = []
        if self.frames:
            points, labels, _ = self.labeled_points()
            path = base.with_name(base.name + ".c3d")
            write_c3d(path, points, labels, rate)
            written.append(path)
        for name, log in sorted(self.subjects.items()):
            if not log.poses:
                continue
            if log.skeleton is None:
                say(f"no skeleton description arrived for {name}: {base.name}_{name}.bvh not written")
                continue
            path = base.with_name(f"{base.name}_{_safe(name)}.bvh")
            write_bvh(path, bvh_motion(log, rate))
            written.append(path)
        path = base.with_name(base.name + "_labels.npz")
        save_labels(path, self, rate)
        written.append(path)
        return written


def _safe(name: str) -> str:
    """A subject name usable in a file name."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "subject"


def bvh_motion(log: SubjectLog, rate_hz: float) -> BvhMotion:
    """A subject's poses as a BVH motion: one frame per frame number, holding the last pose over gaps."""
    skeleton = log.skeleton
    frames = sorted(log.poses)
    n = frames[-1] - frames[0] + 1
    root = np.zeros((n, 3))
    rotations = np.zeros((n, len(skeleton.segments), 4))
    current = log.poses[frames[0]]
    for row in range(n):
        current = log.poses.get(frames[0] + row, current)
        root[row] = current.root_position
        rotations[row] = current.rotations
    return BvhMotion(
        segments=tuple(skeleton.segments),
        parents=tuple(skeleton.parents),
        offsets_m=np.asarray(skeleton.joint_offsets, dtype=float),
        root_positions_m=root,
        rotations_xyzw=rotations,
        rate_hz=rate_hz,
        end_sites_m=end_sites_from_markers(
            len(skeleton.segments), skeleton.parents, skeleton.marker_segment, skeleton.marker_offsets
        ),
    )


def skeleton_from_reply(reply: dict | None) -> Skeleton | None:
    """The description inline in a ``skeleton`` command's reply (the daemon also republishes it), checked
    by a round trip through the wire format; None if absent or malformed."""
    if not reply or not reply.get("ok") or not isinstance(reply.get("skeleton"), dict):
        return None
    d = reply["skeleton"]
    try:
        msg = Skeleton(
            subject=d["subject"], stream=d.get("stream", "default"), segments=list(d["segments"]),
            parents=list(d["parents"]), markers=list(d["markers"]),
            marker_segment=np.asarray(d["marker_segment"], dtype=np.int32),
            marker_offsets=np.asarray(d["marker_offsets_m"], dtype=np.float32),
            joint_offsets=np.asarray(d["joint_offsets_m"], dtype=np.float32),
        )
        return decode(encode(msg))
    except (ProtocolError, KeyError, TypeError, ValueError):
        return None


def pose_json(msg: Pose, recv_ns: int) -> str:
    """One NDJSON line for a pose message (floats rounded to 1e-6: float32 carries no more)."""

    def plain(a):
        return np.round(np.asarray(a, dtype=np.float64), 6).tolist()

    return json.dumps(
        {
            "subject": msg.subject,
            "stream": msg.stream,
            "frame": msg.frame,
            "t_ns": msg.t_ns,
            "recv_ns": recv_ns,
            "root_position_m": plain(msg.root_position),
            "rotations_xyzw": plain(msg.rotations),
            "joint_angles_rad": plain(msg.joint_angles),
        },
        separators=(",", ":"),
    )


@dataclasses.dataclass(frozen=True)
class SubjectLabels:
    """One subject's labels messages as arrays (what `OUT_labels.npz` holds)."""

    markers: tuple[str, ...]  # (M,)
    frames: np.ndarray  # (R,) frame numbers, one row per labels message
    t_ns: np.ndarray  # (R,)
    recv_ns: np.ndarray  # (R,) wall-clock receive time
    point_index: np.ndarray  # (R, M) int32, index into that frame's points, -1 = not observed


def save_labels(path: str | Path, recorder: Recorder, rate_hz: float) -> None:
    arrays: dict[str, np.ndarray] = {"subjects": np.array(list(recorder.subjects), dtype=str),
                                     "rate_hz": np.array(rate_hz)}
    for i, log in enumerate(recorder.subjects.values()):
        index = np.full((len(log.frames), len(log.markers)), -1, dtype=np.int32)
        for row, (cols, idx) in enumerate(zip(log.columns, log.point_index)):
            index[row, cols] = idx
        arrays[f"markers_{i}"] = np.array(log.markers, dtype=str)
        arrays[f"frames_{i}"] = np.array(log.frames, dtype=np.int64)
        arrays[f"t_ns_{i}"] = np.array(log.t_ns, dtype=np.int64)
        arrays[f"recv_ns_{i}"] = np.array(log.recv_ns, dtype=np.int64)
        arrays[f"point_index_{i}"] = index
    np.savez_compressed(path, **arrays)


def load_labels(path: str | Path) -> dict[str, SubjectLabels]:
    """Read `OUT_labels.npz`: subject -> its labels messages."""
    with np.load(path) as z:
        return {
            str(name): SubjectLabels(
                markers=tuple(str(m) for m in z[f"markers_{i}"]),
                frames=z[f"frames_{i}"],
                t_ns=z[f"t_ns_{i}"],
                recv_ns=z[f"recv_ns_{i}"],
                point_index=z[f"point_index_{i}"],
            )
            for i, name in enumerate(z["subjects"])
        }


# ---------------------------------------------------------------------------------------------------- CLI


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="mocap-record", description="Record the daemon's results to C3D, BVH and NDJSON.")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="output base path: writes OUT.c3d, OUT_<subject>.bvh, OUT.ndjson, OUT_labels.npz")
    p.add_argument("--endpoint", default=DEFAULT_ENDPOINT, metavar="EP", help=f"daemon's results endpoint ({DEFAULT_ENDPOINT})")
    p.add_argument("--control", default=DEFAULT_CONTROL, metavar="EP", help=f"daemon's control endpoint ({DEFAULT_CONTROL})")
    p.add_argument("--duration", type=_positive, metavar="S", help="stop after S seconds")
    p.add_argument("--frames", type=int, metavar="N", help="stop after N frames with results")
    p.add_argument("--idle", type=_non_negative, default=5.0, metavar="S",
                   help="stop when no result came for S seconds after the first one (5; 0 = never)")
    p.add_argument("--rate", type=_positive, metavar="HZ", help="rate of the C3D/BVH (default: from t_ns)")
    p.add_argument("--quiet", action="store_true", help="no status line or messages")
    return p


def _status_line(rec: Recorder, recent: list[tuple[float, int]], now_s: float) -> str:
    """subjects | frame rate over the last second | latency | daemon's dropped frames."""
    window = [(t, f) for t, f in recent if now_s - t <= 1.0]
    fps = len(window) / 1.0
    lat = [x for x in rec.latencies_s[-240:] if 0 <= x < PLAUSIBLE_LATENCY_S]
    latency = f"latency p50 {np.median(lat) * 1e3:.1f} ms" if lat else "latency n/a"
    dropped = rec.status.frames_dropped if rec.status else 0
    names = ",".join(rec.subjects) or "none yet"
    return f"subjects {names} | {fps:.0f} fps | {latency} | dropped {dropped} | {len(rec.frames)} frames"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    say = (lambda s: None) if args.quiet else (lambda s: print(f"mocap-record: {s}", file=sys.stderr))
    base = Path(args.output)
    if base.suffix.lower() == ".c3d":
        base = base.with_suffix("")
    if not base.resolve().parent.is_dir():
        print(f"mocap-record: the output directory {base.resolve().parent} does not exist", file=sys.stderr)
        return 2
    if args.frames is not None and args.frames < 1:
        print(f"mocap-record: --frames must be >= 1, got {args.frames}", file=sys.stderr)
        return 2

    stop = {"why": None}

    def on_signal(signum, frame):
        stop["why"] = signal.Signals(signum).name

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    context = zmq.Context()
    sock = context.socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVHWM, 0)  # keep everything: a recorder must not lose results while it writes
    for topic in (TOPIC_LABELS, TOPIC_POSE, TOPIC_SKELETON, TOPIC_STATUS):
        sock.setsockopt(zmq.SUBSCRIBE, topic)
    rec = Recorder()
    ndjson_path = base.with_name(base.name + ".ndjson")
    tty = sys.stderr.isatty() and not args.quiet
    requests: dict[str, tuple[int, float]] = {}  # subject -> (requests sent, last time)
    recent: list[tuple[float, int]] = []  # (receive time, frame) of new frames, for the frame rate
    try:
        try:
            sock.connect(args.endpoint)
        except zmq.ZMQError as e:
            print(f"mocap-record: cannot connect to {args.endpoint}: {e}", file=sys.stderr)
            return 2
        say(f"recording {args.endpoint} to {base}.*")
        start_s = last_result_s = time.monotonic()
        last_line_s = 0.0
        drain_until = None
        try:
            ndjson = open(ndjson_path, "w")
        except OSError as e:
            print(f"mocap-record: cannot write {ndjson_path}: {e.strerror}", file=sys.stderr)
            return 2
        with ndjson:
            while True:
                now_s = time.monotonic()
                if stop["why"] is None:
                    if args.duration and now_s - start_s >= args.duration:
                        stop["why"] = "duration"
                    elif args.idle and rec.frames and now_s - last_result_s >= args.idle:
                        stop["why"] = "idle"
                    elif args.frames and len(rec.frames) >= args.frames:
                        stop["why"] = "frames"
                        drain_until = now_s + DRAIN_S
                if stop["why"] is not None and (drain_until is None or now_s >= drain_until):
                    break
                if sock.poll(100, zmq.POLLIN):
                    for _ in range(MAX_BATCH):  # what is queued (bounded, so the stop checks still run)
                        try:
                            parts = sock.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        recv_ns = time.time_ns()
                        if rec.messages == 0 and rec.bad_messages == 0:
                            say(f"receiving from {args.endpoint}")  # subscribed: a launcher may go on
                        try:
                            msg = decode(parts)
                        except ProtocolError:
                            rec.bad_messages += 1
                            continue
                        frame = getattr(msg, "frame", None)
                        if frame is not None and frame not in rec.frames:
                            if args.frames and len(rec.frames) >= args.frames:
                                continue  # past the frames asked for
                            if tty:
                                recent.append((time.monotonic(), frame))
                        if isinstance(msg, (Labels, Pose)):
                            last_result_s = time.monotonic()
                        rec.add(msg, recv_ns)
                        if isinstance(msg, Pose):
                            ndjson.write(pose_json(msg, recv_ns) + "\n")
                now_s = time.monotonic()
                for name in rec.missing_skeletons():
                    count, last_s = requests.get(name, (0, -math.inf))
                    if count < SKELETON_MAX_REQUESTS and now_s - last_s >= SKELETON_RETRY_S:
                        requests[name] = (count + 1, now_s)
                        reply = control_request(context, args.control, {"cmd": "skeleton", "subject": name}, 0.3)
                        skeleton = skeleton_from_reply(reply)
                        if skeleton is not None:
                            rec.add(skeleton, time.time_ns())
                if tty and now_s - last_line_s >= 0.5:
                    recent = [(t, f) for t, f in recent if now_s - t <= 1.0]
                    print("\r\033[K" + _status_line(rec, recent, now_s), end="", file=sys.stderr, flush=True)
                    last_line_s = now_s
        if tty:
            print(file=sys.stderr)
    finally:
        sock.close()
        context.term()

    if not rec.frames:
        ndjson_path.unlink(missing_ok=True)
        print(f"mocap-record: no results arrived from {args.endpoint} (stopped by {stop['why']}); "
              "nothing written", file=sys.stderr)
        return 1
    try:
        written = rec.write(base, args.rate, say=say) + [ndjson_path]
    except (OSError, ValueError) as e:  # C3DError is a ValueError
        print(f"mocap-record: cannot write the recording to {base}.*: {e}", file=sys.stderr)
        return 1
    lat = [x for x in rec.latencies_s if 0 <= x < PLAUSIBLE_LATENCY_S]
    summary = (f"recorded {len(rec.frames)} frames of {len(rec.subjects)} subject(s) "
               f"({', '.join(sorted(rec.subjects))}), stopped by {stop['why']}")
    if lat:
        summary += f"; latency p50 {np.median(lat) * 1e3:.1f} ms, p99 {np.percentile(lat, 99) * 1e3:.1f} ms"
    if rec.bad_messages:
        summary += f"; {rec.bad_messages} malformed messages dropped"
    print(f"mocap-record: {summary}")
    say("wrote " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    sys.exit(main())
