"""The engine: one registry of tracked subjects for each capture stream, and `Engine.step`, which turns
one unordered frame into labeled markers and poses for every subject.

The per-subject hot path is pure (`service.tracker.step`); this module owns the mutable state: which
subjects exist, their calibrations (`SubjectModel`) and their tracking state, and which points each
subject claimed this frame so no point gets two labels.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import json
import logging
import statistics
import time
import warnings
from pathlib import Path

import numpy as np

from protocol.skeleton import PARENTS, SEGMENTS
from recordings.recording import split_label
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from service import calibration, kernels, layouts, partners, track_state, tracker, worker
from service.config import EngineConfig
from service.kinematics import joint_angles, matrix_to_quat_xyzw
from service.solver import PoseSolver

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class FrameInput:
    """One frame from a capture system, already in metres, z up."""

    stream: str
    frame: int
    t_ns: int
    points_m: np.ndarray  # (N, 3) float
    labels: list[str] | None = None  # N labels "Subject:Marker", "" = unlabeled; seeds or corrects


@dataclasses.dataclass(frozen=True)
class SubjectOutput:
    """What the engine says about one subject for one frame (the labels + pose messages)."""

    subject: str
    stream: str
    frame: int
    t_ns: int
    markers: tuple[str, ...]
    point_index: np.ndarray  # (M,) int32, index into the frame's points, -1 = not observed
    positions_m: np.ndarray  # (M, 3) float32, observed positions, NaN where -1
    predicted_m: np.ndarray  # (M, 3) float32, model position of every marker (fills occlusions)
    solved: bool  # whether the pose optimisation ran this frame
    iterations: int  # Gauss-Newton iterations (0 when skipped)
    residual_m: float  # RMS marker residual of the fit [m] (NaN when skipped)
    root_position_m: np.ndarray  # (3,) float32
    rotations_xyzw: np.ndarray  # (14, 4) float32: root in world, others relative to parent
    joint_angles_rad: np.ndarray  # (13, 3) float32, protocol.skeleton.JOINT_ANGLE_CONVENTION
    has_pose: bool = True  # False until the subject's skeleton is calibrated: publish labels, no pose
    source: np.ndarray | None = None  # (M,) int8: 0 unlabeled, 1 tracked (NNT), 2 re-acquired, 3 given label


@dataclasses.dataclass(frozen=True)
class FrameStats:
    """Per-frame bookkeeping for status counters."""

    n_points: int  # points received
    n_invalid: int  # NaN/inf points dropped
    n_labeled: int  # points given a label by any subject
    n_merged: int  # points left unlabeled as a repeat of another point (EngineConfig.merge_radius_m)
    new_subjects: tuple[str, ...]  # subjects created this frame (publish their skeleton description)


class EngineError(ValueError):
    """A request the engine cannot serve (unknown subject, unreadable calibration); says what is valid."""


HISTORY_FRAMES = 240  # labeled frames kept per subject for (re)calibration
REPEATS_BY_PAIRS = 512  # frames of up to this many points look for repeated points pair by pair, larger ones by k-d tree
REFINE_RMS_M = 0.012  # a skeleton fitting its markers worse than this [m] RMS is re-aligned ...
REFINE_EVERY_FRAMES = 240  # ... at most once per this many frames (then twice as long, ...)
#: A refinement that moves a joint farther than this from where the skeleton had it is not taken: bones do
#: not change length, so its solved poses were wrong (a subject lying prone moved joints by 25-40 cm,
#: Clouthier KneeltoProne at L3).
REFINE_MAX_JOINT_SHIFT_M = 0.1
REFINE_APPLY_S = 1.0  # a refinement started at frame f takes effect this much stream time later (later behind a queue)
LAYOUT_REMEASURE_S = 1.0  # a T-pose subject's marker layouts are measured again on its motion this often (`_maybe_remeasure_layouts`)
#: A seeded subject whose solves miss its markers by more than this [m] RMS on RECALIBRATE_POOR_FRAMES frames
#: is calibrated again from its labeled history (`recalibrated_model`); after one that was refused, not
#: before RECALIBRATE_EVERY_S of stream time (then twice as long, ...). A seed taken with a hand resting on
#: the hip can put the pelvis's markers on the forearm: the skeleton fits while the hand stays there, and
#: misses by 0.3-0.5 m once it moves (both players of the two-player tennis file, in some realizations); the
#: history of the motion since tells the segments apart. (Two-player file, 18 realizations: the worst run's
#: solve residual p90 549 -> 189 mm at L2, 482 -> 125 mm at L3, the second worst 545 -> 81 and 412 -> 110;
#: at 20 frames the worst stayed at 290 / 135 mm. Labels: L2 99.340 -> 99.347 %, L3 97.436 -> 97.477 %, 5
#: runs up, 1 down. Squat at L3, seeds 0-5: residual p90 531 -> 147 and 578 -> 264 mm, labels up.)
RECALIBRATE_RMS_M = 0.08
RECALIBRATE_POOR_FRAMES = 10
RECALIBRATE_EVERY_S = 2.0
#: ... and the new calibration is taken when its solves of the latest RECALIBRATE_JUDGE_FRAMES labeled frames
#: miss the markers by under this share of what the current one's do (mean RMS: the frames the current one
#: misses are the few where the limb moved)
RECALIBRATE_GAIN = 0.5
RECALIBRATE_JUDGE_FRAMES = 40
#: ... unless a bone changes length by more than this [m]: the person is the same (the tennis players' and
#: the squat's recalibrations changed no bone by more than 1 and 4 cm; KneeltoProne's, from its kneeling
#: and prone frames, by 4-8 cm)
RECALIBRATE_MAX_BONE_CHANGE_M = 0.05
#: ... nor when the subject is not standing now (its latest frame under this tall [m], as `calibration` asks of
#: an upright person): KneeltoProne, calibrated again from the frames of its going prone, kept no better fit
#: (520-750 -> 740-830 mm p90) and lost 0.6 % of one run's labels
RECALIBRATE_MIN_HEIGHT_M = 1.0
#: ... but a subject lying on the floor (`calibration.lying_rotations`) is calibrated again, stood up, from
#: the frames in which it has held still (its markers' median distance from their latest places under
#: RECALIBRATE_LYING_STILL_M), once it has done so for RECALIBRATE_LYING_STILL_S (and at least
#: RECALIBRATE_LYING_MIN_FRAMES frames), with bones of its own: a seed that knelt gave the template's
#: straight legs the height of the top marker (KneeltoProne's subject, 1.18 m tall), which held while it
#: knelt and missed the markers by 0.35-0.66 m once it lay prone; calibrated again there, its solves
#: fit them to 6-25 mm in 11 of 12 realizations at L2 and L3 (60 mm in one; median over its last 0.6 s).
RECALIBRATE_LYING_STILL_M, RECALIBRATE_LYING_STILL_S, RECALIBRATE_LYING_MIN_FRAMES = 0.02, 0.25, 24
RECALIBRATE_CATCH_UP_SOLVES = 4  # solves of the latest frame from the current pose (then one a frame)
CALIBRATE_CATCH_UP_SOLVES = 2  # solves that bring a calibration's pose up to the frame it takes effect
#: A calibration started at frame f takes effect this much stream time later (later behind a queue,
#: `_schedule`), counted in the subject's frames. In seconds, not frames: 60 frames, right at 120 Hz, left a
#: 50 Hz serve without a skeleton for 1.2 s after the seed, and the serving arm's labels, tracked alone
#: through the serve, came out permuted and stayed so (tennis, two players, at L2). Longer costs labels: at
#: 0.9 s the dev suite lost 0.16 +- 0.07 points at L3 (-0.03 at L2; the basketball player -0.59, the two
#: players -0.31 at L3); and a calibration queued behind another counted 0.8 s (its p99 below) cost the two
#: players 0.05 (L2) and 0.10 points (L3). So a calibration that runs long on a loaded machine (p50 0.40 s,
#: p90 0.54 s below) makes the frame that takes it wait.
CALIBRATE_APPLY_S = 0.5
#: ... a recalibration (`recalibrated_model`) this much: taken 0.5 s after it started, as a calibration, the
#: frame that took it waited 0.25-0.46 s for it (the subject scan's two subjects: p99 9.8 ms, max 71-507 ms)
RECALIBRATE_APPLY_S = 1.2
#: What one job of each kind may take in the helper process [s] (`_schedule`): a job is taken no sooner than
#: the budgets of the jobs queued before it and its own from its start. Measured (the own time of each job,
#: run inline in 2 benchmark processes on the 2 cores: the dev suite's 8 files and 03_rolling seeded, HDM_mm
#: and squat in T-pose mode, L2/L3, seeds 0-2): calibrations p50 0.40, p99 0.70, max 0.87 s (80 jobs);
#: refinements p50 0.25, max 0.81 s (222); recalibrations max 0.83 s (4), 0.75-0.96 s beside the daemon's
#: paced frame loop (cmu/135_02: a calibration from the history and a kneeling one, and 2 x 40 judging
#: solves); layout measurements max 37 ms (292). (Every job counted 0.45 s before; at 0.3 the frame that took
#: the second and third subjects' calibrations waited 70-250 ms; at 0.2 the two players gained 0.09 points at
#: L3, but the subject scan's 8 subjects went from 84 to 178 ms p99.)
JOB_BUDGET_S = {"calibration": CALIBRATE_APPLY_S, "refinement": 0.8, "recalibration": RECALIBRATE_APPLY_S,
                "layouts": 0.05}
DISCOVER_FRAMES = 60  # frames an unexplained point must ride on an automatic subject to become a marker
DISCOVER_REFIND_Z = 3.0  # ... unless it keeps a lost marker's distances to its partners this well (`_lost_marker_of`)
#: (`_name_mirrors`) a free point this near a named marker's mirror image may be its twin (the tennis
#: player's RBHD sat 2.5-2.8 cm from LBHD's; an unnamed point of HDM_mm 3.1-3.6 cm from RBAC's: a thin
#: margin, so the looks below must agree too), looked for every 3rd frame, on the last frame's state (not to
#: hold up the labels' publication), and is, once it has ridden on the body there MIRROR_FRAMES looks
#: (a ghost track near the body did for 10 at L2; none for 15 in the 288 + 48 runs of benchmarks.realizations)
MIRROR_GATE_M = 0.03
MIRROR_EVERY_FRAMES = 3
MIRROR_FRAMES = 15
MIRROR_REACH_M = 0.3
#: Subjects are given phases 0..PHASES-1 (`tracker.new_state`), so the tracker's periodic work (every 2nd,
#: 3rd, 4th frame) falls on different frames for different subjects: 12 covers every period it uses.
PHASES = 12


@dataclasses.dataclass
class _Subject:
    stream: str
    model: track_state.SubjectModel
    state: track_state.TrackState
    history: collections.deque  # of (M, 3) labeled positions, NaN = unlabeled
    next_calibration_frame: int = 0
    pose_cache: tuple | None = None  # (R_parent_segment it was made from, quaternions, joint angles)
    next_refine_frame: int = 0
    refine_interval: int = 0  # frames between skeleton refinements (doubles each time)
    refine_job: tuple | None = None  # (future, frame to apply it at, kind): `_schedule`
    calibration_job: tuple | None = None  # (future, frame to apply it at, kind)
    auto: bool = False  # created from a T-pose: its markers are its own, and it may discover more
    candidates: list = dataclasses.field(default_factory=list)  # unexplained point tracks: [last frame, positions]
    trial: _Trial | None = None  # a subject just found in a T-pose, until its window ends (`_Trial`)
    mirrors: list | None = None  # a labeled subject's markers its names imply but its seed never showed (`_name_mirrors`)
    mirrors_of: np.ndarray | None = None  # the marker offsets `mirrors` were placed by (a refinement moves them)
    mirror_tracks: dict = dataclasses.field(default_factory=dict)  # their candidate points: {name: [last look, track]}
    mirror_look: tuple | None = None  # (frame, points, free) of a frame `_name_mirrors` is to look at
    poor_fit_frames: int = 0  # frames whose latest fit missed by more than RECALIBRATE_RMS_M, since the last look
    next_recalibration_frame: int = 0
    recalibration_interval: int = 0  # frames between recalibrations (doubles each time)
    between_frame: int = -1  # the state's frame count `_between_frames` last ran at
    layout_job: tuple | None = None  # (future, frame to apply it at, kind): a T-pose subject's layouts remeasured
    next_layout_frame: int = 0


@dataclasses.dataclass
class _StreamClock:
    """The time the tracker runs on for one stream: the frame's stamp when it agrees with the stream's frame
    period (a capture system's clock), else the last time plus the frames elapsed times the median period.
    A stamp taken at send time jitters, and a burst after a stall puts frames microseconds apart: their
    motion over that dt would read as enormous speeds and accelerations."""

    frame: int
    stamp_ns: int
    t_ns: int
    periods_ns: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=31))

    def tick(self, frame: int, stamp_ns: int) -> int:
        if frame > self.frame:
            df = frame - self.frame
            self.periods_ns.append((stamp_ns - self.stamp_ns) / df)
            period = statistics.median(self.periods_ns)  # 31 floats: 4 us, np.median 80 us
            expected = self.t_ns + df * period
            self.t_ns = stamp_ns if abs(stamp_ns - expected) <= 0.25 * period else int(expected)
            self.frame, self.stamp_ns = frame, stamp_ns
        return self.t_ns


@dataclasses.dataclass
class _Trial:
    """A subject found in a T-pose is labeled from that frame on, on trial for a window
    (`EngineConfig.tpose_window_frames`): meanwhile the free points that appear on it (markers hidden when
    it was found) are tracked still, and at the window's end those seen in 40 % of it join the subject, and
    the T-pose is checked again with all its markers, on the window's most complete frame and on its last:
    a subject that did not hold it is dropped. (Before, the subject was made at the window's end: in T-pose
    mode HDM_mm lost its first 0.5 s, 2 points of accuracy.)"""

    tracks: list = dataclasses.field(default_factory=list)  # per point track: [(subject frame count, position)]
    frames: int = 0


class Engine:
    """Registry of subjects per stream; see the module docstring."""

    def __init__(self, config: EngineConfig = EngineConfig()):
        self.config = config
        self.solver = PoseSolver(
            config.max_markers, config.solver_max_steps, config.solver_rtol, config.prior_weight, config.solver_atol
        )
        self._subjects: dict[str, _Subject] = {}
        self._clocks: dict[str, _StreamClock] = {}
        self._auto_count = 0
        self._phases: dict[str, int] = {}  # subject -> its phase (`_phase`)
        self._stepped: list[str] = []  # the subjects the last `step` tracked (`between_frames`)
        # what a helper process needs to build the same solver (`refined_model`)
        self._solver_spec = (config.max_markers, config.solver_max_steps, config.solver_rtol, config.prior_weight,
                             config.solver_atol)

    # ---------------------------------------------------------------- lifecycle
    def warm_up(self) -> float:
        """Compile the jitted solve and FK for every padded size, and the tracker's compiled loops (or load
        them from their persistent caches)."""
        t0 = time.perf_counter()
        helper = self._worker().submit(_warm_solver, self._solver_spec)  # the helper process compiles beside us
        kernels.warm_up()
        self.solver.warm_up()
        try:
            helper.result()
        except worker.WorkerError as e:  # it is started again with the next job; refinements wait on it then
            log.warning("the helper process could not warm up: %s", e)
        return time.perf_counter() - t0

    def subjects(self) -> list[str]:
        return list(self._subjects)

    def reset(self, subject: str | None = None) -> list[str]:
        if subject is None:
            names = list(self._subjects)
            self._subjects.clear()
            self._phases.clear()
            return names
        if subject not in self._subjects:
            raise EngineError(f"no subject {subject!r}; subjects: {', '.join(self._subjects) or 'none'}")
        del self._subjects[subject]
        self._phases.pop(subject, None)  # its phase is free for the next subject
        return [subject]

    def describe(self, subject: str) -> dict:
        if subject not in self._subjects:
            raise EngineError(f"no subject {subject!r}; subjects: {', '.join(self._subjects) or 'none'}")
        s = self._subjects[subject]
        m = s.model
        return {
            "subject": m.name,
            "stream": s.stream,
            "segments": list(SEGMENTS),
            "parents": list(PARENTS),
            "markers": list(m.markers),
            "marker_segment": np.asarray(m.marker_segment, np.int32),
            "marker_offsets_m": np.asarray(m.marker_offsets_m, np.float32),
            "joint_offsets_m": np.asarray(m.joint_offsets_m, np.float32),
            "has_skeleton": m.has_skeleton,
        }

    def save(self, directory) -> list[str]:
        """Write every subject's calibration (and last known marker positions) to `directory`."""
        d = Path(directory).expanduser()
        d.mkdir(parents=True, exist_ok=True)
        for name, s in self._subjects.items():
            m = s.model
            tracker.collect(m, s.state)
            np.savez(
                d / f"{name}.npz",
                meta=json.dumps({"name": name, "stream": s.stream, "markers": list(m.markers), "has_skeleton": m.has_skeleton}),
                marker_segment=m.marker_segment, marker_offsets_m=m.marker_offsets_m, joint_offsets_m=m.joint_offsets_m,
                pos_m=s.state.pos_m, ever_seen=s.state.ever_seen, t_root_m=s.state.t_root_m, R_parent_segment=s.state.R_parent_segment,
                dist_n=s.state.dist_n, dist_mean_m=s.state.dist_mean_m, dist_var_m2=s.state.dist_var_m2,
                dist_slow_mean_m=s.state.dist_slow_mean_m, dist_slow_var_m2=s.state.dist_slow_var_m2,
                **({} if m.layout_rms_m is None else {"layout_offsets_m": m.layout_offsets_m, "layout_rms_m": m.layout_rms_m}),
            )
        return list(self._subjects)

    def load(self, directory) -> list[str]:
        """Restore calibrations saved by `save`; tracking resumes where each subject was last seen."""
        d = Path(directory).expanduser()
        loaded = []
        for f in sorted(d.glob("*.npz")) if d.is_dir() else []:
            try:
                with np.load(f) as z:
                    meta = json.loads(str(z["meta"]))
                    model = track_state.SubjectModel(
                        meta["name"], tuple(meta["markers"]), z["marker_segment"], z["marker_offsets_m"], z["joint_offsets_m"],
                        bool(meta["has_skeleton"]),
                        # files written before the layout check have no layout: the check stays off for them
                        z["layout_offsets_m"] if "layout_offsets_m" in z.files else None,
                        z["layout_rms_m"] if "layout_rms_m" in z.files else None,
                    )
                    pos = np.where(z["ever_seen"][:, None], z["pos_m"], np.nan)
                    st = tracker.new_state(model, pos, 0, phase=self._phase(model.name))
                    st.labeled[:] = False
                    st.dist_n, st.dist_mean_m, st.dist_var_m2 = z["dist_n"], z["dist_mean_m"], z["dist_var_m2"]
                    # files written before the long-memory statistics start them from the running ones
                    slow = ("dist_slow_mean_m", "dist_slow_var_m2") if "dist_slow_mean_m" in z.files else ("dist_mean_m", "dist_var_m2")
                    st.dist_slow_mean_m, st.dist_slow_var_m2 = z[slow[0]].copy(), z[slow[1]].copy()
                    partners._update_partners(st)
                    st.t_root_m, st.R_parent_segment = z["t_root_m"], z["R_parent_segment"]
            except (OSError, KeyError, ValueError) as e:
                raise EngineError(f"calibration file {f} is unreadable: {e}") from None
            self._subjects[model.name] = _Subject(meta["stream"], model, st, collections.deque(maxlen=HISTORY_FRAMES))
            loaded.append(model.name)
        return loaded

    # ---------------------------------------------------------------- the frame loop
    def step(self, frame: FrameInput, defer: bool = False) -> tuple[list[SubjectOutput], FrameStats]:
        """Label one frame. Non-finite points are dropped and counted; labels of the wrong length ignored.
        With `defer`, the subjects' layout checks, state updates and solve launches are left to `complete`
        (or to the next step), so the labels can be published sooner; the labels are the same either way."""
        stamp_ns = frame.t_ns
        clock = self._clocks.get(frame.stream)
        if clock is None or frame.frame <= clock.frame:  # a new stream, or one that restarted
            clock = self._clocks[frame.stream] = _StreamClock(frame.frame, frame.t_ns, frame.t_ns)
        frame = dataclasses.replace(frame, t_ns=clock.tick(frame.frame, frame.t_ns))
        outputs, stats = self._step(frame, defer)
        if frame.t_ns != stamp_ns:
            outputs = [dataclasses.replace(o, t_ns=stamp_ns) for o in outputs]
        return outputs, stats

    def _step(self, frame: FrameInput, defer: bool = False) -> tuple[list[SubjectOutput], FrameStats]:
        pts = np.ascontiguousarray(frame.points_m, dtype=np.float64).reshape(-1, 3)
        keep = kernels.finite_rows(pts)
        n_invalid = len(pts) - len(keep)
        points = pts[keep]
        to_frame = np.append(keep, -1).astype(np.int32)  # a point's index in the frame as sent (-1, none: -1)
        labels = frame.labels if frame.labels is not None and len(frame.labels) == len(pts) else None
        free = np.ones(len(points), bool)
        repeats = _repeats(points, self.config.merge_radius_m)
        free[repeats] = False
        outputs: list[SubjectOutput] = []
        new_subjects: list[str] = []
        given: dict[str, dict[str, int]] = {}
        if labels is not None:
            for j, i in enumerate(keep):
                lab = labels[i].strip() if isinstance(labels[i], str) else ""
                if lab and not lab.split(":")[-1].startswith("*"):
                    subj, marker = split_label(lab)
                    given.setdefault(subj or "subject", {})[marker] = j
        for name, marks in given.items():
            s, created = self._labeled_subject(frame, name, marks, points)
            if created:
                new_subjects.append(name)
            free[list(marks.values())] = False
            outputs.append(self._observe(s, frame, points, marks, to_frame, append=not created))
        order = self._in_order(n for n, s in self._subjects.items() if s.stream == frame.stream and n not in given)
        self._stepped = order
        for name in order:
            s = self._subjects[name]
            self._between_frames(s)  # (done already if the last frame was completed)
            s.state, res = tracker.step(s.model, s.state, points, free, frame.t_ns, self.config, self.solver, defer=True)
            free[res.point_index[res.point_index >= 0]] = False
            s.history.append(res.positions_m)
            outputs.append(self._output(s, frame, res, to_frame))
        if not defer:  # after every subject has labeled the frame, deferred or not: the same labels either way
            for name in order:
                tracker.finish(self._subjects[name].state)
        if labels is None:
            for name in order:
                s = self._subjects[name]
                if s.auto:
                    tracker.finish(s.state)
                    if s.trial is not None:
                        self._judge(s, frame, points, free)
                    else:
                        self._discover(s, frame, points, free)
                elif s.model.has_skeleton:
                    s.mirror_look = (frame, points, free.copy())  # (looked at between frames: `_between_frames`)
        if self.config.tpose_auto and labels is None:
            for name in self._find_tposes(frame, points, free):
                new_subjects.append(name)
                s = self._subjects[name]
                s.state, res = tracker.step(s.model, s.state, points, free, frame.t_ns, self.config, self.solver)
                free[res.point_index[res.point_index >= 0]] = False
                s.history.append(res.positions_m)
                outputs.append(self._output(s, frame, res, to_frame))
        n_labeled = int(sum(int((o.point_index >= 0).sum()) for o in outputs))
        return outputs, FrameStats(len(pts), n_invalid, n_labeled, len(repeats), tuple(new_subjects))

    def _labeled_subject(self, frame, name, marks, points):
        s = self._subjects.get(name)
        new = [m for m in marks if s is None or m not in s.model.markers]
        if s is not None and not new:
            return s, False
        old = () if s is None else s.model.markers
        markers = (old + tuple(sorted(new)))[: self.config.max_markers]
        m = len(markers)
        model = track_state.SubjectModel(name, markers, np.zeros(m, int), np.zeros((m, 3)), np.zeros((14, 3)), False)
        hist = collections.deque(maxlen=HISTORY_FRAMES)
        if s is not None:
            for h in s.history:
                hist.append(np.concatenate([h, np.full((m - len(h), 3), np.nan)]))
        cur = _positions(markers, marks, points)
        hist.append(cur)
        st = tracker.new_state(model, cur, frame.t_ns, np.stack(hist), phase=self._phase(name))
        s = _Subject(frame.stream, model, st, hist, next_calibration_frame=0)
        self._subjects[name] = s
        return s, True

    def _observe(self, s: _Subject, frame, points, marks, to_frame, append: bool) -> SubjectOutput:
        tracker.collect(s.model, s.state)
        cur = _positions(s.model.markers, marks, points)
        if append:
            s.history.append(cur)
        if not s.model.has_skeleton and len(s.history) >= HISTORY_FRAMES:
            self._maybe_calibrate(s)
        s.state, res = tracker.observe(s.model, s.state, cur, frame.t_ns, self.config, self.solver)
        idx = np.array([marks.get(m, -1) for m in s.model.markers], np.int32)
        res = dataclasses.replace(res, point_index=idx)
        return self._output(s, frame, res, to_frame)

    def _phase(self, name: str) -> int:
        """The subject's phase: kept for its life (a subject rebuilt with new markers keeps it); a new one
        takes the phase fewest current subjects have, the lowest first (a lone subject runs at phase 0)."""
        if name not in self._phases:
            used = collections.Counter(self._phases.values())  # the current subjects' (reset frees them)
            self._phases[name] = min(range(PHASES), key=lambda k: (used[k], k))
        return self._phases[name]

    def _maybe_calibrate(self, s: _Subject) -> None:
        """Fit a skeleton once an upright pose is in the labeled history; retry every second if not. The
        work (50-300 ms, more with many markers) runs in the helper process (`service.worker`), like
        refinement, and takes effect CALIBRATE_APPLY_S of stream time after it started (waiting for it then
        if need be): the frame loop does not stall on it, and `label` and the daemon give the same labels."""
        if s.calibration_job is not None:
            future, apply_at, _ = s.calibration_job
            if s.state.frames < apply_at:
                return
            s.calibration_job = None
            result = _result(future, "calibration")
            if result is None or len(result[0]) != len(s.model.markers):
                return
            seg, off, joints, t_root, R, layout = result
            s.model = dataclasses.replace(s.model, marker_segment=seg, marker_offsets_m=off, joint_offsets_m=joints,
                                          has_skeleton=True, layout_offsets_m=off, layout_rms_m=layout)
            s.state.t_root_m, s.state.R_parent_segment = t_root, R
            layouts.learn_layout_trust(s.model, s.state, np.stack(s.history))
            # bring the calibration pose (of a frame CALIBRATE_APPLY_S back) up to now on the latest
            # labels: several solves, as one of max_steps iterations can stop short of a limb that moved
            last = s.history[-1]
            for _ in range(CALIBRATE_CATCH_UP_SOLVES):
                fit = tracker._fit(s.model, s.state, self.solver, last, np.isfinite(last[:, 0]))
                if fit is None or fit.residual_rms_m < 0.01:
                    break
            return
        if s.model.has_skeleton or s.state.frames < s.next_calibration_frame or len(s.history) < 12:
            return
        s.next_calibration_frame = s.state.frames + 120
        s.calibration_job = self._schedule(s, "calibration", CALIBRATE_APPLY_S, history_calibration,
                                           self._solver_spec, np.stack(s.history),
                                           calibration.mirror_index(s.model.markers))

    def _maybe_refine(self, s: _Subject) -> None:
        """Re-align the skeleton to the recent labeled history when it fits the markers poorly (the
        calibration pose hid the joints: a joint shows where it is only when it bends); calibrate a seeded
        subject again when it misses them by decimetres (`_maybe_recalibrate`).

        The work (0.1-0.5 s) runs in the helper process (`service.worker`), off the frame loop, and its
        result is applied exactly REFINE_APPLY_S of stream time (in frames) after it was started — waiting
        for it then if need be — so the daemon never stalls and `mocap-service label` gives the same labels as the daemon,
        frame for frame. Intervals double after each refinement (backoff) so a subject whose markers wobble
        on the skin does not keep the helper busy."""
        st = s.state
        if s.refine_job is not None:
            future, apply_at, _ = s.refine_job
            if st.frames < apply_at:
                return
            s.refine_job = None
            model = _result(future, "refinement or recalibration")
            if isinstance(model, tuple):  # a recalibration taken (`recalibrated_model`): the next may follow
                self._take_recalibration(s, *model)  # as soon as the fit is poor again
                s.recalibration_interval, s.next_recalibration_frame = 0, 0
                return
            if model is not None and len(model.markers) == len(s.model.markers):
                s.model = model
                last = s.history[-1]
                tracker._fit(s.model, st, self.solver, last, np.isfinite(last[:, 0]))
            return
        if not s.model.has_skeleton or self._maybe_recalibrate(s):
            return
        if st.frames < s.next_refine_frame or not st.fit_rms_m > REFINE_RMS_M:
            return
        s.refine_interval = min(2 * s.refine_interval, 20 * REFINE_EVERY_FRAMES) if s.refine_interval else REFINE_EVERY_FRAMES
        s.next_refine_frame = st.frames + s.refine_interval
        s.refine_job = self._schedule(s, "refinement", REFINE_APPLY_S,
                                      functools.partial(refined_model, measure_joints=not s.auto), self._solver_spec,
                                      s.model, np.stack(s.history), st.t_root_m.copy(), st.R_parent_segment.copy())

    def _maybe_remeasure_layouts(self, s: _Subject) -> None:
        """A subject found in its T-pose had its segments' marker layouts measured on that pose, held still:
        it bends no joint, so a segment given markers from both sides of one (a straight arm's elbow and
        wrist markers, all on the upper arm) reads as rigid to a millimetre, and the layout check
        (`layouts._relabel_by_shape`) takes the joint, once bent, for permuted labels. Every
        LAYOUT_REMEASURE_S the motion since measures them again on its own labels (the only ones it has;
        `calibration.layout_residuals`, in the helper process, applied REFINE_APPLY_S of stream time later
        as a refinement is), and each marker keeps the worse of its residuals: a marker a bend moved in its
        segment leaves the check for good. (Squat in tpose mode at L2, seed 1: the right upper arm's four
        labels misfit its T-pose layout by 46-53 mm against 1.7 mm measured still, the check cycled them,
        and they stayed so for the remaining 12 s.) A seeded subject's layouts are measured on the given
        labels of its seed, which moved: they are left alone."""
        model, st = s.model, s.state
        job = s.layout_job
        if job is not None:
            if st.frames >= job[1]:
                s.layout_job = None
                bent = _result(job[0], "layout measurement")
                was = model.layout_rms_m
                if bent is not None and was is not None and len(bent) == len(was):
                    s.model = dataclasses.replace(model, layout_rms_m=np.where(np.isfinite(bent), np.maximum(was, bent), was))
            return
        if not s.auto or not model.has_skeleton or model.layout_rms_m is None or st.frames < s.next_layout_frame:
            return
        s.next_layout_frame = st.frames + self._frames(s, LAYOUT_REMEASURE_S)
        hist = np.stack(s.history)
        hist[:, ~np.isfinite(model.layout_rms_m)] = np.nan  # out of the check already (a marker a refinement moved)
        s.layout_job = self._schedule(s, "layouts", REFINE_APPLY_S, calibration.layout_residuals, hist,
                                      model.marker_segment, model.layout_offsets_m)

    def _maybe_recalibrate(self, s: _Subject) -> bool:
        """Start a recalibration (`recalibrated_model`, in the helper process, in the refinement's job slot)
        once a seeded subject's fit has missed by more than RECALIBRATE_RMS_M on RECALIBRATE_POOR_FRAMES
        frames; True if one was started."""
        st = s.state
        s.poor_fit_frames += bool(st.fit_rms_m > RECALIBRATE_RMS_M)
        if s.auto or s.poor_fit_frames < RECALIBRATE_POOR_FRAMES or st.frames < s.next_recalibration_frame:
            return False
        still = max(self._frames(s, RECALIBRATE_LYING_STILL_S), RECALIBRATE_LYING_MIN_FRAMES)
        if not _calibratable_now(np.stack(list(s.history)[-still:])):
            # the poor frames are kept: it is tried once the subject stands, or lies still, which is looked
            # at again a quarter of RECALIBRATE_LYING_STILL_S later (a look costs ~0.3 ms)
            s.next_recalibration_frame = st.frames + max(1, still // 4)
            return False
        s.poor_fit_frames = 0
        s.recalibration_interval = (2 * s.recalibration_interval if s.recalibration_interval
                                    else self._frames(s, RECALIBRATE_EVERY_S))
        s.next_recalibration_frame = st.frames + s.recalibration_interval
        s.refine_job = self._schedule(s, "recalibration", RECALIBRATE_APPLY_S, recalibrated_model, self._solver_spec,
                                      s.model, np.stack(s.history), calibration.mirror_index(s.model.markers),
                                      st.t_root_m.copy(), st.R_parent_segment.copy())
        return True

    def _take_recalibration(self, s: _Subject, model, t_root: np.ndarray, R: np.ndarray) -> None:
        """Take a recalibration (`recalibrated_model`): its pose is of the frame it was started on, so the
        latest labels are solved from it and from the current pose, which holds wherever the segments kept
        their markers, and the better fit stands. Its layouts are trusted as a calibration's are
        (`layouts.learn_layout_trust`, over the history it was made from)."""
        if len(model.markers) != len(s.model.markers):
            return
        st, last = s.state, s.history[-1]
        lab = np.isfinite(last[:, 0])
        best, kept = None, (st.t_root_m, st.R_parent_segment, st.fit_rms_m)
        for start in ((st.t_root_m, st.R_parent_segment), (t_root, R)):
            st.t_root_m, st.R_parent_segment = start
            fit = None
            for _ in range(RECALIBRATE_CATCH_UP_SOLVES):
                fit = tracker._fit(model, st, self.solver, last, lab) or fit
            if fit is not None and (best is None or fit.residual_rms_m < best[0]):
                best = (fit.residual_rms_m, st.t_root_m, st.R_parent_segment)
        if best is None:  # neither start solved: the old calibration stays, and its pose
            st.t_root_m, st.R_parent_segment, st.fit_rms_m = kept
            return
        s.model = model
        layouts.learn_layout_trust(model, st, np.stack(s.history))
        _, st.t_root_m, st.R_parent_segment = best
        st.fit_rms_m = best[0]

    def _schedule(self, s: _Subject, kind: str, apply_s: float, fn, *args) -> tuple:
        """Submit a helper job of `kind` (JOB_BUDGET_S) for subject s: (future, frame to take it at, kind).
        It is taken `apply_s` of stream time from now, or later behind a queue: the helper runs its jobs one
        at a time, so it is done within the budgets of the jobs queued before it plus its own (three
        subjects seeded together at 120 Hz, their calibrations all taken at one frame, stalled the frame
        loop for 0.25 s waiting on the third). Counted from the jobs' schedule, not their progress (a job
        done but not yet taken still counts: the estimate errs late, never early), so `label` and the
        daemon take each result at the same frame."""
        queued = sum(JOB_BUDGET_S[job[2]] for o in self._subjects.values()
                     for job in (o.calibration_job, o.refine_job, o.layout_job) if job is not None)
        delay = max(self._frames(s, apply_s), self._frames(s, queued + JOB_BUDGET_S[kind]))
        return self._worker().submit(fn, *args), s.state.frames + delay, kind

    @staticmethod
    def _frames(s: _Subject, seconds: float) -> int:
        """`seconds` of stream time in subject s's frames (at least 1), from its last frame interval."""
        dt = max(s.state.acc_dt_s, 1e-3) if s.state.acc_dt_s > 0 else 1.0 / 120  # one just found has no interval yet
        return max(1, round(seconds / dt))

    def _worker(self):
        return worker.shared()

    def _find_tposes(self, frame, points, free) -> list[str]:
        """Automatic initialisation: a group of free points in a T-pose becomes a subject at once, on trial
        (`_Trial`); one at a time per stream."""
        if frame.frame % 4 or any(s.trial is not None for s in self._subjects.values() if s.stream == frame.stream):
            return []
        groups = calibration.detect_tpose(points, free)
        if not groups:
            return []
        g = groups[0][: self.config.max_markers]
        self._auto_count += 1
        name = f"S{self._auto_count}"
        while name in self._subjects:
            self._auto_count += 1
            name = f"S{self._auto_count}"
        markers = tuple(f"M{j:02d}" for j in range(len(g)))
        m = len(markers)
        model = track_state.SubjectModel(name, markers, np.zeros(m, int), np.zeros((m, 3)), np.zeros((14, 3)), False)
        st = tracker.new_state(model, points[g], frame.t_ns, phase=self._phase(name))
        self._subjects[name] = s = _Subject(frame.stream, model, st, collections.deque(maxlen=HISTORY_FRAMES), auto=True)
        s.trial = _Trial()
        s.next_calibration_frame = st.frames + self.config.tpose_window_frames + 1  # after the trial
        return [name]

    def _judge(self, s: _Subject, frame, points, free) -> None:
        """One frame of a subject's trial (`_Trial`): track the free points on it with a tight gate (the
        person stands still); at the window's end, add the points seen long enough and check the T-pose."""
        trial, st = s.trial, s.state
        # its hidden markers first: a subject this young has no rigid partners (partners.PARTNER_MIN_SAMPLES)
        # to find them by, and a marker back from a moment's occlusion would start a track of its own
        lost = np.flatnonzero(st.ever_seen & ~st.labeled)
        last = np.vstack([st.pos_m[lost]] + [t[-1][1][None] for t in trial.tracks])
        idx = np.flatnonzero(free)
        body = st.pos_m[st.ever_seen]
        lo, hi = body.min(0) - 0.3, body.max(0) + 0.3
        idx = idx[np.all((points[idx] > lo) & (points[idx] < hi), axis=1)]
        used = np.zeros(len(idx), bool)
        if len(idx) and len(last):
            d = np.linalg.norm(last[:, None] - points[idx][None], axis=2)
            r, c = linear_sum_assignment(np.where(d < 0.02, d, 1e6))
            ok = d[r, c] < 0.02
            r, c = r[ok], c[ok]
            used[c] = True
            back = r < len(lost)
            tracker.resume(st, lost[r[back]], points[idx[c[back]]])
            s.history[-1][lost[r[back]]] = points[idx[c[back]]]
            for ti, pj in zip(r[~back] - len(lost), c[~back]):
                trial.tracks[ti].append((st.frames, points[idx[pj]]))
        trial.tracks += [[(st.frames, points[j])] for j in idx[~used]]
        trial.frames += 1
        if trial.frames < self.config.tpose_window_frames:
            return
        s.trial = None
        found = len(s.model.markers)
        joining = [t for t in trial.tracks if len(t) >= 0.4 * trial.frames][: self.config.max_markers - len(s.model.markers)]
        if joining:
            self._add_markers(s, frame, joining)
        # (the T-pose is judged on the markers it was found with: a ghost track that lived long enough to
        # join can take the arms off level, and the subject was dropped and found again at once, under new
        # ids, its first 0.5 s of labels lost to the score: squat in tpose mode at L2, seed 0, 86.6 -> 89.5 %)
        hist = np.stack(s.history)[:, :found]
        if not (calibration.is_tpose(calibration.fill_reference(hist)) and
                calibration.is_tpose(calibration.fill_reference(hist, frame=len(hist) - 1))):
            log.info("%s: did not hold its T-pose for its first %d frames; dropped", s.model.name, trial.frames)
            del self._subjects[s.model.name]
            self._phases.pop(s.model.name, None)
            return
        s.next_calibration_frame = 0

    def _discover(self, s: _Subject, frame, points, free) -> None:
        """Markers hidden while a subject stood in its T-pose join it later: an unclaimed point that stays
        near the subject for DISCOVER_FRAMES frames, keeping its distances to the subject's nearest markers
        (it rides on the body: a ghost drifts, and lives 0.08 s on average), becomes a new marker, unless
        it is one of the subject's own lost markers (`_lost_marker_of`), which is then tracked on."""
        st = s.state
        if not st.labeled.any() or len(s.model.markers) >= self.config.max_markers:
            s.candidates.clear()
            return
        body = st.pos_m[st.labeled]
        idx = np.flatnonzero(free)
        if len(idx):
            near = np.min(np.linalg.norm(points[idx, None] - body[None], axis=2), axis=1) < 0.25
            idx = idx[near]
        f = st.frames
        cands = [c for c in s.candidates if f - c[0] <= 3]  # a track may miss up to 3 frames
        used = np.zeros(len(idx), bool)
        if cands and len(idx):
            last = np.array([c[1][-1][1] for c in cands])
            d = np.linalg.norm(last[:, None] - points[idx][None], axis=2)
            r, c = linear_sum_assignment(np.where(d < 0.04, d, 1e6))
            for ri, ci in zip(r, c):
                if d[ri, ci] < 0.04:
                    cands[ri][0] = f
                    cands[ri][1].append((f, points[idx[ci]], st.pos_m.copy(), st.labeled.copy()))
                    used[ci] = True
        for ci in np.flatnonzero(~used):
            cands.append([f, [(f, points[idx[ci]], st.pos_m.copy(), st.labeled.copy())]])
        s.candidates = cands
        for c in cands:
            track = c[1]
            if len(track) < DISCOVER_FRAMES:
                continue
            if self._rides_on_body(track):
                lost = _lost_marker_of(st, track)
                if lost is not None:  # one of its own, back: tracked on under its id
                    if c[0] == f:
                        tracker.resume(st, np.array([lost]), track[-1][1][None])
                    s.candidates = [o for o in cands if o is not c]
                    return
                self._add_markers(s, frame, [track])
                s.candidates = []  # their snapshots have the old marker count
                return
            del track[: len(track) - DISCOVER_FRAMES]  # keep testing the most recent window

    def _name_mirrors(self, s: _Subject, frame, points, free) -> None:
        """A labeled subject's marker hidden through its whole seed has a name nowhere to learn from, but
        its mirror image often has one: a point that rides on the body where LBHD's image across the
        sagittal plane is, for MIRROR_FRAMES looks, and where no marker of the subject was last, becomes
        RBHD (`calibration.mirrored_markers`). (Tennis serve, L2: RBHD hidden through the 2 s seed of one
        corrupted realization was never labeled in its 755 frames in view.)"""
        st, model = s.state, s.model
        if s.mirrors is None or s.mirrors_of is not model.marker_offsets_m:
            # placed anew whenever the model changes: a refinement that moves a segment's origin (its joint
            # measured, `calibration.functional_joints`) moves its markers' offsets, and an image placed
            # before sat 6 cm off (tennis serve, L2, seed 13: RBHD went unlabeled for 755 frames in view)
            s.mirrors = calibration.mirrored_markers(model.markers, model.marker_segment, model.marker_offsets_m,
                                                     1.5 * MIRROR_GATE_M)
            s.mirrors_of = model.marker_offsets_m
        if not s.mirrors or not st.labeled.any():
            return
        idx = np.flatnonzero(free)
        if not len(idx):
            return
        # where its segment's labeled markers place each image (the last fit's pose can be 10 frames old,
        # and lagged a head 5-17 cm behind in a tennis serve); two markers, with the joint where the fit is.
        # Only for images with a free point within MIRROR_REACH_M of where that fit puts them (most frames
        # have none: 0.09 ms a look on 135_02 with every image placed, 41 markers)
        pose = (st.t_root_m, st.R_parent_segment, model.joint_offsets_m)
        Rs, ps = kernels.world_transforms(*(np.require(a, np.float64, "CW") for a in pose), track_state._PARENTS)
        by_fit = np.array([Rs[k] @ off + ps[k] for _, k, off in s.mirrors])
        reach = np.linalg.norm(points[idx, None] - by_fit[None], axis=2).min(0) < MIRROR_REACH_M
        where = np.full_like(by_fit, np.nan)
        for r in np.flatnonzero(reach):
            _, k, off = s.mirrors[r]
            lab = np.flatnonzero((model.marker_segment == k) & st.labeled)
            if len(lab) >= 2:
                a, b = model.marker_offsets_m[lab], st.pos_m[lab]
                if len(lab) == 2:
                    a, b = np.vstack([a, np.zeros(3)]), np.vstack([b, ps[k]])
                R, t = track_state.rigid_motion(a, b)
                where[r] = R @ off + t
        d = np.linalg.norm(points[idx, None] - where[None], axis=2)
        near = d.min(0) < MIRROR_GATE_M
        if not near.any():
            return
        # not where a marker of the subject was last (one back from hiding, not yet re-acquired)
        known = st.pos_m[st.ever_seen]
        f = st.frames
        tracks = {n: c for n, c in s.mirror_tracks.items() if f - c[0] <= 4 * MIRROR_EVERY_FRAMES}  # (may miss 3 looks)
        for r in np.flatnonzero(near):
            j = idx[int(np.argmin(d[:, r]))]
            if len(known) and np.min(np.linalg.norm(known - points[j], axis=1)) < MIRROR_GATE_M:
                continue
            name = s.mirrors[r][0]
            entry = (f, points[j], st.pos_m.copy(), st.labeled.copy())
            c = tracks.get(name)
            if c is not None and np.linalg.norm(c[1][-1][1] - points[j]) < 2 * MIRROR_GATE_M:  # (moved since)
                c[0] = f
                c[1].append(entry)
            else:
                c = tracks[name] = [f, [entry]]
            track = c[1]
            if len(track) >= MIRROR_FRAMES:
                if self._rides_on_body(track):
                    self._add_markers(s, frame, [track], [s.mirrors[r][:2]])
                    return
                del track[: len(track) - MIRROR_FRAMES]  # keep testing the most recent window
        s.mirror_tracks = tracks

    @staticmethod
    def _rides_on_body(track) -> bool:
        """The track keeps its distance to its 3 nearest subject markers within 8 mm over the window."""
        _, p0, pos0, lab0 = track[0]
        _, p1, pos1, lab1 = track[-1]
        both = np.flatnonzero(lab0 & lab1)
        if len(both) < 3:
            return False
        near = both[np.argsort(np.linalg.norm(pos0[both] - p0, axis=1))[:3]]
        spread = []
        for _, p, pos, lab in track:
            ok = lab[near]
            if ok.sum() == 3:
                spread.append(np.linalg.norm(pos[near] - p, axis=1))
        if len(spread) < 0.7 * len(track):
            return False
        return bool(np.all(np.std(np.array(spread), axis=0) < 0.008))

    def complete(self, outputs: list[SubjectOutput]) -> list[SubjectOutput]:
        """`outputs` of the last `step` with the pose of their own frame. `step` returns as soon as the
        labels are known, with the pose of the latest completed fit. This does the frame's deferred
        bookkeeping, which launches the fits on its labels (computed on XLA's thread), for every subject
        before waiting for any fit, so each fit computes beside the others' bookkeeping; then it waits for
        them. So labels can be published first and poses right after; the labels are the same either way."""
        subjects = [self._subjects.get(out.subject) for out in outputs]
        for s in subjects:
            if s is not None:
                tracker.finish(s.state)
        done = []
        for out, s in zip(outputs, subjects):
            if s is None or not out.solved:
                done.append(out)
                continue
            tracker.collect(s.model, s.state)
            st = s.state
            done.append(dataclasses.replace(out, iterations=st.fit_iterations, residual_m=st.fit_rms_m, **self._pose_fields(s)))
        return done

    def between_frames(self) -> None:
        """The work the subjects tracked by the last `step` have between frames (`_between_frames`): the
        daemon calls it once a frame's labels and poses are out; else the next `step` does it before
        labeling. The labels are the same either way."""
        for name in self._in_order(n for n in self._stepped if n in self._subjects):
            self._between_frames(self._subjects[name])

    def _in_order(self, names) -> list[str]:
        """Subjects in the order they label a frame: the latest labeled first."""
        return sorted(names, key=lambda n: -self._subjects[n].state.last_labeled_t_ns)

    def _between_frames(self, s: _Subject) -> None:
        """A subject's work between its frames, once: the last frame's look for mirror images
        (`_name_mirrors`, on the state that frame left), then take the helper's calibration or refinement
        when it is due (blocking solves that bring its pose up to the latest labels: 3-5 ms, more for a
        recalibration) and start the next one. `between_frames` does it once a frame's messages are out,
        else the next `step` does it before labeling; the state is the same either way (the frame count it
        checks moves only in a step). Done in `step` alone, the frame that took a calibration published its labels 5-9 ms
        late, and three or more subjects seeded together (their calibrations taken 0.45 s apart) missed the
        subject scan's 8.3 ms p99."""
        tracker.collect(s.model, s.state)  # the last frame's fit, before anything reads the pose
        look, s.mirror_look = s.mirror_look, None
        if look is not None and s.state.frames % MIRROR_EVERY_FRAMES == 0:
            # (on the state the frame left, whether its bookkeeping was deferred or not: before, a deferred
            # step looked on the frames of another phase and the daemon named markers on other frames than
            # `label`; and off the labels' path)
            self._name_mirrors(s, *look)
        st = s.state
        if s.between_frame == st.frames:
            return
        s.between_frame = st.frames
        self._maybe_calibrate(s)
        self._maybe_refine(s)
        self._maybe_remeasure_layouts(s)

    @staticmethod
    def _pose_fields(s: _Subject) -> dict:
        st = s.state
        # quaternions and angles change only when a solve ran: convert once per solve, not per frame
        if s.pose_cache is None or s.pose_cache[0] is not st.R_parent_segment:
            s.pose_cache = (
                st.R_parent_segment,
                matrix_to_quat_xyzw(st.R_parent_segment).astype(np.float32),
                joint_angles(st.R_parent_segment).astype(np.float32),
            )
        _, quats, angles = s.pose_cache
        return dict(root_position_m=np.asarray(st.t_root_m, np.float32), rotations_xyzw=quats, joint_angles_rad=angles)

    def _add_markers(self, s: _Subject, frame, tracks, named: list[tuple[str, int]] | None = None) -> None:
        """Grow a subject by the markers of these point tracks ([(frame count, position, ...)], the last
        entry of this frame or earlier), keeping the tracking state: each under its own next id on the
        segment of the nearest marker, or under the (name, segment) `named` gives it."""
        tracker.collect(s.model, s.state)  # the pose of the fit in flight, before the state is rebuilt
        old = s.state
        markers, seg, off = list(s.model.markers), list(s.model.marker_segment), list(s.model.marker_offsets_m)
        cur = [np.where(old.labeled[:, None], old.pos_m, np.nan)]
        f0 = old.frames - len(s.history) + 1
        cols = []
        if s.model.has_skeleton:
            Rs, ps = calibration.world_transforms(old.t_root_m, old.R_parent_segment, s.model.joint_offsets_m)
        for n, track in enumerate(tracks):
            f, p_new = track[-1][0], track[-1][1]
            seg.append(0)
            off.append(np.zeros(3))
            if named is not None:
                name, seg[-1] = named[n]
            else:
                name = f"M{len(markers):02d}"
                while name in markers:
                    name = name + "b"
                if s.model.has_skeleton:  # ride on the segment of the nearest marker
                    seg[-1] = s.model.marker_segment[int(np.argmin(np.linalg.norm(old.pos_m - p_new, axis=1)))]
            if s.model.has_skeleton:  # at its current offset
                off[-1] = Rs[seg[-1]].T @ (p_new - ps[seg[-1]])
            markers.append(name)
            cur.append((p_new if f == old.frames else np.full(3, np.nan))[None])
            recent = {e[0]: e[1] for e in track}
            cols.append(np.array([recent.get(f0 + k, np.full(3, np.nan)) for k in range(len(s.history))]))
        n = len(tracks)
        seg, off = np.array(seg), np.array(off)
        hist = collections.deque((np.concatenate([h, np.array([c[k] for c in cols])]) for k, h in enumerate(s.history)),
                                 maxlen=HISTORY_FRAMES)
        layout = {}
        if s.model.layout_rms_m is not None:  # the new markers' places in the layout are not measured
            layout = dict(layout_rms_m=np.append(s.model.layout_rms_m, np.full(n, np.nan)),
                          layout_offsets_m=np.vstack([s.model.layout_offsets_m, off[-n:]]))
        model = dataclasses.replace(s.model, markers=tuple(markers), marker_segment=seg, marker_offsets_m=off, **layout)
        cur = np.vstack(cur)
        st = tracker.new_state(model, cur, frame.t_ns, np.stack(hist))
        st.t_root_m, st.R_parent_segment = old.t_root_m, old.R_parent_segment
        st.frames, st.last_labeled_t_ns = old.frames, old.last_labeled_t_ns
        st.labeled = np.isfinite(cur[:, 0])
        s.model, s.state = model, st
        s.history = hist
        # the mirror images and their candidate tracks are of the old marker count (a track's snapshots
        # compared with the grown model's crashed the engine: two markers named by their images in turn)
        s.mirrors, s.mirror_tracks = None, {}

    def _output(self, s: _Subject, frame, res: tracker.StepResult, to_frame) -> SubjectOutput:
        idx = to_frame[res.point_index]  # back to the frame's own indexing (non-finite points dropped)
        positions = res.positions_m.astype(np.float32)
        return SubjectOutput(
            subject=s.model.name,
            stream=s.stream,
            frame=frame.frame,
            t_ns=frame.t_ns,
            markers=s.model.markers,
            point_index=idx,
            positions_m=positions,
            predicted_m=np.asarray(res.predicted_m, np.float32),
            solved=res.solved,
            iterations=res.iterations,
            residual_m=res.residual_m,
            **self._pose_fields(s),
            has_pose=s.model.has_skeleton,
            source=res.source,
        )


def _lost_marker_of(st, track, n_looks: int = 12) -> int | None:
    """The subject's own marker, unlabeled now, that a point riding on its body is (`_discover`), if one
    is clearly: the one whose long-run distances to its most rigid partners the point keeps best over the
    track (median z of `partners._misfit_at`, over n_looks of its frames, under DISCOVER_REFIND_Z, and
    under half the next best's). A marker lost while in view (its fit misplaced it) was otherwise found
    again as a new marker: two ids for one marker for the rest of the run (HDM_mm in tpose mode at L3:
    a right foot's three markers, 900-1000 frames each). (Tpose mode, seeds 6-17: HDM_mm L3 93.48 ->
    93.92 %, L2 95.88 -> 95.95 %; squat L3 87.61 -> 87.86 %, L2 unchanged; seeds 0-5 up or unchanged.)"""
    lost = np.flatnonzero(st.ever_seen & ~st.labeled)
    if not len(lost) or len(track[0]) < 4 or len(track[-1][2]) != len(st.labeled):
        return None
    looks = track[:: max(1, len(track) // n_looks)]
    z = np.array([[partners._misfit_at(st, k, p, pos, lab) for _, p, pos, lab in looks] for k in lost])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a marker with no partners labeled: all NaN
        z = np.nanmedian(z, axis=1)
    z = np.where(np.isfinite(z), z, np.inf)
    order = np.argsort(z)
    best = z[order[0]]
    if best < DISCOVER_REFIND_Z and (len(z) == 1 or z[order[1]] > 2.0 * best):
        return int(lost[order[0]])
    return None


def _result(future, what: str):
    """A helper-process job's result, or None (logged) if the helper failed it: the subject goes on with the
    skeleton it has, and the job is tried again on schedule."""
    try:
        return future.result()
    except worker.WorkerError as e:
        log.warning("%s failed in the helper process: %s", what, e)
        return None


_SOLVERS: dict[tuple, PoseSolver] = {}


def _solver(spec: tuple) -> PoseSolver:
    """The PoseSolver(*spec) of this (helper) process, built and compiled once."""
    if spec not in _SOLVERS:
        _SOLVERS[spec] = PoseSolver(*spec)
    return _SOLVERS[spec]


def _warm_solver(spec: tuple) -> None:
    _solver(spec).warm_up()


def history_calibration(solver_spec: tuple, hist: np.ndarray, mirror_of: np.ndarray):
    """`calibration.calibrate_from_history` of a subject's labeled history (F, M, 3), its candidates judged
    by this solver's solves too (`calibration.SOLVE_GAIN`). Pure, for the helper process."""
    return calibration.calibrate_from_history(hist, mirror_of, _solver(solver_spec))


def refined_model(solver_spec: tuple, model, hist, t0, R0, n_frames: int = 40, rounds: int = 2, measure_joints: bool = True):
    """A better skeleton for `model` from labeled history (F, M, 3): the limb joints the history turned are
    measured from their segments' own motions (`calibration.functional_joints`); then poses of up to
    n_frames frames are solved with the model, markers move to the segment that carries them best, and the
    least-squares alignment gives new offsets; twice. (Squat, seeds 0-5: L3 99.39 -> 99.74 %, its solves'
    residual p90 60 -> 26 mm; a 41-marker set's limb segments seldom show 3 markers, and the dev suite
    hardly moved.) Not with `measure_joints` False (the engine's T-pose subjects: their segments were given
    their markers on a pose that bent no joint, and a marker across a joint from its bone blends two bones'
    motions into its segment's; squat in tpose mode, L2, seed 1: a wrist pair then swapped for 604 frames,
    99.47 -> 98.92 %). Pure (no engine state), so it can run in the helper process.
    None if the history is too thin or its poses were wrong (REFINE_MAX_JOINT_SHIFT_M). `solver_spec`: the arguments of the PoseSolver it solves with (the helper
    process builds its own, once)."""
    solver = _solver(solver_spec)
    good = np.flatnonzero(np.isfinite(hist[..., 0]).sum(1) >= 8)
    good = good[good >= len(hist) - 3 * n_frames]  # the recent past: it shows the motion that calls for this
    if len(good) < 12:
        return None
    pick = good[np.linspace(0, len(good) - 1, min(n_frames, len(good))).astype(int)]
    marker_segment0, layout_rms_m = model.marker_segment, model.layout_rms_m
    # the joints the history turned are measured first, from the segments' own motions (no pose solve can
    # mislead that); the poses below are solved on them, and the guard leaves them alone
    if measure_joints:
        rigid = None if model.layout_rms_m is None else model.layout_rms_m < track_state.SHAPE_LAYOUT_TOL_M
        off, joints, _ = calibration.functional_joints(hist, model.marker_segment, model.marker_offsets_m,
                                                       model.joint_offsets_m, rigid)
        model = dataclasses.replace(model, marker_offsets_m=off, joint_offsets_m=joints)
    joints0 = model.joint_offsets_m
    frames = hist[pick]
    for _ in range(rounds):
        ts, Rs, _ = _solve_newest_first(solver, model, frames, t0, R0)
        Rw, pw = calibration.world_transforms(ts, Rs, model.joint_offsets_m)
        seg = calibration.reassign(frames, Rw, pw, model.marker_segment)
        off = model.marker_offsets_m.copy()
        moved = seg != model.marker_segment
        if moved.any():  # a moved marker starts from its mean position in its new segment
            local = np.einsum("fmji,fmj->fmi", Rw[:, seg], frames - pw[:, seg])
            off[moved] = np.nanmean(local[:, moved], axis=0)
        off, joints = calibration.refine(frames, Rs, seg, off, model.joint_offsets_m)
        model = dataclasses.replace(model, marker_segment=seg, marker_offsets_m=off, joint_offsets_m=joints)
    if np.linalg.norm(model.joint_offsets_m - joints0, axis=1).max() > REFINE_MAX_JOINT_SHIFT_M:
        return None  # the poses it solved were wrong, not the skeleton (see REFINE_MAX_JOINT_SHIFT_M)
    # the layout is vouched for by the calibration's frames (given labels, in seeded mode), never by the
    # engine's own labels, which may hold the very permutations the layout check is there to undo: a
    # marker that changed segment here loses its say
    layout = None if layout_rms_m is None else np.where(model.marker_segment == marker_segment0, layout_rms_m, np.nan)
    return dataclasses.replace(model, layout_rms_m=layout)


def _still_since(hist: np.ndarray) -> int:
    """The first frame of labeled history (F, M, 3) from which the subject holds its latest pose: its
    markers' median distance from their latest places stays under RECALIBRATE_LYING_STILL_M."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames with no marker seen
        off_last = np.nanmedian(np.linalg.norm(hist - hist[-1], axis=2), axis=1)
    moved = ~(off_last < RECALIBRATE_LYING_STILL_M)  # (NaN: nothing to compare, not still)
    return int(np.flatnonzero(moved)[-1] + 1) if moved.any() else 0


def _calibratable_now(recent: np.ndarray) -> bool:
    """Whether a subject whose latest labeled frames are `recent` (F, M, 3), oldest first, may be calibrated
    again from its history: it stands (RECALIBRATE_MIN_HEIGHT_M tall), or lies on the floor and has held
    still through `recent` (at least RECALIBRATE_LYING_MIN_FRAMES frames). Going down, rolling over or
    crouched it is neither, and a calibration would be refused (the try is not made, nor counted)."""
    last = recent[-1]
    seen = np.isfinite(last[:, 0])
    if seen.sum() < 8:
        return False
    if np.ptp(last[seen, 2]) >= RECALIBRATE_MIN_HEIGHT_M:
        return True
    return (len(recent) >= RECALIBRATE_LYING_MIN_FRAMES and bool(calibration.lying_rotations(last))
            and _still_since(recent) == 0)


def recalibrated_model(solver_spec: tuple, model, hist: np.ndarray, mirror_of: np.ndarray, t0: np.ndarray,
                       R0: np.ndarray):
    """(model, t_world_root_m, R_parent_segment) calibrated anew from labeled history (F, M, 3)
    (`calibration.calibrate_from_history`), when its solves of the recent history miss the markers by less
    than RECALIBRATE_GAIN of what `model`'s do (mean RMS); else None. Segments that took each other's
    markers keep their layouts rigid either way: the joints tell them apart, so the solves judge. The layout
    checks take the new calibration's layouts: the old ones sit in segments the markers left (kept for the
    markers that stayed, a wrist and finger triad moved off the pelvis went unchecked, and stayed permuted
    for 227 frames: two players at L3, seed 11). None too if the subject neither stands now
    (RECALIBRATE_MIN_HEIGHT_M) nor lies on the floor (`calibration.lying_rotations`), or, standing, a bone
    would change length by more than RECALIBRATE_MAX_BONE_CHANGE_M.
    Pure, for the helper process; `solver_spec` as `refined_model`'s, (t0, R0) the current pose."""
    last = hist[-1][np.isfinite(hist[-1, :, 0])]
    if len(last) < 8:
        return None
    lying = bool(calibration.lying_rotations(hist[-1]))
    if lying:
        # from the frames it has held still in, stood up (`calibrate_from_history`), and with bones of its
        # own (RECALIBRATE_LYING_STILL_M); from all its frames lying, those of its getting down made a
        # skeleton that missed the markers by 0.37 m (KneeltoProne at L2, seed 0)
        hist = hist[_still_since(hist):]
        if len(hist) < RECALIBRATE_LYING_MIN_FRAMES:
            return None
    elif np.ptp(last[:, 2]) < RECALIBRATE_MIN_HEIGHT_M:
        return None  # not standing now, nor lying: its history since is no calibration's (kneeling to prone)
    solver = _solver(solver_spec)
    result = calibration.calibrate_from_history(hist, mirror_of, solver)
    if result is None:
        return None
    seg, off, joints, _, _, layout = result
    bones = np.abs(np.linalg.norm(joints, axis=1) - np.linalg.norm(model.joint_offsets_m, axis=1))
    if not lying and bones.max() > RECALIBRATE_MAX_BONE_CHANGE_M:
        return None  # the same person: its history was not one to calibrate from (going prone)
    new = dataclasses.replace(model, marker_segment=seg, marker_offsets_m=off, joint_offsets_m=joints,
                              layout_offsets_m=off, layout_rms_m=layout)
    frames = hist[np.flatnonzero(np.isfinite(hist[..., 0]).sum(1) >= 8)[-RECALIBRATE_JUDGE_FRAMES:]]
    if len(frames) < 3:
        return None
    old_rms = np.mean(_solve_newest_first(solver, model, frames, t0, R0, RECALIBRATE_CATCH_UP_SOLVES)[2])
    ts, Rs, res = _solve_newest_first(solver, new, frames, t0, R0, RECALIBRATE_CATCH_UP_SOLVES)
    if not np.mean(res) < RECALIBRATE_GAIN * old_rms:
        return None
    return new, ts[-1], Rs[-1]


def _solve_newest_first(solver, model, frames: np.ndarray, t0: np.ndarray, R0: np.ndarray, first_solves: int = 1):
    """Poses (ts (F, 3), Rs (F, 14, 3, 3)) and RMS residuals (F,; inf where the solve failed) of labeled
    frames (F, M, 3) under `model`: the newest (last) solved first, `first_solves` times from (t0, R0), each
    earlier one warm-started from the pose of the one after it (a failed solve keeps that pose)."""
    n = len(frames)
    ts, Rs, res = np.empty((n, 3)), np.empty((n, 14, 3, 3)), np.full(n, np.inf)
    t, R = t0, R0
    for k in range(n - 1, -1, -1):
        lab = np.isfinite(frames[k, :, 0])
        for _ in range(first_solves if k == n - 1 else 1):
            fit = solver.fit(t, R, model.joint_offsets_m, model.marker_segment, model.marker_offsets_m, frames[k], lab)
            if fit.ok:
                t, R = fit.t_world_root_m, fit.R_parent_segment
        ts[k], Rs[k] = t, R
        if fit.ok:
            res[k] = fit.residual_rms_m
    return ts, Rs, res


def _repeats(points: np.ndarray, radius_m: float) -> np.ndarray:
    """Indices of the points that repeat an earlier point of the frame within radius_m (of each close pair,
    the later one): a marker reconstructed twice is one marker, and only one of its copies is labeled."""
    if radius_m <= 0 or len(points) < 2:
        return np.empty(0, int)
    if len(points) <= REPEATS_BY_PAIRS:
        return kernels.repeats(points, radius_m)
    pairs = cKDTree(points).query_pairs(radius_m, output_type="ndarray")
    return np.unique(pairs.max(1)) if len(pairs) else np.empty(0, int)


def _positions(markers, marks: dict, points: np.ndarray) -> np.ndarray:
    cur = np.full((len(markers), 3), np.nan)
    for k, m in enumerate(markers):
        j = marks.get(m)
        if j is not None:
            cur[k] = points[j]
    return cur
