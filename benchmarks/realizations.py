"""Seeded accuracy over many corrupted realizations: what a change to the tracker or the calibration is
judged by. One realization of a file moves by a point or more when a single cascade happens (a swap that
lasts, a marker lost for good), so a change is judged by the mean over many, and by its worst.

    python3 -m benchmarks.realizations --seeds 0-17 [--files 85_12 tennis] [--levels L2 L3]
                                       [--out runs.json] [--compare before.json] [--mode tpose]

Runs the adaptive engine in seeded mode on every labeled file x level x corruption seed (each file capped
at its first 25 s, as the benchmark), in 2 processes: 8 files x L2/L3 x 18 seeds take ~5 min. Prints, per
file and level, the mean and the worst accuracy, the mean precision and the skeleton solves' residual p90
(the median and the worst of the runs: is the skeleton still on its markers?); with --compare, beside those
of an earlier run's JSON, with the paired change (mean +- standard error of the per-run differences, runs
up and down), and every run that moved by 0.005 % or more; and, for files whose own labels
are wrong somewhere (`benchmarks.truth_errors`), the means with those spells left unscored. `--mode tpose`
runs the files with a T-pose (`benchmarks.run.TPOSE_FILES`: HDM_mm, squat) with nothing given instead,
scored from frame 0.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from benchmarks.run import (DEFAULT_DATA, FULL_MAX_S, TPOSE_FILES, UsageError, labeled_files, plan, run_jobs,
                            select_files)
from benchmarks.skeleton import parse_seeds
from recordings.corruption import ALL_LEVELS

#: files run by default: the labeled files where the engine tracks a skeleton from a standing seed (03_rolling's
#: seed lies on the floor, where its calibration cannot see the joints and its runs swing by 20 points, which
#: the means would be all about; KneeltoProne's kneels; HDM_dg's is too short to score: add them with --files)
DEV_FILES = ("cmu/135_02.c3d", "cmu/85_12.c3d", "cmu/85_02.c3d", "cmu/07_01.c3d", "cmu/cmu_dribble_shoot_basketball.c3d",
             "hdm05/HDM_mm_01-02_03_120.c3d", "kineticstoolkit/kinematics_tennis_serve.c3d",
             "kineticstoolkit/kinematics_tennis_serve_2players.c3d")


def run(data_dir: Path, files: list[str], levels: list[str], seeds: list[int], workers: int = 2,
        mode: str = "seeded") -> list[dict]:
    """One row per file x level x seed: accuracy, precision [%], true points, wrong, unlabeled, the skeleton
    solves' RMS residual p90 [mm] (NaN without solves: how far the skeleton strays from the markers on its
    worse frames; a calibration that puts a segment's markers on another reads hundreds), error. `mode`
    "tpose" runs the files of `benchmarks.run.TPOSE_FILES` among `files` with nothing given."""
    from service.config import ServiceConfig

    jobs, _ = plan(data_dir, files, levels, FULL_MAX_S)
    jobs = [dataclasses.replace(j, seed=s) for j in jobs if j.mode == mode and j.variant == "adaptive" for s in seeds]
    results = run_jobs(data_dir, jobs, workers, str(Path(ServiceConfig().cache_dir).expanduser()))
    rows = [dict(file=r.job.file, level=r.job.level, seed=r.job.seed, acc=100 * r.score.accuracy,
                 prec=100 * r.score.precision, n=int(r.score.n_true_points), wrong=int(r.score.n_wrong),
                 unlabeled=int(r.score.n_unlabeled), fit_p90_mm=_p90(r.fit_rms_mm), error=r.error,
                 **_known_errors_out(r)) for r in results]
    return sorted(rows, key=lambda r: (r["file"], r["level"], r["seed"]))


def _known_errors_out(r) -> dict:
    """{acc_out, prec_out} [%]: the run scored with its file's own label errors left out
    (`benchmarks.truth_errors`), where the file has any listed; else nothing."""
    s = r.score_known_errors_out
    return {} if s is None else dict(acc_out=100 * s.accuracy, prec_out=100 * s.precision)


def _p90(values: list[float]) -> float:
    return float(np.percentile(values, 90)) if len(values) else float("nan")


def _cells(rows: list[dict]) -> list[str]:
    """["accuracy mean / worst", "precision mean", "solve residual p90, median of the runs"] of some runs."""
    if not rows:
        return ["–", "–", "–"]
    p90 = [r.get("fit_p90_mm", np.nan) for r in rows]
    return [f"{sum(r['acc'] for r in rows) / len(rows):.2f} / {min(r['acc'] for r in rows):.2f}",
            f"{sum(r['prec'] for r in rows) / len(rows):.2f}",
            f"{np.nanmedian(p90):.0f} / {np.nanmax(p90):.0f}" if np.isfinite(p90).any() else "–"]


def _paired(rows: list[dict], old: dict) -> str:
    """The accuracy change of `rows` against the same runs in `old` ({(file, level, seed): row}): mean
    +- standard error of the per-run differences [points], and how many runs went up and down. A single
    realization can swing by several points on a chaotic file (03_rolling: up to 7 either way), so a mean
    over six seeds says little unless the error says so too."""
    d = np.array([r["acc"] - old[k]["acc"] for r in rows if (k := (r["file"], r["level"], r["seed"])) in old])
    if len(d) == 0:
        return "–"
    se = f" +- {d.std(ddof=1) / np.sqrt(len(d)):.3f}" if len(d) > 1 else ""
    return f"{d.mean():+.3f}{se} ({np.count_nonzero(d > 0)} up, {np.count_nonzero(d < 0)} down)"


def summary(rows: list[dict], before: list[dict] | None = None) -> list[str]:
    """Markdown lines: per file and level, mean / worst accuracy and mean precision (beside `before`'s, with
    the paired change: `_paired`)."""
    old = {(r["file"], r["level"], r["seed"]): r for r in before or []}
    head = "accuracy mean / worst | precision mean | residual p90 median / worst [mm] |"
    lines = ["| file | level | runs | " + head + (" before: " + head + " accuracy change [points] |" if before else ""),
             "|---|---|---|---|---|---|" + ("---|---|---|---|" if before else "")]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["file"], r["level"]), []).append(r)
    for (file, level), rr in sorted(groups.items()):
        cells = _cells(rr)
        if before:
            cells += _cells([old[k] for k in ((r["file"], r["level"], r["seed"]) for r in rr) if k in old])
            cells.append(_paired(rr, old))
        lines.append(f"| {file} | {level} | {len(rr)} | " + " | ".join(cells) + " |")
    for level in sorted({r["level"] for r in rows}):
        rr = [r for r in rows if r["level"] == level]
        line = f"\n{level}: {len(rr)} runs, accuracy mean {sum(r['acc'] for r in rr) / len(rr):.3f} %, precision mean {sum(r['prec'] for r in rr) / len(rr):.3f} %"
        oo = [old[(r["file"], r["level"], r["seed"])] for r in rr if (r["file"], r["level"], r["seed"]) in old]
        if oo:
            line += (f" (before, same runs: {sum(r['acc'] for r in oo) / len(oo):.3f} / {sum(r['prec'] for r in oo) / len(oo):.3f} %;"
                     f" change {_paired(rr, old)})")
        lines.append(line)
    out = [r for r in rows if "acc_out" in r]
    if out:
        lines.append("\nwith the files' own label errors left unscored (benchmarks/truth_errors.py), same runs:")
        for (file, level) in sorted({(r["file"], r["level"]) for r in out}):
            rr = [r for r in out if (r["file"], r["level"]) == (file, level)]
            mean = {k: sum(r[k] for r in rr) / len(rr) for k in ("acc_out", "acc", "prec_out", "prec")}
            lines.append(f"- {file} {level}: accuracy mean {mean['acc_out']:.3f} % (scored: {mean['acc']:.3f}), "
                         f"precision mean {mean['prec_out']:.3f} % (scored: {mean['prec']:.3f})")
    moved = [(r, old[k]) for r in rows if (k := (r["file"], r["level"], r["seed"])) in old
             and max(abs(r["acc"] - old[k]["acc"]), abs(r["prec"] - old[k]["prec"])) >= 0.005]
    if before:
        lines.append(f"\nruns that moved: {len(moved)}")
        lines += [f"- {r['file']} {r['level']} seed {r['seed']}: accuracy {o['acc']:.3f} -> {r['acc']:.3f}, "
                  f"precision {o['prec']:.3f} -> {r['prec']:.3f}" for r, o in moved]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m benchmarks.realizations", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="directory of the recordings (default ../shared/data)")
    parser.add_argument("--files", nargs="+", metavar="PATTERN", help="only files whose path matches a glob or contains the text (default: the 8 dev files)")
    parser.add_argument("--levels", nargs="+", default=["L2", "L3"], choices=list(ALL_LEVELS),
                        help="corruption levels (default L2 L3); the L2-... ones are harsher than EVALUATION.md's "
                             "(recordings.corruption.STRESS_LEVELS)")
    parser.add_argument("--seeds", default="0-17", help="corruption seeds, e.g. 0-17 or 1,4,7 (default 0-17)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, help="write the runs as JSON here")
    parser.add_argument("--compare", type=Path, help="an earlier --out JSON to print beside")
    parser.add_argument("--mode", default="seeded", choices=["seeded", "tpose"],
                        help="seeded (default), or tpose: nothing given, on the files with a T-pose (HDM_mm, squat)")
    args = parser.parse_args(argv)
    try:
        try:
            seeds = parse_seeds(args.seeds)
        except ValueError:
            raise UsageError(f"--seeds {args.seeds!r} is not like 0-17 or 1,4,7") from None
        if not args.data.is_dir():
            raise UsageError(f"data directory {args.data} does not exist; pass --data DIR")
        before = None
        if args.compare is not None:
            try:
                before = json.loads(args.compare.read_text())
            except (OSError, ValueError) as e:
                raise UsageError(f"cannot read {args.compare} as an earlier run's JSON ({e})") from None
        available = labeled_files(args.data)
        default = TPOSE_FILES if args.mode == "tpose" else DEV_FILES
        files = select_files(available, args.files, quick=False) if args.files else [f for f in default if f in available]
        if args.mode == "tpose" and not set(files) & set(TPOSE_FILES):
            raise UsageError(f"none of the files is one with a T-pose ({', '.join(TPOSE_FILES)})")
    except UsageError as e:
        print(f"benchmarks.realizations: {e}", file=sys.stderr)
        return 2
    rows = run(args.data, files, args.levels, seeds, args.workers, args.mode)
    if args.out is not None:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")
    print("\n".join(summary(rows, before)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
