"""Corrupt a clean recording the way EVALUATION.md defines levels L0-L3, and keep the ground truth apart.

A labeler under test sees only `CorruptedSequence.points_m`: per frame an unordered cloud (shuffled every
frame, so an index carries no identity), with occlusions, noise, ghost points and dropped frames added.
`truth` says which true marker each point is, for scoring only.

Every random component draws from its own child of `SeedSequence(seed)`, so a sequence is a pure function
of (recording, level, seed), and changing one component (say the noise) leaves the others identical.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from recordings.recording import Recording, is_marker_label, split_label

#: subject name given to true markers whose file label carries no "Subject:" prefix, so that every
#: ground-truth name has the full "Subject:Marker" form the wire protocol uses.
DEFAULT_SUBJECT = "subject"


# Near-body ghosts live an exponential time of this mean [s] (EVALUATION.md: ~0.08 s).
GHOST_LIFETIME_MEAN_S = 0.08


@dataclasses.dataclass(frozen=True)
class CorruptionLevel:
    """One row of EVALUATION.md's corruption table."""

    occluded_fraction: float  # fraction of each marker's samples hidden by added occlusion spells
    noise_sigma_m: float  # Gaussian noise per axis [m]
    near_ghosts_per_s: float  # births of near-body ghost tracks per second
    far_ghost_fraction: float  # fraction of frames with one ghost anywhere in the capture volume
    cluster_events_per_s: float  # rate of "a marker and its 3 nearest neighbours vanish together"
    dropped_frame_fraction: float  # fraction of frames dropped entirely
    ghost_lifetime_s: float = GHOST_LIFETIME_MEAN_S  # mean life of a near-body ghost track [s]


LEVELS: dict[str, CorruptionLevel] = {
    "L0": CorruptionLevel(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "L1": CorruptionLevel(0.08, 0.0005, 0.0, 0.0, 0.0, 0.0),
    "L2": CorruptionLevel(0.08, 0.0005, 15.0, 0.02, 0.0, 0.0),
    "L3": CorruptionLevel(0.15, 0.0008, 25.0, 0.05, 0.2, 0.01),
}

#: Beyond EVALUATION.md: L2 with one thing made harsher, to see how a labeler degrades past the levels it is
#: judged on (`python3 -m benchmarks.realizations --levels L2-lasting-ghosts ...`). Never part of the
#: benchmark's default run.
STRESS_LEVELS: dict[str, CorruptionLevel] = {
    # reflections that stay: ghosts live 0.5 s instead of 0.08 (about 7 near the body at any time, not 1)
    "L2-lasting-ghosts": dataclasses.replace(LEVELS["L2"], ghost_lifetime_s=0.5),
    # a quarter of every marker's samples hidden (03_rolling's real occlusion is 23 %)
    "L2-occlusion-25": dataclasses.replace(LEVELS["L2"], occluded_fraction=0.25),
    # 2 mm noise per axis (a poorly calibrated volume)
    "L2-noise-2mm": dataclasses.replace(LEVELS["L2"], noise_sigma_m=0.002),
    # 60 near-body ghost tracks per second, and a far ghost in 10 % of the frames
    "L2-ghost-storm": dataclasses.replace(LEVELS["L2"], near_ghosts_per_s=60.0, far_ghost_fraction=0.1),
    # 5 % of the frames dropped (a lossy link)
    "L2-dropped-frames": dataclasses.replace(LEVELS["L2"], dropped_frame_fraction=0.05),
    # a marker and its 3 nearest neighbours vanish together once a second, for 0.3-1.5 s
    "L2-cluster-dropouts": dataclasses.replace(LEVELS["L2"], cluster_events_per_s=1.0),
}
#: every level `corrupt` takes, EVALUATION.md's first
ALL_LEVELS: dict[str, CorruptionLevel] = {**LEVELS, **STRESS_LEVELS}

# Occlusion gaps: lognormal, median 0.1 s, sigma 1 in log space, capped at 5 s (EVALUATION.md).
GAP_MEDIAN_S = 0.1
GAP_LOG_SIGMA = 1.0
GAP_MAX_S = 5.0
# Near-body ghosts (EVALUATION.md): 3-15 cm from a visible marker, ~1 mm/frame drift.
GHOST_DISTANCE_M = (0.03, 0.15)
GHOST_DRIFT_M_PER_FRAME = 0.001
# Far ghosts are drawn in the bounding box of the recording's points grown by this margin [m].
FAR_GHOST_MARGIN_M = 0.5
# Seeded mode: the first SEED_S seconds of frames carry the ground-truth label of every point.
SEED_S = 2.0
# Cluster dropouts: the marker and its CLUSTER_NEIGHBOURS nearest neighbours, for a uniform duration.
CLUSTER_NEIGHBOURS = 3
CLUSTER_DURATION_S = (0.3, 1.5)


@dataclasses.dataclass(frozen=True, eq=False)  # array fields: a generated == would raise
class CorruptedSequence:
    """What a labeler sees (points_m) and what the scorer knows (truth), frame by frame."""

    points_m: list[np.ndarray | None]  # per frame (N_f, 3) float64, shuffled; None = frame dropped
    truth: list[np.ndarray | None]  # per frame (N_f,) int: index into marker_names, -1 = ghost
    marker_names: tuple[str, ...]  # full "Subject:Marker" label of every true marker
    rate_hz: float
    level: str = "L0"
    seed: int = 0
    source: str = ""

    @property
    def n_frames(self) -> int:
        return len(self.points_m)

    @property
    def seed_frames(self) -> int:
        """Frames at the start that carry labels in seeded mode (the first SEED_S seconds)."""
        return min(self.n_frames, int(round(SEED_S * self.rate_hz)))

    def true_labels(self, frame: int) -> list[str]:
        """The ground-truth label of each point of `frame` ("" for a ghost), as a seed would give them."""
        truth = self.truth[frame]
        if truth is None:
            return []
        return [self.marker_names[t] if t >= 0 else "" for t in truth]


def full_label(label: str) -> str:
    """The "Subject:Marker" form of a file label; unprefixed labels get DEFAULT_SUBJECT."""
    subject, marker = split_label(label.strip())
    return f"{subject or DEFAULT_SUBJECT}:{marker}"


def corrupt(recording: Recording, level: str, seed: int) -> CorruptedSequence:
    """Apply corruption `level` ("L0".."L3", or one of STRESS_LEVELS) to `recording`, deterministically for
    `seed`.

    The file's own gaps are kept (NaN samples are simply absent from the cloud). Points whose label is no
    marker (`*N`, duplicate fragments such as `RBAC-1`) stay in the cloud as ghosts (truth -1).
    """
    if level not in ALL_LEVELS:
        raise ValueError(f"unknown corruption level {level!r}; valid levels: {', '.join(ALL_LEVELS)}")
    spec = ALL_LEVELS[level]
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(7)]
    rng_occl, rng_cluster, rng_noise, rng_near, rng_far, rng_drop, rng_shuffle = rngs

    points = np.array(recording.points_m, dtype=np.float64)  # (F, N, 3), copied: we write into it
    n_frames, n_points, _ = points.shape
    is_marker = np.array([is_marker_label(l) for l in recording.labels], dtype=bool)
    marker_cols = np.flatnonzero(is_marker)
    marker_names = tuple(full_label(recording.labels[i]) for i in marker_cols)
    truth_of_col = np.full(n_points, -1, dtype=np.int64)
    truth_of_col[marker_cols] = np.arange(len(marker_cols))

    visible = np.all(np.isfinite(points), axis=2)  # (F, N): the file's own gaps stay gaps
    hidden = np.zeros_like(visible)
    if spec.occluded_fraction > 0:
        for col in marker_cols:
            hidden[:, col] = occlusion_mask(n_frames, recording.rate_hz, spec.occluded_fraction, rng_occl)
    if spec.cluster_events_per_s > 0:
        hidden[:, marker_cols] |= cluster_dropouts(
            points[:, marker_cols], visible[:, marker_cols], recording.rate_hz, spec.cluster_events_per_s,
            rng_cluster,
        )
    visible &= ~hidden
    if spec.noise_sigma_m > 0:
        points += rng_noise.normal(0.0, spec.noise_sigma_m, size=points.shape)

    near = near_ghosts(points, visible & is_marker, recording.rate_hz, spec.near_ghosts_per_s, rng_near,
                       spec.ghost_lifetime_s)
    far = far_ghosts(recording.points_m, spec.far_ghost_fraction, rng_far)
    n_drop = int(round(spec.dropped_frame_fraction * n_frames))
    dropped = set(rng_drop.choice(n_frames, size=n_drop, replace=False).tolist()) if n_drop else set()

    out_points: list[np.ndarray | None] = []
    out_truth: list[np.ndarray | None] = []
    for f in range(n_frames):
        if f in dropped:
            out_points.append(None)
            out_truth.append(None)
            continue
        cols = np.flatnonzero(visible[f])
        extra = near[f] + far[f]
        cloud = np.concatenate([points[f, cols], np.reshape(extra, (-1, 3))], axis=0)
        truth = np.concatenate([truth_of_col[cols], np.full(len(extra), -1, dtype=np.int64)])
        order = rng_shuffle.permutation(len(cloud))
        out_points.append(cloud[order])
        out_truth.append(truth[order])
    return CorruptedSequence(
        points_m=out_points,
        truth=out_truth,
        marker_names=marker_names,
        rate_hz=float(recording.rate_hz),
        level=level,
        seed=seed,
        source=recording.source,
    )


def mean_gap_s() -> float:
    """Mean of the capped lognormal gap duration [s]: E[min(X, cap)], X ~ LogNormal(ln median, sigma).

    Closed form (partial expectation of a lognormal) so the visible-spell mean is exact, not sampled.
    """
    mu, s, cap = math.log(GAP_MEDIAN_S), GAP_LOG_SIGMA, GAP_MAX_S
    phi = lambda x: 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))  # noqa: E731 - standard normal CDF
    below = math.exp(mu + s * s / 2) * phi((math.log(cap) - mu - s * s) / s)
    return below + cap * (1.0 - phi((math.log(cap) - mu) / s))


def occlusion_mask(n_frames: int, rate_hz: float, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """(n_frames,) bool, True where hidden: alternating exponential visible spells and lognormal gaps.

    Spells are drawn in continuous time and a frame is hidden when its timestamp falls in a gap, so gaps
    shorter than a frame still contribute their expected share and the hidden fraction is `fraction`.
    The renewal process starts in a gap with probability `fraction` (its stationary state).
    """
    gap_mean_s = mean_gap_s()
    visible_mean_s = gap_mean_s * (1.0 - fraction) / fraction
    duration_s = n_frames / rate_hz
    mask = np.zeros(n_frames, dtype=bool)
    t = 0.0
    in_gap = rng.random() < fraction
    while t < duration_s:
        if in_gap:
            length = min(rng.lognormal(math.log(GAP_MEDIAN_S), GAP_LOG_SIGMA), GAP_MAX_S)
            first, end = math.ceil(t * rate_hz), math.ceil((t + length) * rate_hz)
            mask[first:end] = True
        else:
            length = rng.exponential(visible_mean_s)
        t += length
        in_gap = not in_gap
    return mask


def cluster_dropouts(
    points_m: np.ndarray, visible: np.ndarray, rate_hz: float, events_per_s: float, rng: np.random.Generator
) -> np.ndarray:
    """(F, M) bool hidden mask: Poisson events where a visible marker and its nearest neighbours vanish.

    Neighbours are the nearest visible markers at the event's first frame (one occluding limb or prop
    hides a whole patch of the body, not independent markers).
    """
    n_frames, n_markers, _ = points_m.shape
    hidden = np.zeros((n_frames, n_markers), dtype=bool)
    n_events = rng.poisson(events_per_s * n_frames / rate_hz)
    for _ in range(n_events):
        f0 = int(rng.integers(n_frames))
        cols = np.flatnonzero(visible[f0])
        if len(cols) == 0:
            continue
        centre = rng.choice(cols)
        dist = np.linalg.norm(points_m[f0, cols] - points_m[f0, centre], axis=1)
        group = cols[np.argsort(dist)[: CLUSTER_NEIGHBOURS + 1]]  # includes the centre (distance 0)
        n = max(1, int(round(rng.uniform(*CLUSTER_DURATION_S) * rate_hz)))
        hidden[f0 : f0 + n, group] = True
    return hidden


def near_ghosts(
    points_m: np.ndarray, visible: np.ndarray, rate_hz: float, births_per_s: float, rng: np.random.Generator,
    lifetime_s: float = GHOST_LIFETIME_MEAN_S,
) -> list[list[np.ndarray]]:
    """Per frame, the positions of near-body ghost tracks alive then.

    Each track is born near a random visible marker (uniform direction, distance uniform in
    GHOST_DISTANCE_M), lives an exponential time (mean `lifetime_s`, at least one frame) and random-walks
    with an expected step of about GHOST_DRIFT_M_PER_FRAME (a reflection off skin or clothing that wanders).
    """
    n_frames = points_m.shape[0]
    ghosts: list[list[np.ndarray]] = [[] for _ in range(n_frames)]
    if births_per_s <= 0:
        return ghosts
    # Per-axis sigma so that the expected 3D step length is the drift (E|N(0, s^2 I3)| = s * sqrt(8/pi)).
    step_sigma_m = GHOST_DRIFT_M_PER_FRAME / math.sqrt(8.0 / math.pi)
    births = rng.poisson(births_per_s / rate_hz, size=n_frames)
    for f0 in np.flatnonzero(births):
        cols = np.flatnonzero(visible[f0])
        if len(cols) == 0:
            continue
        for _ in range(births[f0]):
            anchor = points_m[f0, rng.choice(cols)]
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            pos = anchor + direction * rng.uniform(*GHOST_DISTANCE_M)
            n = max(1, int(round(rng.exponential(lifetime_s) * rate_hz)))
            for f in range(f0, min(f0 + n, n_frames)):
                ghosts[f].append(pos)
                pos = pos + rng.normal(0.0, step_sigma_m, size=3)
    return ghosts


def far_ghosts(points_m: np.ndarray, fraction: float, rng: np.random.Generator) -> list[list[np.ndarray]]:
    """Per frame, at most one ghost anywhere in the capture volume, in `fraction` of the frames.

    The volume is the bounding box of all the recording's points grown by FAR_GHOST_MARGIN_M, floor
    (z = 0) included.
    """
    n_frames = points_m.shape[0]
    ghosts: list[list[np.ndarray]] = [[] for _ in range(n_frames)]
    if fraction <= 0:
        return ghosts
    flat = points_m.reshape(-1, 3)
    flat = flat[np.all(np.isfinite(flat), axis=1)]
    lo = flat.min(axis=0) - FAR_GHOST_MARGIN_M
    hi = flat.max(axis=0) + FAR_GHOST_MARGIN_M
    lo[2] = min(lo[2] + FAR_GHOST_MARGIN_M, 0.0)
    for f in np.flatnonzero(rng.random(n_frames) < fraction):
        ghosts[f].append(rng.uniform(lo, hi))
    return ghosts
