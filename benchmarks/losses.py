"""Where one seeded run loses its points: what to look at once `benchmarks.realizations` has shown a run
that fell.

    python3 -m benchmarks.losses FILE [--level L3] [--seed 13 | --seeds 0-17] [--top 12]

Runs the adaptive engine on one corrupted realization (seeded, the file capped at its first 25 s, as the
benchmark) and lists, from the first scored frame on:
- the wrong labels, as (label given, marker whose point it was) pairs: frames, first frame;
- the markers left unlabeled while in view after SETTLE_FRAMES frames running in view (a marker just back
  from a gap is allowed a few frames), with their spells, and on how many of those frames its name was on
  another point (a swap, not a loss of track);
- the markers the seed never showed, which no labeler can name (they are out of the score's ceiling).

With --seeds (e.g. 0-17) it runs every one of those realizations (in two processes) and sums what they
lost: the markers losing most (labels given on their points wrongly, and frames unlabeled in view), the
stretches of the recording where the losses fall (one-second windows: a tennis player's serves), and the
longest spells, each with its seed: where a change should look first, once `benchmarks.realizations`
has shown a file's mean short of its target.

With --true-skeleton it runs once more, each subject's skeleton replaced, as soon as it has one after the
seed, by one aligned to the whole run's true labels (`true_skeleton`; refinement then off), and prints both
runs' accuracy: how much of what the run lost is the skeleton's fault (joints a still seed never showed)
rather than the tracking's. A diagnostic, not a labeler: it reads the answers.
"""

from __future__ import annotations

import argparse
import collections
import copy
import dataclasses
import multiprocessing
import sys
from pathlib import Path

import numpy as np

from benchmarks.run import (DEFAULT_DATA, FULL_MAX_S, UsageError, corrupted, drive, engine_step, init_worker,
                            labeled_files, plan, select_files)
from benchmarks.skeleton import parse_seeds
from recordings.corruption import ALL_LEVELS

#: a marker counts as lost while in view once it has been in view this many frames running
SETTLE_FRAMES = 10


def _wrong_labels(seq, given: list, first: int):
    """(frame, label given, true label or "" for a ghost's point) of every wrong label from frame `first`."""
    for f in range(first, seq.n_frames):
        if given[f] is None:
            continue
        for g, t in zip(given[f], seq.true_labels(f)):
            if g and g != t:
                yield f, g, t


def wrong_pairs(seq, given: list, first: int) -> list[tuple[str, str, int, int]]:
    """(label given, true label or "" for a ghost's point, frames, first frame), the most frames first."""
    count: collections.Counter = collections.Counter()
    start: dict[tuple[str, str], int] = {}
    for f, g, t in _wrong_labels(seq, given, first):
        count[(g, t)] += 1
        start.setdefault((g, t), f)
    return [(g, t, n, start[(g, t)]) for (g, t), n in count.most_common()]


def _spells(frames: list[int]) -> list[tuple[int, int]]:
    """Runs of consecutive frame numbers as (first, last)."""
    out: list[tuple[int, int]] = []
    for f in frames:
        if out and f == out[-1][1] + 1:
            out[-1] = (out[-1][0], f)
        else:
            out.append((f, f))
    return out


def unlabeled_in_view(seq, given: list, first: int, settle: int = SETTLE_FRAMES) -> list[tuple[str, int, int, list]]:
    """(true label, frames unlabeled in view, of those the frames its name was on another point, spells),
    the most frames first. A dropped frame neither counts nor breaks a marker's run in view."""
    in_view: collections.Counter = collections.Counter()
    lost: dict[str, list[int]] = collections.defaultdict(list)
    elsewhere: collections.Counter = collections.Counter()
    for f in range(seq.n_frames):
        if seq.truth[f] is None:
            continue
        labels = seq.true_labels(f)
        visible = {t for t in labels if t}
        for t in list(in_view):
            if t not in visible:
                del in_view[t]
        in_view.update(visible)
        if f < first or given[f] is None:
            continue
        used = set(given[f])
        for g, t in zip(given[f], labels):
            if t and not g and in_view[t] > settle:
                lost[t].append(f)
                elsewhere[t] += t in used
    rows = [(t, len(fs), elsewhere[t], _spells(fs)) for t, fs in lost.items()]
    return sorted(rows, key=lambda r: (-r[1], r[0]))


def never_in_seed(seq, first: int) -> list[str]:
    """True markers seen after the seed but never in its frames: their names are nowhere to learn."""
    seen_seed, seen_after = set(), set()
    for f in range(seq.n_frames):
        if seq.truth[f] is not None:
            (seen_seed if f < first else seen_after).update(t for t in seq.true_labels(f) if t)
    return sorted(seen_after - seen_seed)


def report(seq, given: list, first: int, top: int = 12) -> list[str]:
    """The three lists above as text lines (each list cut at `top`)."""
    lines = [f"{Path(seq.source).name} {seq.level} seed {seq.seed}: scored from frame {first} of {seq.n_frames}", "",
             "wrong labels (label given  on  the point of):"]
    pairs = wrong_pairs(seq, given, first)
    lines += [f"  {g:24s} on {t or 'a ghost':24s} {n:5d} frames, first {f0}" for g, t, n, f0 in pairs[:top]] or ["  none"]
    lines += ["", f"unlabeled in view (after {SETTLE_FRAMES} frames in view):"]
    rows = unlabeled_in_view(seq, given, first)
    lines += [f"  {t:24s} {n:5d} frames, name elsewhere on {e:4d}; spells {spells[:6]}{' ...' if len(spells) > 6 else ''}"
              for t, n, e, spells in rows[:top]] or ["  none"]
    missing = never_in_seed(seq, first)
    lines += ["", "never in the seed: " + (", ".join(missing) if missing else "none")]
    return lines


@dataclasses.dataclass(frozen=True)
class RunLosses:
    """What one realization lost (`run_losses`), for `summary`: its seed; per true marker (or "" for ghost
    points), the wrong labels on its points and the frames it was unlabeled in view; the frames of each
    loss; the spells (frames, kind, label, point's true label or "", first frame); and the recording's
    frames, rate and first scored frame."""

    seed: int
    wrong: dict
    unlabeled: dict
    loss_frames: list
    spells: list
    n_frames: int
    rate_hz: float
    first: int


def run_losses(seq, given: list, first: int) -> RunLosses:
    """One realization's losses from frame `first` on, as `summary` sums them over realizations: wrong labels
    (`_wrong_labels`) and markers unlabeled in view (`unlabeled_in_view`)."""
    wrong: collections.Counter = collections.Counter()
    frames = []
    for f, _, t in _wrong_labels(seq, given, first):
        wrong[t] += 1
        frames.append(f)
    spells = [(n, "wrong", g, t, f0) for g, t, n, f0 in wrong_pairs(seq, given, first)]
    unlabeled: collections.Counter = collections.Counter()
    for t, n, _, runs in unlabeled_in_view(seq, given, first):
        unlabeled[t] += n
        for a, b in runs:
            frames += range(a, b + 1)
            spells.append((b - a + 1, "unlabeled", t, "", a))
    return RunLosses(seq.seed, dict(wrong), dict(unlabeled), frames, spells, seq.n_frames, seq.rate_hz, first)


def summary(runs: list[RunLosses], window: int, n_frames: int, first: int, top: int = 12) -> list[str]:
    """`runs` summed, as text lines: the markers losing most, the `window`-frame stretches of the recording
    where the losses fall, and the longest spells with their seeds (each list cut at `top`)."""
    wrong: collections.Counter = collections.Counter()
    unlabeled: collections.Counter = collections.Counter()
    in_runs: collections.Counter = collections.Counter()
    windows: collections.Counter = collections.Counter()
    spells = []
    for r in runs:
        wrong.update(r.wrong)
        unlabeled.update(r.unlabeled)
        in_runs.update(set(r.wrong) | set(r.unlabeled))
        windows.update(f // window for f in r.loss_frames)
        spells += [(n, r.seed, kind, label, point, f0) for n, kind, label, point, f0 in r.spells]
    total = sum(windows.values())
    lines = [f"{len(runs)} runs: {sum(wrong.values())} wrong labels, {sum(unlabeled.values())} marker-frames "
             f"unlabeled in view, from frame {first} of {n_frames}", "",
             "markers losing most (wrong: labels given on its points; a ghost's points as \"a ghost\"):"]
    most = sorted(set(wrong) | set(unlabeled), key=lambda t: -(wrong[t] + unlabeled[t]))
    lines += [f"  {t or 'a ghost':24s} wrong {wrong[t]:5d}, unlabeled in view {unlabeled[t]:5d}, "
              f"in {in_runs[t]:2d} runs" for t in most[:top]] or ["  none"]
    lines += ["", f"where the losses fall ({window}-frame windows):"]
    lines += [f"  frames {w * window:5d}-{(w + 1) * window - 1:5d} {n:6d} ({100 * n / total:4.1f} %)"
              for w, n in sorted(windows.most_common(top))] or ["  none"]
    lines += ["", "longest spells (a wrong pair's frames counted together, as in the one run's report):"]
    for n, seed, kind, label, point, f0 in sorted(spells, key=lambda x: (-x[0], x[1]))[:top]:
        what = f"{label} on {point or 'a ghost'}" if kind == "wrong" else f"{label} unlabeled"
        lines.append(f"  {n:5d} frames, seed {seed:2d}, {what}, first {f0}")
    return lines


def _labels(seq) -> list:
    """Each frame's labels as the adaptive engine gives them, seeded."""
    from service.config import EngineConfig
    from service.engine import Engine

    engine = Engine(EngineConfig())
    engine.warm_up()
    return drive(seq, "seeded", engine_step(engine, seq.seed_frames))[0]


def _run_losses_job(args) -> RunLosses:
    """One realization of `main --seeds`, in a worker process: (data dir, file, level, max_frames, seed)."""
    data_dir, file, level, max_frames, seed = args
    seq = corrupted(data_dir, file, level, max_frames, seed)
    return run_losses(seq, _labels(seq), seq.seed_frames)


#: (`true_skeleton`) rounds of solving every frame and re-aligning; poses kept of every this many frames;
#: and the alignment's prior (weaker than the engine's 0.3: the true labels are to be believed)
TRUE_SKELETON_ROUNDS, TRUE_SKELETON_EVERY, TRUE_SKELETON_PRIOR = 3, 5, 0.05


def true_labeled_frames(seq, subject: str, markers) -> np.ndarray:
    """(F, M, 3) each frame's points at their true markers of `subject` (NaN = unseen or dropped)."""
    from benchmarks.skeleton import labeled_positions

    return labeled_positions(seq, [f"{subject}:{m}" for m in markers])


def true_skeleton(model, state, solver, frames: np.ndarray, first: int):
    """`model` (a calibrated SubjectModel) with its marker and joint offsets aligned to true-labeled frames
    (F, M, 3) from frame `first` on (`calibration.refine`): each round solves every frame in order, warm-
    started from `state`'s pose (a copy: `state` is left as it is), and aligns to the poses of every
    TRUE_SKELETON_EVERY-th frame. The markers keep their segments."""
    from service import calibration, tracker

    for _ in range(TRUE_SKELETON_ROUNDS):
        st = copy.deepcopy(state)
        kept, poses = [], []
        for f in range(first, len(frames)):
            seen = np.isfinite(frames[f, :, 0])
            fit = None
            for _ in range(2):
                fit = tracker._fit(model, st, solver, frames[f], seen) or fit
            if fit is not None and (f - first) % TRUE_SKELETON_EVERY == 0:
                kept.append(f)
                poses.append(st.R_parent_segment.copy())
        if len(kept) < 2:
            return model
        off, joints = calibration.refine(frames[kept], np.stack(poses), model.marker_segment, model.marker_offsets_m,
                                         model.joint_offsets_m, prior_weight=TRUE_SKELETON_PRIOR)
        model = dataclasses.replace(model, marker_offsets_m=off, joint_offsets_m=joints)
    return model


def true_skeleton_step(engine, seq):
    """`engine_step` for an engine whose subjects take `true_skeleton` on their first frame with a skeleton
    after the seed, and then refine and recalibrate no more."""
    step, swapped = engine_step(engine, seq.seed_frames), set()

    def swapping(frame):
        labels = step(frame)
        if frame.frame >= seq.seed_frames:
            for name, s in engine._subjects.items():
                if name not in swapped and s.model.has_skeleton and s.refine_job is None:
                    frames = true_labeled_frames(seq, name, s.model.markers)
                    s.model = true_skeleton(s.model, s.state, engine.solver, frames, frame.frame)
                    s.next_refine_frame = s.next_recalibration_frame = 1 << 62
                    swapped.add(name)
        return labels

    return swapping


def _run_seeds(data_dir: str, file: str, level: str, max_frames, seeds: list[int], cache_dir: str,
               workers: int = 2) -> list[RunLosses]:
    """`_run_losses_job` for each seed, in `workers` spawned processes (as `benchmarks.run.run_jobs`)."""
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(workers, initializer=init_worker, initargs=(cache_dir,)) as pool:
        runs = pool.map(_run_losses_job, [(data_dir, file, level, max_frames, seed) for seed in seeds])
    return sorted(runs, key=lambda r: r.seed)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m benchmarks.losses", description=__doc__.split("\n\n")[0])
    parser.add_argument("file", help="a labeled recording: a glob or a text its path contains, matching one file")
    parser.add_argument("--level", default="L3", choices=list(ALL_LEVELS),
                        help="corruption level (default L3); the L2-... ones are harsher than EVALUATION.md's")
    parser.add_argument("--seed", type=int, default=1, help="corruption seed (default 1, the benchmark's)")
    parser.add_argument("--seeds", help="several corruption seeds, e.g. 0-17 or 1,4,7: their losses summed")
    parser.add_argument("--top", type=int, default=12, help="rows per list (default 12)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="directory of the recordings (default ../shared/data)")
    parser.add_argument("--true-skeleton", action="store_true",
                        help="run again with each skeleton aligned to the run's true labels, and print both accuracies")
    args = parser.parse_args(argv)
    try:
        if not args.data.is_dir():
            raise UsageError(f"data directory {args.data} does not exist; pass --data DIR")
        files = select_files(labeled_files(args.data), [args.file], quick=False)
        if len(files) > 1:
            raise UsageError(f"{args.file!r} matches {len(files)} files ({', '.join(files)}); name one")
        seeds = None
        if args.seeds is not None:
            try:
                seeds = parse_seeds(args.seeds)
            except ValueError:
                raise UsageError(f"--seeds {args.seeds!r} is not like 0-17 or 1,4,7") from None
            if args.true_skeleton:
                raise UsageError("--true-skeleton runs one realization: give --seed, not --seeds")
    except UsageError as e:
        print(f"benchmarks.losses: {e}", file=sys.stderr)
        return 2
    jobs, notes = plan(args.data, files, [args.level], FULL_MAX_S)  # the benchmark's cap on the file
    seeded = [j for j in jobs if j.mode == "seeded"]
    if not seeded:
        print(f"benchmarks.losses: {'; '.join(notes) or files[0] + ' has no seeded run'}", file=sys.stderr)
        return 2
    from service.config import EngineConfig, ServiceConfig
    from service.engine import Engine

    cache_dir = str(Path(ServiceConfig().cache_dir).expanduser())
    if seeds is not None:
        runs = _run_seeds(str(args.data), files[0], args.level, seeded[0].max_frames, seeds, cache_dir)
        print(f"{Path(files[0]).name} {args.level}, seeds {args.seeds}")
        window = max(1, round(runs[0].rate_hz))
        print("\n".join(summary(runs, window, runs[0].n_frames, runs[0].first, args.top)))
        return 0
    init_worker(cache_dir)  # the benchmark's XLA flags and cache
    seq = corrupted(str(args.data), files[0], args.level, seeded[0].max_frames, args.seed)
    given = _labels(seq)
    print("\n".join(report(seq, given, seq.seed_frames, args.top)))
    if args.true_skeleton:
        from benchmarks.score import score

        engine = Engine(EngineConfig())
        given_true, _ = drive(seq, "seeded", true_skeleton_step(engine, seq))
        print("\naccuracy / precision [%]:")
        for what, g in (("as it runs", given), ("with the true skeleton", given_true)):
            sc = score(seq, g, "seeded", seq.seed_frames)
            print(f"  {what:24s} {100 * sc.accuracy:5.1f} / {100 * sc.precision:5.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
