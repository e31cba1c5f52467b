"""Offline labeling (`mocap-service label`): a recording through the same engine, frame by frame, causally.

Causal on purpose: each frame is labeled from the past only, exactly as the daemon would label it live, so
offline results predict online ones (and the daemon's accuracy can be measured without a socket). Frames
are built by `service.daemon.frame_input`, the function the daemon uses, so the engine input is identical.
"""

from __future__ import annotations

import sys

import numpy as np
import tqdm

from recordings.corruption import full_label
from recordings.recording import Recording, is_marker_label
from service.config import EngineConfig, ServiceConfig
from service.daemon import frame_input

#: stream name of offline frames (the daemon's default stream), so calibrations are interchangeable.
STREAM = "default"


def frame_time_ns(frame: int, rate_hz: float) -> int:
    """Capture time of frame `frame` of a recording at `rate_hz`, counted from its first frame [ns]."""
    return int(round(frame * 1e9 / rate_hz))


def seed_labels(labels) -> list[str]:
    """A file's point names as seed labels: "Subject:Marker" for a marker (unprefixed names get the
    default subject, as in the benchmark), "" for unnamed points (`*N`, "") and duplicate fragments."""
    return [full_label(label) if is_marker_label(label) else "" for label in labels]


def label_recording(recording: Recording, config: ServiceConfig | EngineConfig = EngineConfig(),
                    seed_frames: int = 0, progress: bool = True, engine=None) -> tuple[np.ndarray, list[str]]:
    """Label `recording` causally; returns (points_m (F, M, 3), labels M "Subject:Marker").

    Each frame feeds the engine the recording's non-NaN points in file order, with the file's names as
    seed labels for frames < `seed_frames` (no labels after). The output has one column per marker of
    every subject the engine tracked, in order of first appearance: its observed position, NaN when the
    marker was not observed. `engine` may be passed (warm, or a test double); by default one is built.
    """
    if engine is None:
        from service.engine import Engine  # here: importing this module must not cost a jax import

        engine = Engine(config.engine if isinstance(config, ServiceConfig) else config)
        engine.warm_up()
    seeds = seed_labels(recording.labels)
    columns: dict[str, int] = {}  # "Subject:Marker" -> output column
    observed: list[tuple[int, np.ndarray, np.ndarray]] = []  # (frame, columns, positions)
    for f in tqdm.trange(recording.n_frames, desc="labeling", unit="frame", disable=not progress,
                         file=sys.stderr, leave=False):
        points = recording.points_m[f]
        visible = np.flatnonzero(np.all(np.isfinite(points), axis=1))
        labels = [seeds[i] for i in visible] if f < seed_frames else None
        outputs, _ = engine.step(frame_input(STREAM, f, frame_time_ns(f, recording.rate_hz), points[visible],
                                             labels))
        for out in outputs:
            cols = np.array([columns.setdefault(f"{out.subject}:{m}", len(columns)) for m in out.markers], int)
            seen = np.asarray(out.point_index) >= 0
            observed.append((f, cols[seen], np.asarray(out.positions_m)[seen]))
    points_m = np.full((recording.n_frames, len(columns), 3), np.nan)
    for f, cols, positions in observed:
        points_m[f, cols] = positions
    return points_m, list(columns)
