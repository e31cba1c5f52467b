"""The benchmark: labeling accuracy on the real recordings (EVALUATION.md) and speed, written to BENCHMARK.md.

    python3 -m benchmarks.run [--quick] [--files PATTERN ...] [--levels L0 L2 ...] [--max-seconds S]

For every labeled recording in the data directory x corruption level x initialisation mode, each variant
labels the same corrupted sequence in-process, frame by frame, with exactly the daemon's engine input
(`service.daemon.frame_input`):
- ``adaptive``: the engine as shipped (`EngineConfig()`, solve skipped while nearest-neighbour tracking
  holds, up to `max_skip_frames`);
- ``every-frame``: the engine with the solve forced every frame (`max_skip_frames=0`, the paper's
  trade-off);
- ``nnt`` / ``nnt-velocity``: the nearest-neighbour baselines of `benchmarks.nnt` (seeded mode only: they
  cannot initialise themselves).

Modes: ``seeded`` on every file (the first 2 s carry the true labels, scored after); ``tpose`` on the
files that start in a T-pose (HDM_mm; HDM_dg does not: its wrists start 0.4 m apart, in front of the body),
scored from frame 0.

Jobs run in a pool of 2 processes (the machine has 2 cores), each with single-threaded XLA so the two
do not fight over cores, sharing the persistent JAX compilation cache. Speed measurements that need the
real daemon or CLI run afterwards, alone (`benchmarks.speed`).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import fnmatch
import functools
import json
import multiprocessing
import os
import platform
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks import truth_errors
from benchmarks.nnt import NearestNeighbourTracker
from benchmarks.score import Score, plot_errors, score
from recordings.corruption import LEVELS, SEED_S, CorruptedSequence, corrupt
from recordings.recording import Recording, is_marker_label

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
OUT_DIR = REPO / "benchmarks" / "out"
VARIANTS = ("adaptive", "every-frame", "nnt", "nnt-velocity")
ENGINE_VARIANTS = ("adaptive", "every-frame")
#: recordings with a T-pose (checked by hand: arms out, wrists ~1.4 m apart): HDM_mm's at frame 0, squat's
#: from 2.3 s on (the frames before it count as unlabeled: its tpose ceiling is ~89 %, not the column's)
TPOSE_FILES = ("hdm05/HDM_mm_01-02_03_120.c3d", "georgiatech/squat.c3d")
#: a file needs this many named markers to have ground truth (S09_KneeltoRun02 has none: all `*N`)
MIN_TRUE_MARKERS = 4
QUICK_FILES = ("cmu/135_02.c3d", "hdm05/HDM_mm_01-02_03_120.c3d")
QUICK_LEVELS = ("L0", "L2")
QUICK_MAX_S = 8.0
FULL_MAX_S = 25.0
CORRUPTION_SEED = 1
STREAM = "default"
# Single-threaded XLA per worker: two workers on two cores; intra-op threads would only contend.
WORKER_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


class UsageError(Exception):
    """A bad flag or missing data directory: printed as one sentence, exit status 2."""


@dataclasses.dataclass(frozen=True)
class Job:
    file: str  # path relative to the data directory
    level: str
    mode: str  # "seeded" | "tpose"
    variant: str
    max_frames: int | None
    seed: int = CORRUPTION_SEED  # the corruption's (`benchmarks.realizations` runs many)


@dataclasses.dataclass(frozen=True)
class JobResult:
    job: Job
    n_frames: int
    rate_hz: float
    score: Score
    step_s: np.ndarray  # (frames answered,) wall time of each step call [s]
    solved_fraction: float  # engine: frames where some subject ran the solve / frames answered (NaN for NNT)
    subjects: tuple[str, ...]  # subjects the labeler ended with
    peak_rss_mb: float  # worker process peak resident memory so far
    error: str = ""  # non-empty if the run failed (reported in the table, not fatal)
    fit_rms_mm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))  # engine: scored solves' residuals
    segments: dict = dataclasses.field(default_factory=dict)  # engine: "Subject:Marker" -> segment at the end
    score_known_errors_out: Score | None = None  # the score with the file's own label errors unscored (`truth_errors`)


# ----------------------------------------------------------------------------------------------- data


def labeled_files(data_dir: Path) -> list[str]:
    """C3D files under data_dir with ground truth (at least MIN_TRUE_MARKERS named markers)."""
    from recordings.c3d import C3DError, read_c3d

    files = []
    for path in sorted(data_dir.rglob("*.c3d")):
        try:
            rec = read_c3d(path)
        except C3DError as e:  # one unreadable file costs its own rows, not the whole benchmark
            print(f"benchmarks.run: skipping {path.relative_to(data_dir)}: {e}", file=sys.stderr)
            continue
        if sum(is_marker_label(label) for label in rec.labels) >= MIN_TRUE_MARKERS:
            files.append(path.relative_to(data_dir).as_posix())
    return files


@functools.lru_cache(maxsize=4)
def load(data_dir: str, file: str, max_frames: int | None) -> Recording:
    from recordings.c3d import read_c3d

    rec = read_c3d(Path(data_dir) / file)
    if max_frames is not None and rec.n_frames > max_frames:
        rec = dataclasses.replace(rec, points_m=rec.points_m[:max_frames])
    return rec


@functools.lru_cache(maxsize=4)
def corrupted(data_dir: str, file: str, level: str, max_frames: int | None, seed: int = CORRUPTION_SEED) -> CorruptedSequence:
    return corrupt(load(data_dir, file, max_frames), level, seed)


def frame_time_ns(frame: int, rate_hz: float) -> int:
    return int(round(frame * 1e9 / rate_hz))


# ----------------------------------------------------------------------------------------------- labelers


def drive(seq: CorruptedSequence, mode: str, step) -> tuple[list[list[str] | None], np.ndarray]:
    """Feed `seq` frame by frame to `step(FrameInput) -> labels per point`; returns (given, step times).

    Seeded mode puts the true labels in the first `seq.seed_frames` frames (ghosts ""), as a capture
    system streams its own labels; tpose never labels. A dropped frame is never sent (None).
    """
    from service.daemon import frame_input

    given: list[list[str] | None] = []
    times = []
    for f, points in enumerate(seq.points_m):
        if points is None:
            given.append(None)
            continue
        labels = seq.true_labels(f) if mode == "seeded" and f < seq.seed_frames else None
        frame = frame_input(STREAM, f, frame_time_ns(f, seq.rate_hz), points, labels)
        t0 = time.perf_counter()
        out = step(frame)
        times.append(time.perf_counter() - t0)
        given.append(out)
    return given, np.array(times)


def engine_step(engine, first: int, solved: list[int] | None = None, fit_rms_mm: list[float] | None = None):
    """`drive`'s step for an engine: each point's full label ("" = none). Counts frames with a solve in
    `solved` ([solved, all]) and collects the solves' RMS residual [mm] from frame `first` on."""
    solved = [0, 0] if solved is None else solved
    fit_rms_mm = [] if fit_rms_mm is None else fit_rms_mm

    def step(frame):
        outputs, _ = engine.step(frame)
        labels = [""] * len(frame.points_m)
        for out in outputs:
            for marker, i in zip(out.markers, out.point_index):
                if i >= 0:
                    labels[i] = f"{out.subject}:{marker}"
        solved[0] += any(out.solved for out in outputs)
        solved[1] += 1
        if frame.frame >= first:
            fit_rms_mm.extend(1e3 * out.residual_m for out in outputs if out.solved and np.isfinite(out.residual_m))
        return labels

    return step


def run_job(data_dir: str, job: Job) -> JobResult:
    """One labeler on one corrupted sequence, scored. Exceptions become a failed row, not a dead run."""
    seq = corrupted(data_dir, job.file, job.level, job.max_frames, job.seed)
    first = seq.seed_frames if job.mode == "seeded" else 0
    solved = [0, 0]
    subjects: tuple[str, ...] = ()
    fit_rms_mm: list[float] = []
    segments: dict[str, str] = {}
    try:
        if job.variant in ENGINE_VARIANTS:
            from service.config import EngineConfig
            from service.engine import Engine

            engine = Engine(EngineConfig() if job.variant == "adaptive" else EngineConfig(max_skip_frames=0))
            engine.warm_up()
            given, times = drive(seq, job.mode, engine_step(engine, first, solved, fit_rms_mm))
            subjects = tuple(engine.subjects())
            for name in subjects:
                d = engine.describe(name)
                if d["has_skeleton"]:
                    segments.update({f"{name}:{m}": d["segments"][k] for m, k in zip(d["markers"], d["marker_segment"])})
        else:
            tracker = NearestNeighbourTracker(velocity=job.variant == "nnt-velocity")
            given, times = drive(seq, job.mode, lambda frame: tracker.step(frame.points_m, frame.labels))
            subjects = tuple(sorted({n.rpartition(":")[0] for n in tracker.names}))
        error = ""
    except Exception as e:  # noqa: BLE001 - one failing labeler must not lose the other rows
        given, times, error = [None] * seq.n_frames, np.zeros(0), f"{type(e).__name__}: {e}"
    cleaned = truth_errors.unscored(job.file, seq, given) if job.mode == "seeded" else None
    return JobResult(
        job=job,
        n_frames=seq.n_frames,
        rate_hz=seq.rate_hz,
        score=score(seq, given, job.mode, first),
        score_known_errors_out=score(*cleaned, job.mode, first) if cleaned else None,
        step_s=times.astype(np.float32),
        solved_fraction=solved[0] / solved[1] if solved[1] else float("nan"),
        subjects=subjects,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        error=error,
        fit_rms_mm=np.array(fit_rms_mm, np.float32),
        segments=segments,
    )


def init_worker(cache_dir: str) -> None:
    """A benchmark process's setup (each pool worker's, and `benchmarks.losses`'): XLA flags, compile cache."""
    os.environ["XLA_FLAGS"] = WORKER_XLA_FLAGS
    from service.daemon import enable_compilation_cache

    enable_compilation_cache(cache_dir)


def _run_job_star(args) -> JobResult:
    return run_job(*args)


def run_jobs(data_dir: Path, jobs: list[Job], workers: int, cache_dir: str) -> list[JobResult]:
    """Run `jobs` in `workers` spawned processes (spawn: forking after jax is imported is unsafe)."""
    import tqdm

    # Longest first, so the last job to finish is a short one.
    weight = {"adaptive": 3, "every-frame": 4, "nnt": 1, "nnt-velocity": 1}
    ordered = sorted(jobs, key=lambda j: -(j.max_frames or 10**6) * weight[j.variant])
    ctx = multiprocessing.get_context("spawn")
    results = []
    with ctx.Pool(workers, initializer=init_worker, initargs=(cache_dir,), maxtasksperchild=None) as pool:
        todo = [(str(data_dir), job) for job in ordered]
        for result in tqdm.tqdm(pool.imap_unordered(_run_job_star, todo), total=len(todo), desc="runs",
                                file=sys.stderr, leave=False):
            results.append(result)
    return results


def plan(data_dir: Path, files: list[str], levels: list[str], max_s: float | None) -> tuple[list[Job], list[str]]:
    """The jobs, and notes on what was left out and why."""
    jobs, notes = [], []
    for file in files:
        rec = load(str(data_dir), file, None)
        max_frames = int(round(max_s * rec.rate_hz)) if max_s else None
        modes = ["tpose"] if file in TPOSE_FILES else []
        if min(rec.n_frames, max_frames or rec.n_frames) > round(SEED_S * rec.rate_hz) + 0.25 * rec.rate_hz:
            modes.insert(0, "seeded")
        else:  # nothing (or under a quarter second) would be left to score after the 2 s seed
            notes.append(f"{file} ({rec.n_frames / rec.rate_hz:.1f} s) is too short for seeded mode (2 s seed + 0.25 s)")
        for level in levels:
            for mode in modes:
                for variant in VARIANTS:
                    if mode == "tpose" and variant not in ENGINE_VARIANTS:
                        continue
                    jobs.append(Job(file, level, mode, variant, max_frames))
    return jobs, notes


# ----------------------------------------------------------------------------------------------- report


def machine() -> dict[str, str]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        mem_kb = next(int(l.split()[1]) for l in Path("/proc/meminfo").read_text().splitlines() if l.startswith("MemTotal"))
        ram = f"{mem_kb / 2**20:.1f} GiB"
    except (OSError, StopIteration, ValueError):
        ram = "unknown"
    versions = {}
    for name in ("jax", "jaxlib", "optimistix", "numpy", "scipy", "pyzmq"):
        try:
            from importlib.metadata import version

            versions[name] = version(name)
        except Exception:  # noqa: BLE001 - a missing package is reported as such
            versions[name] = "not installed"
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                                text=True, timeout=10).stdout.strip() or "uncommitted"
    except (OSError, subprocess.SubprocessError):
        commit = "unknown"
    return {
        "cpu": cpu,
        "cores": str(os.cpu_count()),
        "ram": ram,
        "python": platform.python_version(),
        "versions": ", ".join(f"{k} {v}" for k, v in versions.items()),
        "commit": commit,
    }


def _pct(x: float) -> str:
    return "–" if x != x else f"{100 * x:.1f}"


def _cell(r: JobResult | None) -> str:
    if r is None:
        return ""
    if r.error:
        return "failed"
    s = r.score
    return f"{_pct(s.accuracy)} / {_pct(s.precision)} / {_pct(s.ghost_rate)}"


def accuracy_table(results: list[JobResult], files: list[str], levels: list[str]) -> list[str]:
    by_key = {(r.job.file, r.job.level, r.job.mode, r.job.variant): r for r in results}
    lines = [
        "| file | level | mode | frames | ceiling | " + " | ".join(VARIANTS) + " |",
        "|---|---|---|---|---|" + "---|" * len(VARIANTS),
    ]
    for file in files:
        for mode in ("seeded", "tpose"):
            for level in levels:
                row = [by_key.get((file, level, mode, v)) for v in VARIANTS]
                first = next((r for r in row if r is not None), None)
                if first is None:
                    continue
                frames = f"{first.n_frames - first.score.first_scored_frame}"
                if first.job.max_frames is not None and first.n_frames >= first.job.max_frames:
                    frames += " (capped)"
                ceiling = next((_pct(r.score.ceiling) for r in row if r is not None and not r.error), "")
                lines.append(f"| {file} | {level} | {mode} | {frames} | {ceiling} | " + " | ".join(_cell(r) for r in row) + " |")
    return lines


def summary_table(results: list[JobResult], levels: list[str]) -> list[str]:
    """Mean accuracy per level and variant over the seeded files (each file weighs the same)."""
    lines = ["| level | ceiling | " + " | ".join(VARIANTS) + " |", "|---|---|" + "---|" * len(VARIANTS)]
    for level in levels:
        ceilings = [r.score.ceiling for r in results if r.job.level == level and r.job.variant == VARIANTS[0]
                    and r.job.mode == "seeded" and r.score.n_true_points]
        cells = [_pct(float(np.mean(ceilings))) if ceilings else ""]
        for v in VARIANTS:
            acc = [r.score.accuracy for r in results if r.job.level == level and r.job.variant == v
                   and r.job.mode == "seeded" and not r.error and r.score.n_true_points]
            cells.append(_pct(float(np.mean(acc))) if acc else "")
        lines.append(f"| {level} | " + " | ".join(cells) + " |")
    return lines


def skeleton_lines(results: list[JobResult]) -> list[str]:
    """The adaptive engine's skeleton per run: solve residuals, and named markers off their segment."""
    from benchmarks.skeleton import misplaced, residual_summary

    lines = ["| file | level | mode | fit RMS p50 / p90 [mm] | named markers off their segment (at the end) |",
             "|---|---|---|---|---|"]
    total = [0, 0]
    runs = sorted((r for r in results if r.job.variant == "adaptive" and not r.error),
                  key=lambda r: (r.job.file, r.job.mode, r.job.level))
    for r in runs:
        judged, wrong = misplaced(r.segments)
        if r.job.mode == "seeded":
            total[0] += judged
            total[1] += len(wrong)
        if not r.segments:
            verdict = "no skeleton"
        elif not judged:
            verdict = "–"
        else:
            verdict = f"{len(wrong)} of {judged}"
            if wrong:
                verdict += ": " + ", ".join(wrong[:6]) + (", ..." if len(wrong) > 6 else "")
        lines.append(f"| {r.job.file} | {r.job.level} | {r.job.mode} | {residual_summary(r.fit_rms_mm)} | {verdict} |")
    lines += ["", f"Seeded runs: {total[1]} of {total[0]} judged markers off their segment "
              f"({_pct(total[1] / total[0]) if total[0] else '–'} %)."]
    return lines


def worst_runs(results: list[JobResult], n: int = 12) -> list[JobResult]:
    engine = [r for r in results if r.job.variant == "adaptive" and not r.error and r.score.accuracy < 1]
    return sorted(engine, key=lambda r: r.score.accuracy)[:n]


def worst_markers_lines(results: list[JobResult]) -> list[str]:
    lines = ["| file | level | mode | accuracy | worst markers (wrong / unlabeled frames) |", "|---|---|---|---|---|"]
    for r in worst_runs(results):
        one_subject = len({n.rpartition(":")[0] for n in r.score.marker_names}) == 1
        markers = ", ".join(f"{name.rpartition(':')[2] if one_subject else name} ({w}/{u})"
                            for name, w, u in r.score.worst_markers(4))
        lines.append(f"| {r.job.file} | {r.job.level} | {r.job.mode} | {_pct(r.score.accuracy)} | {markers} |")
    return lines


def save_plots(results: list[JobResult]) -> list[Path]:
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    paths = []
    for r in worst_runs(results, 6):
        name = f"{Path(r.job.file).stem}_{r.job.level}_{r.job.mode}_{r.job.variant}.png"
        path = OUT_DIR / name
        plot_errors(r.score, path, title=f"{r.job.file} {r.job.level} {r.job.mode} {r.job.variant}",
                    rate_hz=r.rate_hz)
        paths.append(path)
    return paths


def in_process_speed(results: list[JobResult]) -> dict[str, dict]:
    """Per variant: offline frames/s over every run (summed), and the per-frame cost on the 41-marker
    L2 seeded runs (mean, p99)."""
    out = {}
    for v in VARIANTS:
        runs = [r for r in results if r.job.variant == v and not r.error and len(r.step_s)]
        if not runs:
            continue
        steps = np.concatenate([r.step_s for r in runs])
        l2 = [r.step_s for r in runs if r.job.level == "L2" and r.job.mode == "seeded"
              and len(r.score.marker_names) == 41]
        l2s = np.concatenate(l2) if l2 else np.zeros(0)
        out[v] = {
            "frames": int(len(steps)),
            "fps": float(len(steps) / steps.sum()),
            "l2_mean_ms": float(1e3 * l2s.mean()) if len(l2s) else float("nan"),
            "l2_p99_ms": float(1e3 * np.percentile(l2s, 99)) if len(l2s) else float("nan"),
            "solved_fraction": float(np.mean([r.solved_fraction for r in runs])) if v in ENGINE_VARIANTS else float("nan"),
            "peak_rss_mb": float(max(r.peak_rss_mb for r in runs)),
        }
    return out


def write_report(path: Path, args, meta: dict, files, levels, results, notes, speed_inproc, speed, plots,
                 wall_s) -> None:
    lines = [
        "# Benchmark",
        "",
        f"Written by `{args.command_line}` on {meta['date']} in {wall_s / 60:.1f} min. Protocol: "
        "`../shared/EVALUATION.md`; code: `benchmarks/` (see `benchmarks/README.md`).",
        "",
        f"- machine: {meta['cpu']}, {meta['cores']} cores, {meta['ram']} RAM",
        f"- python {meta['python']}; {meta['versions']}",
        f"- commit: {meta['commit']}; corruption seed {CORRUPTION_SEED}"
        + (f"; every file capped at its first {args.max_seconds:g} s" if args.max_seconds else ""),
        "",
        "## Accuracy",
        "",
        "Each cell: accuracy / precision / ghost false-label rate, in %. Seeded runs are scored from the first "
        "unlabeled frame (after 2 s), tpose runs from frame 0; `–` = no ghost points (or no label given). "
        "`nnt` is last-position nearest-neighbour tracking (3 cm gate), `nnt-velocity` the same with a "
        "constant-velocity prediction; both only in seeded mode. `ceiling`: the best accuracy any labeler could "
        "expect on the run (`benchmarks/score.py`): seeded, markers whose names no seed frame gave cannot be named; "
        "either mode, a point with an exact copy among the ghost points (HDM05's `*N`) is a coin toss.",
        "",
        *accuracy_table(results, files, levels),
        "",
        "Mean accuracy over the seeded files:",
        "",
        *summary_table(results, levels),
        "",
    ]
    lines += [f"- {note}" for note in notes] + ([""] if notes else [])
    failed = [r for r in results if r.error]
    if failed:
        lines += ["Failed runs:", ""] + [f"- {r.job}: {r.error}" for r in failed] + [""]
    tpose = [r for r in results if r.job.mode == "tpose" and not r.error]
    if tpose:
        lines += ["T-pose runs ended with subjects: " + "; ".join(
            f"{r.job.level} {r.job.variant}: {', '.join(r.subjects) or 'none'}" for r in tpose), ""]
    lines += ["## Worst markers (engine, adaptive)", "", *worst_markers_lines(results), ""]
    if plots:
        lines += ["Error-over-time plots of the worst runs: " + ", ".join(f"`{p.relative_to(REPO)}`" for p in plots)
                  + " (not committed).", ""]
    lines += ["## Skeleton (engine, adaptive)", "",
              "Fit RMS: the residual of the skeleton's solves over the scored frames. Markers off their segment: "
              "for the files whose marker names we can read (`benchmarks/skeleton.py`: the CMU/HDM05 and "
              "Plug-in Gait conventions, joint markers not judged), the markers the subject model carries on "
              "another segment than their name says, after the whole run (calibration and refinements).", "",
              *skeleton_lines(results), ""]
    lines += ["## Speed", ""]
    from benchmarks import speed as speed_mod

    lines += speed_mod.report_lines(speed_inproc, speed)
    path.write_text("\n".join(lines) + "\n")
    (OUT_DIR / "results.json").write_text(json.dumps({
        "meta": meta,
        "runs": [
            {**dataclasses.asdict(r.job), "accuracy": r.score.accuracy, "precision": r.score.precision,
             "ghost_rate": r.score.ghost_rate, "n_true_points": r.score.n_true_points, "error": r.error,
             "step_mean_ms": float(1e3 * r.step_s.mean()) if len(r.step_s) else None}
            for r in results
        ],
        "speed_in_process": speed_inproc,
        "speed": speed,
    }, indent=1, default=str))


# ----------------------------------------------------------------------------------------------- main


def write_speed_report(path: Path, args, meta: dict, speed: dict, wall_s) -> None:
    """The speed section alone (`--speed-only`): the same measurements as the full report's."""
    from benchmarks import speed as speed_mod

    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Speed",
        "",
        f"Written by `{args.command_line}` on {meta['date']} in {wall_s / 60:.1f} min (no accuracy runs, so no "
        "in-process step times). Protocol: `../shared/EVALUATION.md`.",
        "",
        f"- machine: {meta['cpu']}, {meta['cores']} cores, {meta['ram']} RAM",
        f"- python {meta['python']}; {meta['versions']}",
        f"- commit: {meta['commit']}",
        "",
        *speed_mod.report_lines({}, speed),
    ]
    path.write_text("\n".join(lines) + "\n")


def parse_args(argv: list[str] | None):
    parser = argparse.ArgumentParser(prog="python3 -m benchmarks.run", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help=f"{len(QUICK_FILES)} files, levels {'+'.join(QUICK_LEVELS)}, first {QUICK_MAX_S:g} s, short speed runs")
    parser.add_argument("--files", nargs="+", metavar="PATTERN",
                        help="only files whose path (relative to the data directory) matches a glob or contains the text")
    parser.add_argument("--levels", nargs="+", choices=list(LEVELS), help="corruption levels (default all)")
    parser.add_argument("--max-seconds", type=float, help=f"label only each file's first S seconds (default {FULL_MAX_S:g}, quick {QUICK_MAX_S:g}; 0 = whole files)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="directory of the recordings (default ../shared/data)")
    parser.add_argument("--workers", type=int, default=2, help="processes for the accuracy runs (default 2)")
    parser.add_argument("--no-speed", action="store_true", help="skip the speed section that needs the CLI and the daemon")
    parser.add_argument("--speed-only", action="store_true",
                        help="only the speed section (daemon, CLI, scale; no accuracy runs), written to benchmarks/out/SPEED.md unless --output")
    parser.add_argument("--output", type=Path, help="report to write (default BENCHMARK.md)")
    args = parser.parse_args(argv)
    if args.speed_only and args.no_speed:
        raise UsageError("--speed-only and --no-speed leave nothing to measure; pass one of them")
    if args.output is None:
        args.output = OUT_DIR / "SPEED.md" if args.speed_only else REPO / "BENCHMARK.md"
    args.command_line = "python3 -m benchmarks.run" + ("" if not argv else " " + shlex.join(argv))
    if args.max_seconds is None:
        args.max_seconds = QUICK_MAX_S if args.quick else FULL_MAX_S
    if args.max_seconds < 0 or args.workers < 1:
        raise UsageError("--max-seconds must be >= 0 and --workers >= 1")
    if not args.data.is_dir():
        raise UsageError(f"data directory {args.data} does not exist; pass --data DIR")
    return args


def select_files(all_files: list[str], patterns: list[str] | None, quick: bool) -> list[str]:
    if patterns:
        chosen = [f for f in all_files if any(fnmatch.fnmatch(f, p) or p in f for p in patterns)]
        if not chosen:
            raise UsageError(f"no labeled file matches {' '.join(patterns)}; files: {', '.join(all_files)}")
        return chosen
    if quick:
        return [f for f in QUICK_FILES if f in all_files]
    return all_files


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        args = parse_args(argv)
        all_files = labeled_files(args.data)
        files = select_files(all_files, args.files, args.quick)
    except UsageError as e:
        print(f"benchmarks.run: {e}", file=sys.stderr)
        return 2
    levels = args.levels or (list(QUICK_LEVELS) if args.quick else list(LEVELS))
    from service.config import ServiceConfig

    cache_dir = str(Path(ServiceConfig().cache_dir).expanduser())
    t0 = time.perf_counter()
    meta = {"date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"), **machine()}
    print(f"benchmark: {len(files)} files x {len(levels)} levels, {meta['cpu']}", file=sys.stderr)
    results, notes, speed_inproc, plots, speed = [], [], {}, [], {}
    if not args.speed_only:
        jobs, notes = plan(args.data, files, levels, args.max_seconds or None)
        results = run_jobs(args.data, jobs, args.workers, cache_dir)
        print(f"\nbenchmark: accuracy runs done in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        speed_inproc = in_process_speed(results)
        plots = save_plots(results)
    if not args.no_speed:
        from benchmarks import speed as speed_mod

        speed = speed_mod.measure(args.data, quick=args.quick, cache_dir=cache_dir)
    if args.speed_only:
        write_speed_report(args.output, args, meta, speed, time.perf_counter() - t0)
        print(f"benchmark: wrote {args.output} in {(time.perf_counter() - t0) / 60:.1f} min", file=sys.stderr)
        return 0
    write_report(args.output, args, meta, files, levels, results, notes, speed_inproc, speed, plots,
                 time.perf_counter() - t0)
    print(f"benchmark: wrote {args.output} in {(time.perf_counter() - t0) / 60:.1f} min", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
