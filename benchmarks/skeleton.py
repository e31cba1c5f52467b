"""Is the tracked skeleton right? Two figures per engine run for the benchmark report.

- How well the fitted skeleton explains the markers: the RMS residual of its solves [mm] (median, p90).
  Skin moves over bone and the model has no shoulder girdle, so ~10 mm is good; tens of mm mean a limb is
  mis-posed or carries another limb's markers.
- Whether each marker rides the segment its name says, for the naming conventions we can read (the
  CMU / HDM05 41-marker set and Plug-in Gait, which share their stems). The engine reads no segment
  from names (only which markers are left/right twins): this checks its calibration against what an
  operator would expect. Markers over a joint (SHO, ELB,
  KNE, ANK), whose segment is a matter of convention, are not judged.

The same judgement over many corrupted realizations, calibration alone (no tracking: a minute for the 12
labeled files x L2/L3 x 6 seeds), is what a change to `service/calibration.py` is measured by:

    python3 -m benchmarks.skeleton --seeds 0-17 [--files 85_12 tennis] [--levels L3]

It calibrates every subject from its 2 s seed, as the engine does from a capture system's labels, and
counts the markers off their named segment and the calibrations facing backwards (most left-named markers
on right segments: a skeleton whose knees bend forwards).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

#: name stem (after the L/R side letter) -> segment stem; our 14 segments have no hands, so the wrist and
#: finger markers ride the forearm
_LIMB_STEMS = {
    "UPA": "upperarm", "FRM": "forearm", "WRA": "forearm", "WRB": "forearm", "FIN": "forearm",
    "THI": "thigh", "SHN": "shank", "TIB": "shank", "HEE": "foot", "TOE": "foot", "MT5": "foot",
}
_TRUNK_STEMS = {"FHD": "head", "BHD": "head", "FWT": "pelvis", "BWT": "pelvis", "ASI": "pelvis", "PSI": "pelvis"}
_TORSO = {"C7", "T10", "CLAV", "STRN", "RBAC", "RBAK"}
#: numediart's Qualisys set (03_rolling): every name starts with L, then the side (LL_TH1, LRUA2, LR-SK1);
#: its acromions (AC), epicondyles (HLE, HME, FLE, FME), trochanters (FTC) and malleoli are not judged
_NUMEDIART_STEMS = {
    "FHD": "head", "BHD": "head", "UA": "upperarm", "RSP": "forearm", "USP": "forearm", "HM": "forearm",
    "HL": "forearm", "F": "forearm", "IPS": "pelvis", "IAS": "pelvis", "TH": "thigh", "SK": "shank",
    "FCC": "foot", "FM": "foot",
}
_NUMEDIART_TORSO = {"LCLAV", "LSTRN", "LCV7", "LTV10"}


def expected_segment(name: str) -> str | None:
    """The segment a marker named `name` ("Subject:LWRA" or "LWRA") belongs on, or None if not judged."""
    marker = name.rpartition(":")[2].upper()
    if marker in _TORSO or marker in _NUMEDIART_TORSO:
        return "torso"
    m = re.fullmatch(r"L([LR])[_-]?([A-Z]+?)\d*", marker)
    if m is not None and m.group(2) in _NUMEDIART_STEMS:
        side, stem = m.groups()
        segment = _NUMEDIART_STEMS[stem]
        return segment if segment in ("head", "pelvis") else ("l_" if side == "L" else "r_") + segment
    m = re.fullmatch(r"([LR])([A-Z0-9]+)", marker)
    if m is None:
        return None
    side, stem = m.groups()
    if stem in _TRUNK_STEMS:
        return _TRUNK_STEMS[stem]
    if stem in _LIMB_STEMS:
        return ("l_" if side == "L" else "r_") + _LIMB_STEMS[stem]
    return None


def misplaced(segments: dict[str, str]) -> tuple[int, list[str]]:
    """(markers judged, ["LWRA->l_upperarm", ...] those off their segment) of {marker name: segment}."""
    judged = {n: s for n, s in segments.items() if expected_segment(n) is not None}
    wrong = [f"{n.rpartition(':')[2]}->{s}" for n, s in judged.items() if s != expected_segment(n)]
    return len(judged), wrong


def residual_summary(rms_mm: np.ndarray) -> str:
    """"p50 / p90" of solve residuals [mm], or "–" without solves."""
    if len(rms_mm) == 0:
        return "–"
    return f"{np.median(rms_mm):.1f} / {np.percentile(rms_mm, 90):.1f}"


def side_crossed(segments: dict[str, str]) -> tuple[int, int]:
    """(judged markers named for a side, those on the other side's segment) of {marker name: segment}."""
    sided = [(expected_segment(n)[:2], s) for n, s in segments.items()
             if (expected_segment(n) or "")[:2] in ("l_", "r_")]
    return len(sided), sum(1 for side, s in sided if s[:2] == ("r_" if side == "l_" else "l_"))


def labeled_positions(seq, names, n_frames: int | None = None) -> np.ndarray:
    """(F, M, 3) each of the first n_frames frames' points (all frames by default) at their true markers
    `names` (full labels; one the recording lacks stays unseen); NaN = unseen, or a dropped frame."""
    n_frames = seq.n_frames if n_frames is None else n_frames
    index = {seq.marker_names.index(n): k for k, n in enumerate(names) if n in seq.marker_names}
    positions = np.full((n_frames, len(names), 3), np.nan)
    for f in range(n_frames):
        if seq.points_m[f] is None:
            continue
        for p, t in zip(seq.points_m[f], seq.truth[f]):
            if int(t) in index:
                positions[f, index[int(t)]] = p
    return positions


def seed_history(seq, subject: str) -> tuple[list[str], np.ndarray]:
    """(marker names, labeled history (F, M, 3)) of one subject over the seed of a corrupted recording,
    each point at its true marker: what the engine calibrates a seeded subject from."""
    names = [n for n in seq.marker_names if n.partition(":")[0] == subject]
    history = labeled_positions(seq, names, seq.seed_frames)
    return names, history[np.isfinite(history[..., 0]).any(1)]


def seed_calibration(seq, subject: str) -> dict[str, str] | None:
    """{marker name: segment} of `subject` calibrated from its seed, or None if no frame calibrates."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import calibrate_from_history, mirror_index

    names, history = seed_history(seq, subject)
    # the markers the seed shows, as the engine's model has them (one never seen has no segment to judge:
    # 8 of 03_rolling's 68)
    seen = np.isfinite(history[..., 0]).any(0)
    names, history = [n for n, ok in zip(names, seen) if ok], history[:, seen]
    result = calibrate_from_history(history, mirror_index([n.partition(":")[2] for n in names]))
    return None if result is None else {n: SEGMENTS[k] for n, k in zip(names, result[0])}


def calibration_sweep(data_dir: Path, files: list[str], levels: list[str], seeds: list[int]) -> list[dict]:
    """One row per file x level x seed x subject: judged, off (["LWRA->pelvis", ...]), backwards."""
    from recordings.c3d import read_c3d
    from recordings.corruption import corrupt

    rows = []
    for file in files:
        rec = read_c3d(data_dir / file)
        for level in levels:
            for seed in seeds:
                seq = corrupt(rec, level, seed)
                for subject in dict.fromkeys(n.partition(":")[0] for n in seq.marker_names):
                    got = seed_calibration(seq, subject)
                    row = dict(file=file, level=level, seed=seed, subject=subject)
                    if got is None:
                        rows.append({**row, "judged": 0, "off": [], "backwards": False, "calibrated": False})
                        continue
                    judged, off = misplaced(got)
                    n_sided, crossed = side_crossed(got)
                    rows.append({**row, "judged": judged, "off": off, "backwards": crossed > n_sided / 2, "calibrated": True})
    return rows


def parse_seeds(text: str) -> list[int]:
    """"0-17" or "1,4,7" or "3" -> seeds."""
    seeds = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        seeds += list(range(int(lo), int(hi or lo) + 1))
    return seeds


def main(argv: list[str] | None = None) -> int:
    from benchmarks.run import DEFAULT_DATA, UsageError, labeled_files, select_files

    parser = argparse.ArgumentParser(prog="python3 -m benchmarks.skeleton",
                                     description="Seed calibrations over many corrupted realizations: markers off their named segment.")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="directory of the recordings (default ../shared/data)")
    parser.add_argument("--files", nargs="+", metavar="PATTERN", help="only files whose path matches a glob or contains the text")
    parser.add_argument("--levels", nargs="+", default=["L2", "L3"], choices=["L0", "L1", "L2", "L3"])
    parser.add_argument("--seeds", default="0-5", help="corruption seeds, e.g. 0-17 or 1,4,7 (default 0-5)")
    parser.add_argument("--verbose", action="store_true", help="list every calibration with a marker off its segment")
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
        if not args.data.is_dir():
            raise UsageError(f"data directory {args.data} does not exist; pass --data DIR")
        files = select_files(labeled_files(args.data), args.files, quick=False)
    except ValueError:
        print(f"benchmarks.skeleton: --seeds {args.seeds!r} is not like 0-17 or 1,4,7", file=sys.stderr)
        return 2
    except UsageError as e:
        print(f"benchmarks.skeleton: {e}", file=sys.stderr)
        return 2
    rows = calibration_sweep(args.data, files, args.levels, seeds)
    print("| file | level | calibrations | none | markers judged | off their segment | facing backwards |")
    print("|---|---|---|---|---|---|---|")
    for file in files:
        for level in args.levels:
            rr = [r for r in rows if r["file"] == file and r["level"] == level]
            print(f"| {file} | {level} | {len(rr)} | {sum(not r['calibrated'] for r in rr)} | {sum(r['judged'] for r in rr)} "
                  f"| {sum(len(r['off']) for r in rr)} | {sum(r['backwards'] for r in rr)} |")
    print(f"\n{len(rows)} calibrations (seeds {args.seeds}): {sum(len(r['off']) for r in rows)} of "
          f"{sum(r['judged'] for r in rows)} judged markers off their segment, {sum(r['backwards'] for r in rows)} facing backwards")
    if args.verbose:
        for r in rows:
            if r["off"]:
                print(f"{r['file']} {r['subject']} {r['level']} seed {r['seed']}: {', '.join(r['off'])}"
                      + (" (backwards)" if r["backwards"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
