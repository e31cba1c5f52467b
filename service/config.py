"""One frozen configuration for the engine and the daemon. The CLI and the TOML loader only build it.

Every field carries its unit in its name or docstring. Fields marked *shape* change array shapes of the
jitted solve: changing them costs one recompilation (1-2 s), nothing else does.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path


class ConfigError(ValueError):
    """A configuration file or flag is invalid; the message says what is valid."""


def _check_non_negative(config) -> None:
    """Every number of a config is a size, a time or a distance: none may be negative."""
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and v < 0:
            raise ConfigError(f"{f.name} must be >= 0, got {v}")


@dataclasses.dataclass(frozen=True)
class EngineConfig:
    """Tracking-engine parameters."""

    max_markers: int = 96
    """*shape* Markers per subject the solve is compiled for (padded with masks)."""
    max_skip_frames: int = 10
    """Frames in a row the skeleton solve may be skipped while NNT labels everything (0 = solve always)."""
    max_skip_s: float = 0.1
    """... and at most this long [s]: the paper's 10 frames at 100 Hz, 5 at 50 Hz (a stale pose is a poor
    start for the solve and a poor predictor on a fast limb)."""
    nnt_gate_m: float = 0.03
    """Gate [m] between a tracked marker's predicted position (velocity, acceleration) and a point; the
    tracker widens it with the marker's step and with the frame interval (`tracker.NNT_UNMODELED_ACC_M_S2`:
    5 mm more at 50 Hz, under 1 mm at 120 Hz)."""
    reacquire_gate_m: float = 0.045
    """Gate [m] between a skeleton-predicted (occluded) marker and a point for the Hungarian assignment."""
    rigid_check_m: float = 0.025
    """A tracked label farther than this [m] (plus 4x the partners' misfit) from where its rigid partners put
    the marker is withdrawn (swaps, ghosts)."""
    reject_residual_m: float = 0.06
    """A label whose point is farther than this [m] from the fitted model is withdrawn."""
    prior_weight: float = 0.05
    """Weight of the prior pulling the pose toward its prediction, relative to one marker residual [m/rad]."""
    solver_max_steps: int = 10
    """Most Gauss-Newton iterations per solve (it stops sooner once converged: 4-6 typically). The solve
    starts from the last fitted pose, up to max_skip_frames old: a fast limb needs more than 3 steps."""
    solver_rtol: float = 3e-3
    """Relative tolerance of the Gauss-Newton solve (on the pose and on the residual)."""
    solver_atol: float = 3e-4
    """Absolute tolerance of the Gauss-Newton solve [m, rad]: far below skin motion and marker noise."""
    tpose_auto: bool = True
    """Detect people standing in a T-pose in unlabeled points and create subjects from them."""
    tpose_window_frames: int = 60
    """Frames a subject found in a T-pose is on trial: labeled from the frame it is found, it is dropped
    unless it still holds the T-pose at their end, when the markers hidden as it was found join it."""
    merge_radius_m: float = 0.005
    """Points closer than this [m] are one marker reconstructed twice (two camera sets' rays, an exporter's
    copy): only one of them is labeled. Body markers never come this close (their centres lie a diameter
    apart, 6-25 mm); lower it for facial markers spaced closer than that; 0 keeps every point."""
    max_points: int = 4096
    """Frames with more points are rejected as malformed (a capture volume never sees that many)."""

    def __post_init__(self) -> None:
        _check_non_negative(self)
        if self.max_markers < 4:
            raise ConfigError(f"max_markers must be >= 4, got {self.max_markers}")


@dataclasses.dataclass(frozen=True)
class ServiceConfig:
    """Daemon parameters (endpoints, queues, state)."""

    frames_endpoint: str = "tcp://127.0.0.1:7701"
    """Where the daemon binds its SUB socket for frames."""
    publish_endpoint: str = "tcp://127.0.0.1:7702"
    """Where the daemon binds its PUB socket for labels, poses, skeletons and status."""
    control_endpoint: str = "tcp://127.0.0.1:7703"
    """Where the daemon binds its REP socket for commands."""
    state_dir: str = "~/.local/state/mocap-labeler"
    """Directory where subject calibrations are saved on stop/`save` and restored on start."""
    status_period_s: float = 1.0
    """Seconds between two `status` messages."""
    max_queue_frames: int = 64
    """Frames the daemon buffers (ZeroMQ high-water mark); beyond it the oldest are dropped and counted."""
    cache_dir: str = "~/.cache/mocap-labeler/jax"
    """Compilation caches: JAX's persistent cache, and under numba/ the tracker's compiled loops ("" disables
    JAX's; numba then keeps its default, beside the source)."""
    busy_poll_s: float = 0.0
    """For this long [s] after each frame the daemon waits for the next by polling without sleeping (0 = it
    sleeps until a message arrives). A stream faster than 1/busy_poll_s keeps one core spinning between
    frames, and in exchange the CPU stays awake: on our 2-core machine the latency p50 went 2.3 -> 1.9 ms
    at 120 Hz (BENCHMARK.md). For a dedicated capture machine; an idle daemon never spins."""
    engine: EngineConfig = dataclasses.field(default_factory=EngineConfig)

    def __post_init__(self) -> None:
        _check_non_negative(self)


def _build(cls, table: dict, where: str):
    names = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in table.items():
        if key not in names:
            valid = ", ".join(sorted(n for n in names if n != "engine"))
            raise ConfigError(f"unknown key {where}{key!r}; valid keys: {valid}")
        if key == "engine":
            if not isinstance(value, dict):
                raise ConfigError("[engine] must be a table")
            value = _build(EngineConfig, value, "engine.")
        else:
            default = getattr(cls(), key)
            if isinstance(default, bool) != isinstance(value, bool) or not isinstance(
                value, (type(default), int) if isinstance(default, float) else type(default)
            ):
                raise ConfigError(f"{where}{key} must be {type(default).__name__}, got {value!r}")
        kwargs[key] = value
    return cls(**kwargs)


def load_config(path: str | Path | None = None, **overrides) -> ServiceConfig:
    """Build a ServiceConfig from an optional TOML file, then keyword overrides (None values ignored).

    The file has top-level daemon keys and an ``[engine]`` table, with the field names above.
    """
    table: dict = {}
    if path is not None:
        try:
            table = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(f"config file {path} does not exist") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ConfigError(f"config file {path} is not valid TOML: {e}") from None
    engine_over = {k[len("engine_"):]: v for k, v in overrides.items() if k.startswith("engine_") and v is not None}
    service_over = {k: v for k, v in overrides.items() if not k.startswith("engine_") and v is not None}
    if engine_over:
        table.setdefault("engine", {}).update(engine_over)
    table.update(service_over)
    return _build(ServiceConfig, table, "")
