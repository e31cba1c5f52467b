"""Helpers shared by the tracker's tests (test_tracker, test_partners, test_segment_search, test_layouts):
the frame clock, a subject seeded from given labels, the tracker run over shuffled points, and the synthetic
performer with segments turned unseen."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from recordings.synthetic import perform
from service import track_state, tracker
from service.config import EngineConfig

CONFIG = EngineConfig()
RATE_HZ = 120.0


def t_ns(f: int) -> int:
    return int(round(f * 1e9 / RATE_HZ))


def seeded_state(points_m: np.ndarray, seed_frames: int):
    """A subject model without skeleton, and its state after `seed_frames` of given labels (observe)."""
    m = points_m.shape[1]
    model = track_state.SubjectModel("P", tuple(f"M{i}" for i in range(m)), np.zeros(m, int), np.zeros((m, 3)),
                                     np.zeros((14, 3)))
    st = tracker.new_state(model, points_m[0], t_ns(0), points_m[:1])
    for f in range(1, seed_frames):
        st, _ = tracker.observe(model, st, points_m[f], t_ns(f), CONFIG)
    return model, st


def turned_unseen(rng, turns: dict, measured_layouts: bool = False):
    """The synthetic performer (seed 3) at a random pose, tracked with its skeleton there, and the same
    pose after `turns` ({segment: (axis, degrees)}) turned those segments at their joints unseen.
    Returns (perf, model, state, markers before (M, 3), markers after (M, 3), after(root) the turned pose
    with its root moved to `root`)."""
    from protocol.skeleton import SEGMENTS
    from service.calibration import world_transforms

    perf = perform(3, duration_s=0.1)
    layout = dict(layout_offsets_m=perf.marker_offsets_m, layout_rms_m=np.full(len(perf.marker_names), 0.002))
    model = track_state.SubjectModel("P", perf.marker_names, perf.marker_segment, perf.marker_offsets_m,
                                     perf.joint_offsets_m, True, **(layout if measured_layouts else {}))
    R_old = Rotation.from_rotvec(rng.normal(0.0, 0.2, (14, 3))).as_matrix()
    t = np.array([0.3, -0.2, 0.95])
    R_new = R_old.copy()
    for name, (axis, degrees) in turns.items():
        k = SEGMENTS.index(name)
        R_new[k] = Rotation.from_euler(axis, degrees, degrees=True).as_matrix() @ R_old[k]

    def markers(R, root=t):
        Rw, pw = world_transforms(root, R, perf.joint_offsets_m)
        return np.einsum("mij,mj->mi", Rw[perf.marker_segment], perf.marker_offsets_m) + pw[perf.marker_segment]

    old = markers(R_old)
    st = tracker.new_state(model, old, t_ns(0))
    st.t_root_m, st.R_parent_segment = t, R_old
    return perf, model, st, old, markers(R_new), lambda root: markers(R_new, root)


def run_tracker(points_m: np.ndarray, seed_frames: int, shuffle_seed: int = 0, ghosts_m=None):
    """Seed, then step every later frame with the points shuffled; returns per frame the true marker each
    marker slot was given (-1 = none, -2 = a ghost)."""
    rng = np.random.default_rng(shuffle_seed)
    model, st = seeded_state(points_m, seed_frames)
    got = np.full(points_m.shape[:2], -1)
    for f in range(seed_frames, len(points_m)):
        seen = np.flatnonzero(np.isfinite(points_m[f, :, 0]))
        cloud, truth = points_m[f, seen], seen
        if ghosts_m is not None:
            cloud = np.concatenate([cloud, ghosts_m[f]])
            truth = np.concatenate([truth, np.full(len(ghosts_m[f]), -2)])
        order = rng.permutation(len(cloud))
        cloud, truth = cloud[order], truth[order]
        st, res = tracker.step(model, st, cloud, np.ones(len(cloud), bool), t_ns(f), CONFIG)
        idx = res.point_index
        got[f] = np.where(idx >= 0, truth[np.maximum(idx, 0)], -1)
    return got
