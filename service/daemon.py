"""The realtime daemon (`mocap-service serve`): frames in over ZeroMQ, labels/poses/status out, commands on
a REP socket, all on one thread.

Why one thread and a `zmq.Poller`: the engine is not thread-safe and its work per frame is short, so a
single loop over the frames SUB socket and the control REP socket is the simplest correct design; commands
are served between frames, never concurrently with `Engine.step`.

Backpressure: the SUB socket keeps at most `max_queue_frames` frames (ZeroMQ high-water mark; beyond it
ZeroMQ drops). Each loop turn drains every waiting frame. A backlog the daemon can work through within
CATCH_UP_BUDGET_S (at its recent processing time per frame; at least MAX_BACKLOG_FRAMES of a stream: one
slow frame, a scheduling hiccup) is processed in order, so no frame goes unanswered. A longer one (the
daemon has fallen behind, or a sender stalled and then sent its frames in a burst) is thinned: evenly
spaced frames of it, ending with the newest, are processed and the others counted as dropped ("catching
up", flagged in status). Thinning keeps the latency bounded (working through a long backlog would make
every later frame late too), and the tracker still sees the motion, at a lower rate, instead of a jump:
measured on the synthetic performer (seedless, L2, seed 4), a 2.9 s burst processed as its newest frame
only lost the subject for good, every 8th frame of it left 60 % of the markers labeled, every 3rd 100 %.

Order of publication per frame: every subject's `labels/<subject>` as soon as `Engine.step` returns,
then `Engine.complete` (waits for the skeleton fits launched on this frame's labels, which XLA computed
meanwhile on its own thread) and every `pose/<subject>`. Latency-critical consumers of labels never wait
for a solve.

Start-up: sockets are bound first (a port conflict fails at once), then the engine is created with JAX's
persistent compilation cache enabled and warmed up; only then does the loop run. A client may connect at
any time, but requests are answered only after warm-up, so *any* reply to ``ping`` means ready. Frames
sent during warm-up wait in the queue and the stale ones are dropped as above.

Errors: a malformed frame or request is counted under its reason and dropped (and a request answered
``{"ok": false, "error": ...}``); an exception inside the engine is counted as "engine_error" and logged
once per exception type. Nothing a peer sends stops the daemon. INFO logs only lifecycle events.
"""

from __future__ import annotations

import collections
import gc
import logging
import math
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zmq

from protocol import messages as pm
from protocol.skeleton import PARENTS, SEGMENTS
from service.config import ServiceConfig
from service.engine import FrameInput

log = logging.getLogger(__name__)

#: Processing times kept for the latency percentiles of `status` (a bounded ring: the recent window).
LATENCY_WINDOW = 1024
#: Consecutive frames numbered below the last one after which a stream is taken to have restarted (a
#: replay looping, a capture system restarted) rather than delivering stale frames.
RESTART_AFTER_FRAMES = 8
#: Frames of one stream found waiting that are always all processed, in order, however slow the recent
#: frames were. A step takes ~1.5 ms, so a stall of up to 12 frames (100 ms at 120 Hz: a calibration, a
#: slow solve, the machine busy elsewhere) is worked through within ~2 frame periods and every frame is
#: answered; with 4 (the first setting), the 30-50 ms stalls this shared 2-core machine shows left ~0.5 %
#: of frames unanswered at 120 Hz.
MAX_BACKLOG_FRAMES = 12
#: Processing time [s] a backlog may take before it is thinned (see the module docstring). A loop turn
#: drains at most `max_queue_frames` (64) frames, so at ~2 ms per frame (one subject) a burst is worked
#: through whole, 64 frames a turn (a 2.9 s stall of the sender: nothing dropped, each late frame answered
#: within 0.22 s of its arrival); at ~6 ms (three subjects) every 2nd frame of it is processed.
CATCH_UP_BUDGET_S = 0.25
#: Recent frames whose processing times give the time per frame of a catch-up (their median: one slow
#: frame, a calibration applied, does not make the daemon thin the frames it delayed).
STEP_TIME_WINDOW = 64
#: Longest wait in the poller [s], so a stop request is seen promptly.
POLL_MAX_S = 0.1


def catch_up(frames: list, step_s: float) -> list:
    """The frames of one stream's backlog to process, given the recent processing time per frame: all of
    them when that takes at most CATCH_UP_BUDGET_S (always up to MAX_BACKLOG_FRAMES); otherwise evenly
    spaced ones, as many as that budget affords, ending with the newest."""
    if len(frames) <= MAX_BACKLOG_FRAMES:
        return frames
    affordable = max(MAX_BACKLOG_FRAMES, int(CATCH_UP_BUDGET_S / max(step_s, 1e-3)))
    if len(frames) <= affordable:
        return frames
    stride = math.ceil(len(frames) / affordable)
    return frames[::-1][::stride][::-1]


class DaemonError(RuntimeError):
    """The daemon cannot start (an endpoint cannot be bound); the message says which and why."""


def frame_input(stream: str, frame: int, t_ns: int, points_m, labels) -> FrameInput:
    """The one way a frame becomes engine input, shared by the daemon and `service.offline`.

    Points are rounded to float32 exactly as the wire does, and a label list with no label in it is
    dropped, so the offline labeler and the daemon feed the engine bit-identical input.
    """
    points = np.asarray(points_m, dtype=np.float32).reshape(-1, 3)
    if labels is not None and not any(labels):
        labels = None
    return FrameInput(stream=stream, frame=int(frame), t_ns=int(t_ns), points_m=points,
                      labels=list(labels) if labels is not None else None)


def enable_compilation_cache(cache_dir: str) -> None:
    """Turn on JAX's persistent compilation cache in `cache_dir` ("" = leave it off).

    Must run before the engine compiles anything. Every compilation is cached (minimum compile time 0):
    the solve compiles in ~1-2 s, under JAX's default 1 s threshold on a fast machine, and a warm start is
    the point.
    """
    if not cache_dir:
        return
    import jax  # only here: the daemon module is importable without paying for jax until it runs

    path = Path(cache_dir).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)


def skeleton_message(description: dict) -> pm.Skeleton:
    """`Engine.describe` -> the skeleton/<subject> message."""
    return pm.Skeleton(
        subject=description["subject"],
        stream=description["stream"],
        segments=list(description["segments"]),
        parents=[int(p) for p in description["parents"]],
        markers=list(description["markers"]),
        marker_segment=np.asarray(description["marker_segment"], dtype=np.int32),
        marker_offsets=np.asarray(description["marker_offsets_m"], dtype=np.float32),
        joint_offsets=np.asarray(description["joint_offsets_m"], dtype=np.float32),
        has_skeleton=bool(description.get("has_skeleton", True)),
    )


def label_message(out) -> pm.Labels:
    """One `SubjectOutput` -> its labels/<subject> message."""
    return pm.Labels(
        subject=out.subject, stream=out.stream, frame=out.frame, t_ns=out.t_ns, markers=list(out.markers),
        point_index=out.point_index, positions=out.positions_m, solved=bool(out.solved),
        predicted=out.predicted_m, iterations=int(out.iterations), residual_m=float(out.residual_m),
    )


def pose_message(out) -> pm.Pose:
    """One `SubjectOutput` (completed: `Engine.complete`) -> its pose/<subject> message. Send it only once
    the subject has a calibrated skeleton (`has_pose`): before that the pose is meaningless."""
    return pm.Pose(
        subject=out.subject, stream=out.stream, frame=out.frame, t_ns=out.t_ns, segments=list(SEGMENTS),
        parents=list(PARENTS), root_position=out.root_position_m, rotations=out.rotations_xyzw,
        joint_angles=out.joint_angles_rad,
    )


class Daemon:
    """The service. ``Daemon(config).run(stop_event)`` blocks until `stop_event` is set (or a ``shutdown``
    command), then closes its sockets (linger 0) and saves the subject calibrations.

    Tests run it in a thread: pass endpoints like ``tcp://127.0.0.1:*`` to get free ports, wait for
    `ready`, then read the bound addresses from `endpoints`. `engine` may be given (a test double, or an
    engine already warm); by default a `service.engine.Engine` is built from ``config.engine``.
    """

    def __init__(self, config: ServiceConfig = ServiceConfig(), engine=None) -> None:
        self.config = config
        self.engine = engine
        self.ready = threading.Event()  # set once bound and warmed up
        self.endpoints: dict[str, str] = {}  # "frames", "publish", "control" -> bound address
        self._stop = threading.Event()
        self._ctx: zmq.Context | None = None
        self._started_s = time.monotonic()
        # Counters (status). Rejections by reason; frames dropped only when catching up.
        self.frames_received = 0
        self.frames_processed = 0
        self.frames_dropped = 0
        self.points_received = 0
        self.points_invalid = 0
        self.points_labeled = 0
        self.points_merged = 0
        self.rejected: collections.Counter[str] = collections.Counter()
        self._dropped_at_last_status = 0
        self._latency_s: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)
        self._step_s: collections.deque[float] = collections.deque(maxlen=STEP_TIME_WINDOW)  # sizes catch-ups
        self._last_frame: dict[str, int] = {}  # stream -> last accepted frame number
        self._backwards: collections.Counter[str] = collections.Counter()  # stream -> consecutive old frames
        self._logged_errors: set[str] = set()
        self._save_on_stop = True
        self._has_pose: dict[str, bool] = {}  # subject -> calibrated when last seen (skeleton republished)
        self._frame_seen_s = -float("inf")  # monotonic time of the last frame received (busy polling)

    # ------------------------------------------------------------------------------------------ lifecycle

    def run(self, stop: threading.Event | None = None) -> None:
        """Serve until `stop` is set. Raises DaemonError if an endpoint cannot be bound."""
        stop = stop if stop is not None else threading.Event()
        cfg = self.config
        self._started_s = time.monotonic()
        self._ctx = zmq.Context()
        try:
            self._sub = self._bind(zmq.SUB, "frames", cfg.frames_endpoint)
            self._pub = self._bind(zmq.PUB, "publish", cfg.publish_endpoint)
            self._rep = self._bind(zmq.REP, "control", cfg.control_endpoint)
            self._start_engine()
            self.ready.set()
            log.info("ready: frames %s, publish %s, control %s", self.endpoints["frames"],
                     self.endpoints["publish"], self.endpoints["control"])
            self._loop(stop)
        finally:
            self._close()

    def _bind(self, kind: int, name: str, endpoint: str) -> zmq.Socket:
        sock = self._ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        if kind == zmq.SUB:
            sock.setsockopt(zmq.RCVHWM, max(1, self.config.max_queue_frames))
            sock.setsockopt(zmq.SUBSCRIBE, pm.TOPIC_FRAME)
        elif kind == zmq.PUB:
            # A slow consumer must not grow memory without bound: beyond this many queued messages per
            # subscriber ZeroMQ drops results for that subscriber (2 per subject per frame + status).
            sock.setsockopt(zmq.SNDHWM, 16 * max(1, self.config.max_queue_frames))
        try:
            sock.bind(endpoint)
        except zmq.ZMQError as e:
            sock.close(0)
            raise DaemonError(f"cannot bind the {name} endpoint {endpoint}: {e.strerror}") from None
        self.endpoints[name] = sock.getsockopt_string(zmq.LAST_ENDPOINT)
        return sock

    def _start_engine(self) -> None:
        if self.engine is None:
            enable_compilation_cache(self.config.cache_dir)
            from service.engine import Engine

            self.engine = Engine(self.config.engine)
        try:
            restored = self._state_call("load")
        except Exception as e:  # noqa: BLE001 - a damaged state dir must not keep the service down
            log.error("could not restore subject calibrations from %s (starting without them; they are "
                      "not overwritten on stop, only by an explicit save): %s", self._state_dir(), e)
            self._save_on_stop = False
            restored = []
        if restored:
            log.info("restored %d subject calibration(s) from %s: %s", len(restored), self._state_dir(),
                     ", ".join(restored))
        seconds = self.engine.warm_up()
        log.info("engine warmed up in %.2f s", seconds)
        # Tail latency: what exists after start-up (modules, compiled code) is never scanned by the cyclic
        # collector again, so its pauses stay short...
        gc.collect()
        gc.freeze()
        # ... and the frame loop gets the GIL back within 1 ms, not Python's 5 ms, from the threads that
        # pickle the helper process's jobs and results (`service.worker`).
        sys.setswitchinterval(0.001)

    def _state_dir(self) -> Path:
        return Path(self.config.state_dir).expanduser()

    def _state_call(self, what: str) -> list[str]:
        """engine.save/load on state_dir (created if needed; a missing one loads nothing). Raises what the
        engine raises: the callers decide whether that is a failed command, a log line or a warning."""
        directory = self._state_dir()
        if what == "load" and not directory.is_dir():
            return []
        directory.mkdir(parents=True, exist_ok=True)
        return list(getattr(self.engine, what)(directory))

    def _close(self) -> None:
        """Save calibrations, close every socket at once (linger 0) so the ports are free on return."""
        started = self.ready.is_set()
        if started and self._save_on_stop:
            try:
                saved = self._state_call("save")
                log.info("saved %d subject calibration(s) to %s", len(saved), self._state_dir())
            except Exception as e:  # noqa: BLE001 - stopping must finish (free the ports) whatever happened
                log.error("could not save subject calibrations to %s: %s", self._state_dir(), e)
        self.ready.clear()
        if self._ctx is not None:
            self._ctx.destroy(linger=0)
            self._ctx = None
        if started:
            log.info("stopped")

    # -------------------------------------------------------------------------------------------- loop

    def _loop(self, stop: threading.Event) -> None:
        poller = zmq.Poller()
        poller.register(self._sub, zmq.POLLIN)
        poller.register(self._rep, zmq.POLLIN)
        period_s = self.config.status_period_s
        next_status_s = time.monotonic()
        while not (stop.is_set() or self._stop.is_set()):
            now_s = time.monotonic()
            if now_s >= next_status_s:
                self._publish(pm.encode(self.status()))
                next_status_s = now_s + period_s
            events = self._wait(poller, min(now_s + POLL_MAX_S, next_status_s))
            if self._rep in events:
                self._serve_request()
            if self._sub in events:
                self._serve_frames()

    def _wait(self, poller: zmq.Poller, deadline_s: float) -> dict:
        """The sockets with a message by `deadline_s` (monotonic), {} if none. Within busy_poll_s of the last
        frame, polled without sleeping: a core that slept between frames wakes slow and cold (the same
        frame took ~25 % longer end to end here), so a capture machine may trade one core for latency."""
        spin_until_s = min(self._frame_seen_s + self.config.busy_poll_s, deadline_s)
        while time.monotonic() < spin_until_s:
            events = dict(poller.poll(0))
            if events:
                return events
        return dict(poller.poll(max(0.0, 1000 * (deadline_s - time.monotonic()))))

    def _publish(self, parts: list[bytes]) -> None:
        self._pub.send_multipart(parts, copy=False)

    def _serve_frames(self) -> None:
        """Drain the waiting frames; per stream, process the backlog in order, thinned if it is long
        (`catch_up`)."""
        waiting: dict[str, list[tuple[int, pm.Frame]]] = collections.defaultdict(list)
        for _ in range(max(1, self.config.max_queue_frames)):  # bounded, so requests are served between
            try:
                parts = self._sub.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            received_ns = time.perf_counter_ns()
            self._frame_seen_s = time.monotonic()
            self.frames_received += 1
            frame = self._accept(parts)
            if frame is not None:
                waiting[frame.stream].append((received_ns, frame))
        for frames in waiting.values():
            kept = catch_up(frames, float(np.median(self._step_s)) if self._step_s else 0.0)
            self.frames_dropped += len(frames) - len(kept)
            for received_ns, frame in kept:
                self._process(received_ns, frame)

    def _accept(self, parts: list[bytes]) -> pm.Frame | None:
        """Decode and order-check one frame message; None (counted under its reason) if rejected."""
        try:
            frame = pm.decode(parts, max_points=self.config.engine.max_points)
        except pm.ProtocolError as e:
            self.rejected[e.reason] += 1
            return None
        if not isinstance(frame, pm.Frame):  # unreachable with the b"frame" subscription; kept for safety
            self.rejected["unknown_topic"] += 1
            return None
        last = self._last_frame.get(frame.stream)
        if last is not None and frame.frame <= last:
            if frame.frame == last:
                self.rejected["repeated_frame"] += 1
                return None
            self._backwards[frame.stream] += 1
            if self._backwards[frame.stream] < RESTART_AFTER_FRAMES:
                self.rejected["out_of_order"] += 1
                return None
            log.info("stream %r restarted at frame %d (was at %d)", frame.stream, frame.frame, last)
        self._backwards[frame.stream] = 0
        self._last_frame[frame.stream] = frame.frame
        return frame

    def _process(self, received_ns: int, frame: pm.Frame) -> None:
        started_ns = time.perf_counter_ns()
        try:
            outputs, stats = self.engine.step(
                frame_input(frame.stream, frame.frame, frame.t_ns, frame.points, frame.labels), defer=True
            )
        except Exception as e:  # noqa: BLE001 - the daemon never dies of a frame; counted and logged once
            self._count_error("engine_error", e)
            return
        for subject in stats.new_subjects:  # first, so a consumer can read the labels that follow
            self._publish_skeleton(subject)
        # labels first, as soon as they are known; then the poses, whose fits computed meanwhile
        for out in outputs:
            has_pose = getattr(out, "has_pose", True)
            if has_pose and not self._has_pose.get(out.subject, False):  # calibrated since: new description
                self._publish_skeleton(out.subject)
            self._has_pose[out.subject] = has_pose
            self._publish(pm.encode(label_message(out)))
        try:
            outputs = self.engine.complete(outputs)
        except Exception as e:  # noqa: BLE001 - as for step; the labels are out, only the poses are lost
            self._count_error("engine_error", e)
            outputs = []
        for out in outputs:
            if getattr(out, "has_pose", True):
                self._publish(pm.encode(pose_message(out)))
        try:
            self.engine.between_frames()  # (taking a calibration costs 3-5 ms: not before the messages are out)
        except Exception as e:  # noqa: BLE001 - as for step; the next step does it again
            self._count_error("engine_error", e)
        self.frames_processed += 1
        self.points_received += stats.n_points
        self.points_invalid += stats.n_invalid
        self.points_labeled += stats.n_labeled
        self.points_merged += stats.n_merged
        done_ns = time.perf_counter_ns()
        self._latency_s.append((done_ns - received_ns) * 1e-9)
        self._step_s.append((done_ns - started_ns) * 1e-9)

    def _count_error(self, reason: str, error: Exception) -> None:
        self.rejected[reason] += 1
        key = f"{reason}:{type(error).__name__}"
        if key not in self._logged_errors:  # once per kind: a persistent bug must not flood the log
            self._logged_errors.add(key)
            log.error("%s (counted in status as %r; logged once)", reason, reason, exc_info=error)

    def _publish_skeleton(self, subject: str) -> None:
        try:
            skeleton = skeleton_message(self.engine.describe(subject))
            self._publish(pm.encode(skeleton))
            self._has_pose[subject] = skeleton.has_skeleton
        except Exception as e:  # noqa: BLE001 - a description the protocol cannot carry must not stop us
            self._count_error("skeleton_error", e)

    def status(self) -> pm.Status:
        """The current counters as a status message."""
        if self._latency_s:
            lat_ms = 1e3 * np.asarray(self._latency_s)
            latency = {"p50": float(np.percentile(lat_ms, 50)), "p99": float(np.percentile(lat_ms, 99)),
                       "max": float(lat_ms.max())}
        else:
            latency = {"p50": math.nan, "p99": math.nan, "max": math.nan}
        catching_up = self.frames_dropped > self._dropped_at_last_status
        self._dropped_at_last_status = self.frames_dropped
        return pm.Status(
            t_ns=time.time_ns(),
            frames_received=self.frames_received,
            frames_processed=self.frames_processed,
            frames_dropped=self.frames_dropped,
            rejected=dict(self.rejected),
            subjects=list(self.engine.subjects()) if self.engine is not None else [],
            latency_ms=latency,
            ready=self.ready.is_set(),
            uptime_s=time.monotonic() - self._started_s,
            catching_up=catching_up,
            points_received=self.points_received,
            points_invalid=self.points_invalid,
            points_labeled=self.points_labeled,
            points_merged=self.points_merged,
        )

    # ----------------------------------------------------------------------------------------- control

    def _serve_request(self) -> None:
        """Answer one request; REP requires exactly one reply per request, whatever it held."""
        parts = self._rep.recv_multipart()
        try:
            if len(parts) != 1:
                raise pm.ProtocolError("bad_parts", f"a request is one message part, got {len(parts)}")
            reply = self._command(pm.decode_request(parts[0]))
        except pm.ProtocolError as e:
            self.rejected[f"request:{e.reason}"] += 1
            reply = {"ok": False, "error": f"malformed request ({e}); send a msgpack map with a \"cmd\" string"}
        except _Refused as e:
            reply = {"ok": False, "error": str(e)}
        except Exception as e:  # noqa: BLE001 - a failing command is an answer, never a crash
            self._count_error("command_error", e)
            reply = {"ok": False, "error": f"{type(e).__name__}: {e}"}
        try:
            raw = pm.encode_reply(reply)
        except (TypeError, ValueError) as e:
            raw = pm.encode_reply({"ok": False, "error": f"reply could not be encoded: {e}"})
        self._rep.send(raw)

    def _command(self, request: dict) -> dict:
        cmd = request["cmd"]
        handler = getattr(self, f"_cmd_{cmd}", None)
        if handler is None:
            return {"ok": False, "error": f"unknown command {cmd!r}; valid commands: {', '.join(COMMANDS)}"}
        return handler(request)

    def _subject_arg(self, request: dict, required: bool) -> str | None:
        subject = request.get("subject")
        if subject is None and not required:
            return None
        if not isinstance(subject, str):
            raise _Refused('"subject" must be a subject name string')
        tracked = self.engine.subjects()
        if subject not in tracked:
            raise _Refused(f"unknown subject {subject!r}; tracked subjects: {', '.join(tracked) or 'none'}")
        return subject

    def _cmd_ping(self, request: dict) -> dict:
        return {"ok": True, "ready": self.ready.is_set(), "uptime_s": time.monotonic() - self._started_s,
                "subjects": len(self.engine.subjects())}

    def _cmd_status(self, request: dict) -> dict:
        return {"ok": True, **self.status().as_dict()}

    def _cmd_subjects(self, request: dict) -> dict:
        return {"ok": True, "subjects": list(self.engine.subjects())}

    def _cmd_skeleton(self, request: dict) -> dict:
        subject = self._subject_arg(request, required=True)
        description = self.engine.describe(subject)
        self._publish_skeleton(subject)
        return {"ok": True, "skeleton": description}

    def _cmd_reset(self, request: dict) -> dict:
        subject = self._subject_arg(request, required=False)
        removed = list(self.engine.reset(subject))
        for name in removed:
            self._has_pose.pop(name, None)
        if subject is None:
            self._last_frame.clear()  # a full reset also forgets frame numbering (a new session may start)
            self._backwards.clear()
        log.info("reset: removed %s", ", ".join(removed) or "no subject")
        return {"ok": True, "removed": removed}

    def _cmd_save(self, request: dict) -> dict:
        saved = self._state_call("save")
        log.info("saved %d subject calibration(s) to %s", len(saved), self._state_dir())
        return {"ok": True, "saved": saved, "directory": str(self._state_dir())}

    def _cmd_load(self, request: dict) -> dict:
        loaded = self._state_call("load")
        log.info("loaded %d subject calibration(s) from %s", len(loaded), self._state_dir())
        return {"ok": True, "loaded": loaded, "directory": str(self._state_dir())}

    def _cmd_shutdown(self, request: dict) -> dict:
        log.info("shutdown requested over the control socket")
        self._stop.set()
        return {"ok": True}


class _Refused(Exception):
    """A well-formed command the daemon declines (bad argument); its message is the reply's error."""


COMMANDS = tuple(name[len("_cmd_"):] for name in vars(Daemon) if name.startswith("_cmd_"))
