"""A recording in memory: the one shape every file reader, generator and consumer of recordings shares."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Recording:
    """Marker trajectories in metres, right-handed, z up (converted at the file edge).

    points_m[f, i] is point i in frame f, NaN where that point was not seen. labels[i] is the point's name
    as the source gives it ("Subject:Marker", "Marker", "*12" for an unnamed point, "" if unlabeled).
    """

    points_m: np.ndarray  # (F, N, 3) float64, NaN = missing
    labels: tuple[str, ...]  # (N,)
    rate_hz: float
    source: str = ""  # file path or generator name, for messages

    def __post_init__(self) -> None:
        if self.points_m.ndim != 3 or self.points_m.shape[2] != 3:
            raise ValueError(f"points_m must be (frames, points, 3), got {self.points_m.shape}")
        if len(self.labels) != self.points_m.shape[1]:
            raise ValueError(f"{len(self.labels)} labels for {self.points_m.shape[1]} points")
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")

    @property
    def n_frames(self) -> int:
        return self.points_m.shape[0]

    @property
    def n_points(self) -> int:
        return self.points_m.shape[1]


def split_label(label: str) -> tuple[str, str]:
    """'Subject:Marker' -> ('Subject', 'Marker'); 'Marker' -> ('', 'Marker')."""
    subject, sep, marker = label.rpartition(":")
    return (subject, marker) if sep else ("", label)


def is_marker_label(label: str) -> bool:
    """True for a named marker; False for unnamed points ('*12', '') and duplicate fragments ('RBAC-1').

    EVALUATION.md counts the latter as ghosts.
    """
    _, name = split_label(label.strip())
    if not name or name.startswith("*"):
        return False
    stem, dash, tail = name.rpartition("-")
    return not (dash and stem and tail.isdigit())
