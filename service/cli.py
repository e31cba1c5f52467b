"""`mocap-service`: the command line. It only builds the frozen config and calls the daemon or the offline
labeler; a bad flag or file gets one sentence on stderr and exit status 2, never a traceback."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

# One BLAS thread, set before numpy loads: the engine's arrays are tiny, and BLAS threads that spin-wait
# beside the frame loop and XLA's solver thread on a 2-core machine cost far more than they give (a
# 300 x 300 solve took 0.37 s instead of 2 ms under that contention).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from service.config import ConfigError, load_config  # noqa: E402 - after the thread settings

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
CACHE_HELP = 'compilation caches: JAX\'s, and the tracker kernels\' under numba/ ("" disables JAX\'s)'


class UsageError(Exception):
    """A bad flag or input file; its message is the one sentence the user sees."""


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (argparse prints usage plus the error by default)."""

    def error(self, message: str):
        raise UsageError(f"{self.prog}: {message} (see --help)")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mocap-service", description="Realtime labeling of optical motion-capture markers.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="{serve,label}")

    serve = sub.add_parser("serve", help="run the daemon until SIGINT/SIGTERM",
                           description="Run the labeling daemon until SIGINT/SIGTERM.")
    serve.add_argument("--frames", metavar="EP", help="endpoint to bind for incoming frames (SUB)")
    serve.add_argument("--publish", metavar="EP", help="endpoint to bind for results (PUB)")
    serve.add_argument("--control", metavar="EP", help="endpoint to bind for commands (REP)")
    serve.add_argument("--config", metavar="FILE", help="TOML configuration file")
    serve.add_argument("--state-dir", metavar="DIR", help="where subject calibrations are kept")
    serve.add_argument("--cache-dir", metavar="DIR", help=CACHE_HELP)
    serve.add_argument("--max-skip-frames", metavar="K", type=int,
                       help="frames the skeleton solve may be skipped in a row (0 = solve every frame)")
    serve.add_argument("--busy-poll", metavar="S", type=float, dest="busy_poll_s",
                       help="after each frame, wait for the next this long [s] without sleeping: lower latency "
                            "for one core spinning while frames stream (default 0: off)")
    serve.add_argument("--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS)

    label = sub.add_parser("label", help="label a C3D file offline (causal, same engine as the daemon)",
                           description="Label a C3D recording offline, causally, with the daemon's engine.")
    label.add_argument("input", metavar="IN.c3d", help="recording with unlabeled points")
    label.add_argument("-o", "--output", metavar="OUT.c3d", required=True, help="labeled C3D to write")
    label.add_argument("--seed-frames", metavar="K", type=int, default=0,
                       help="frames < K use the file's point names as seed labels")
    label.add_argument("--max-skip-frames", metavar="K", type=int,
                       help="frames the skeleton solve may be skipped in a row (0 = solve every frame)")
    label.add_argument("--config", metavar="FILE", help="TOML configuration file")
    label.add_argument("--cache-dir", metavar="DIR", help=CACHE_HELP)
    label.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    label.add_argument("--log-level", default="WARNING", type=str.upper, choices=LOG_LEVELS)
    return parser


def _prepare_caches(cache_dir: str) -> None:
    """Create the compilation cache directory (a bad one is a usage error, not a traceback from deep in
    JAX) and keep the tracker's compiled loops (numba) beside JAX's compilations, in cache_dir/numba, so
    one directory holds a warm start and an empty one measures a cold start. Before numba loads: it reads
    NUMBA_CACHE_DIR once. (With no cache directory numba keeps its own default, beside the source.)"""
    if not cache_dir:
        return
    path = Path(cache_dir).expanduser() / "numba"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"mocap-service: cannot use cache directory {cache_dir}: {e.strerror or e}") from None
    os.environ.setdefault("NUMBA_CACHE_DIR", str(path))


def _serve(args) -> int:
    config = load_config(args.config, frames_endpoint=args.frames, publish_endpoint=args.publish,
                         control_endpoint=args.control, state_dir=args.state_dir, cache_dir=args.cache_dir,
                         busy_poll_s=args.busy_poll_s, engine_max_skip_frames=args.max_skip_frames)
    _prepare_caches(config.cache_dir)
    from service.daemon import Daemon, DaemonError  # after the config: a bad flag must not wait for jax
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    try:
        Daemon(config).run(stop)
    except DaemonError as e:
        print(f"mocap-service: {e}", file=sys.stderr)
        return 1
    return 0


def _label(args) -> int:
    from recordings.c3d import C3DError, read_c3d, write_c3d

    config = load_config(args.config, cache_dir=args.cache_dir, engine_max_skip_frames=args.max_skip_frames)
    if args.seed_frames < 0:
        raise UsageError(f"mocap-service: --seed-frames must be >= 0, got {args.seed_frames}")
    out_dir = Path(args.output).expanduser().resolve().parent
    if not out_dir.is_dir():  # checked first: finding out after labeling a long recording wastes the run
        raise UsageError(f"mocap-service: cannot write {args.output}: directory {out_dir} does not exist")
    try:
        recording = read_c3d(args.input)
    except C3DError as e:  # its message is already one sentence naming the file
        raise UsageError(f"mocap-service: {e}") from None
    except OSError as e:
        raise UsageError(f"mocap-service: cannot read {args.input}: {e.strerror or e}") from None
    _prepare_caches(config.cache_dir)
    from service.daemon import enable_compilation_cache  # imported late: jax costs seconds, errors do not
    from service.offline import label_recording

    enable_compilation_cache(config.cache_dir)
    points_m, labels = label_recording(recording, config, seed_frames=args.seed_frames,
                                       progress=not args.no_progress)
    if not labels:  # a C3D needs a point to hold; an empty file would pass for a result
        why = (f"its first {args.seed_frames} frames name no marker" if args.seed_frames else
               "no frame shows a person standing in a T-pose, and no seed labels were given (--seed-frames K)")
        print(f"mocap-service: no subject found in {args.input}: {why}; nothing written", file=sys.stderr)
        return 1
    try:
        write_c3d(args.output, points_m, labels, recording.rate_hz)
    except C3DError as e:
        raise UsageError(f"mocap-service: {e}") from None
    except OSError as e:
        raise UsageError(f"mocap-service: cannot write {args.output}: {e.strerror or e}") from None
    logging.getLogger(__name__).info("labeled %d frames, %d markers -> %s", len(points_m), len(labels),
                                     args.output)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `mocap-service` console script; returns the exit status."""
    try:
        args = _parser().parse_args(argv)
        logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        return _serve(args) if args.command == "serve" else _label(args)
    except UsageError as e:
        print(e, file=sys.stderr)
        return 2
    except ConfigError as e:
        print(f"mocap-service: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mocap-service: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
