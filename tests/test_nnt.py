"""benchmarks.nnt, the nearest-neighbour baseline, on small sequences built here."""

import numpy as np

from benchmarks.nnt import NearestNeighbourTracker, run_nnt
from benchmarks.score import score
from recordings.corruption import corrupt
from recordings.recording import Recording

RATE_HZ = 100.0


def walking_grid(n_frames: int = 600, speed_m_s: float = 1.0) -> Recording:
    """12 markers on a 10 cm grid translating along x: they never come within 10 cm of each other."""
    grid = np.array([[x, y, 1.0] for x in (0.0, 0.1, 0.2) for y in (0.0, 0.1, 0.2, 0.3)])
    t = np.arange(n_frames) / RATE_HZ
    points = grid[None] + (speed_m_s * t)[:, None, None] * np.array([1.0, 0.0, 0.0])
    return Recording(points, tuple(f"S:M{i}" for i in range(len(grid))), RATE_HZ)


def test_perfect_at_l0_without_crossings():
    seq = corrupt(walking_grid(), "L0", seed=0)
    for velocity in (False, True):
        s = score(seq, run_nnt(seq, velocity=velocity), "seeded", seq.seed_frames)
        assert s.accuracy == 1.0 and s.precision == 1.0


def test_unseeded_labels_nothing():
    seq = corrupt(walking_grid(100), "L0", seed=0)
    assert all(l == "" for labels in run_nnt(seq, seeded=False) for l in labels)


def test_gate_one_to_one_and_ghosts():
    tracker = NearestNeighbourTracker(gate_m=0.03)
    assert tracker.step(np.array([[0.0, 0, 0], [1.0, 0, 0]]), ["S:A", "S:B"]) == ["S:A", "S:B"]
    # A moved 2 cm, a ghost 1 cm from B's last position and B 2.5 cm away: B takes the nearer (the ghost)
    out = tracker.step(np.array([[1.025, 0, 0], [0.02, 0, 0], [5.0, 0, 0], [1.0, 0.01, 0]]))
    assert out == ["", "S:A", "", "S:B"]
    # a jump beyond the gate loses the marker; it keeps its last position and is found there again
    assert tracker.step(np.array([[0.2, 0, 0]])) == [""]
    assert tracker.step(np.array([[0.03, 0, 0]])) == ["S:A"]


def test_velocity_follows_fast_markers_that_plain_nnt_loses():
    fast = walking_grid(300, speed_m_s=4.0)  # 4 cm per frame: more than the gate
    seq = corrupt(fast, "L0", seed=1)
    plain = score(seq, run_nnt(seq), "seeded", seq.seed_frames)
    velocity = score(seq, run_nnt(seq, velocity=True), "seeded", seq.seed_frames)
    assert plain.accuracy == 0.0
    assert velocity.accuracy == 1.0


def test_labels_in_a_frame_reseed_the_tracker():
    tracker = NearestNeighbourTracker()
    tracker.step(np.array([[0.0, 0, 0]]), ["S:A"])
    assert tracker.step(np.array([[0.5, 0, 0]])) == [""]
    assert tracker.step(np.array([[0.5, 0, 0], [0.9, 0, 0]]), ["", "S:A"]) == ["", "S:A"]
    assert tracker.step(np.array([[0.91, 0, 0], [0.5, 0, 0]])) == ["S:A", ""]
    assert tracker.step(np.array([[np.nan, 0, 0], [0.92, 0, 0]])) == ["", "S:A"]
