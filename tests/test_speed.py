"""benchmarks/speed.py: the per-frame engine cost calls the engine as the daemon does, and times each path."""

from __future__ import annotations

import time
import types

import numpy as np

from benchmarks import speed


class _RecordingEngine:
    """Stands in for service.engine.Engine: records the calls, each taking a known time."""

    calls: list = []

    def warm_up(self) -> float:
        return 0.0

    def step(self, frame, defer=False):
        type(self).calls.append(("step", frame.frame, defer))
        time.sleep(0.001)
        return [], None

    def complete(self, outputs):
        type(self).calls.append(("complete",))
        time.sleep(0.001)
        return outputs

    def between_frames(self):
        type(self).calls.append(("between",))
        time.sleep(0.001)


def test_engine_cost_calls_the_engine_as_the_daemon_does_and_times_labels_pose_and_whole_frame(monkeypatch):
    from service import engine, worker

    _RecordingEngine.calls = []
    monkeypatch.setattr(engine, "Engine", _RecordingEngine)
    monkeypatch.setattr(worker, "shared", lambda: types.SimpleNamespace(cpu_s=lambda: 0.0, wait_idle=lambda: None))
    rate = 100.0
    n_seed = int(round(speed.SEED_S * rate))
    n = n_seed + 10
    points = [np.zeros((2, 3))] * n
    seq = types.SimpleNamespace(points_m=points, rate_hz=rate, truth=[[0, -1]] * n, marker_names=["A"])
    out = speed._cost_run(seq, 0.1, paced=False)

    # per frame, in the daemon's order: labels (deferred bookkeeping), then the pose, then between frames
    assert _RecordingEngine.calls[:3] == [("step", 0, True), ("complete",), ("between",)]
    assert _RecordingEngine.calls == [c for f in range(n) for c in (("step", f, True), ("complete",), ("between",))]
    assert out["frames"] == 10
    # each path includes the one before it: ~1, ~2 and ~3 ms of the stand-in's sleeps
    assert 1.0 <= out["labels_mean_ms"] < out["pose_mean_ms"] < out["frame_mean_ms"]
    assert out["frame_mean_ms"] >= 3.0
