"""The engine's helper process: skeleton calibration and refinement, beside the frame loop.

These jobs take 50-500 ms of numpy, scipy and Python. On a thread of the daemon's own process they held the
interpreter lock against the frame loop: frames that met them took 2-10 ms instead of about 1 ms (they made
the engine's p99). In a process of their own they share nothing with it but the CPU.

`Worker.submit(fn, *args)` returns a `concurrent.futures.Future`. `fn` must be a module-level function and
its arguments and result picklable. Jobs and results travel pickled over the child's stdin and a pipe of its
own: both ends are this module, in processes it started itself (nothing from the network is unpickled).

The child is `python -m service.worker`, not multiprocessing's spawn, which re-runs the parent's main script
in the child (any user script driving an `Engine` would have needed an `if __name__ == "__main__"` guard).
It is started on the first job, exits when its stdin closes (the parent stopped or died), and is started
again if it dies: its pending jobs then fail with `WorkerError`, and the engine goes on without their result.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
from pathlib import Path

_HEADER = struct.Struct("<QQ")  # job id, payload length
_REPO = Path(__file__).resolve().parents[1]


class WorkerError(RuntimeError):
    """The helper process failed a job, or died with it pending."""


class Worker:
    """One helper process, its jobs run one at a time, in order."""

    def __init__(self, cache_dir: str = ""):
        self.cache_dir = cache_dir
        self._lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        self._pending: dict[int, concurrent.futures.Future] = {}  # the running child's jobs not yet answered
        self._next_id = 0
        self._outbox: queue.SimpleQueue | None = None  # the running child's jobs, written by a thread of their own

    def submit(self, fn, *args) -> concurrent.futures.Future:
        future: concurrent.futures.Future = concurrent.futures.Future()
        payload = pickle.dumps((fn, args), protocol=pickle.HIGHEST_PROTOCOL)
        with self._lock:
            self._running()
            job = self._next_id
            self._next_id += 1
            self._pending[job] = future
            # written by another thread: a child busy with a job reads the next only then, and a frame loop
            # writing a history of a few hundred kB into the full pipe would wait for it
            self._outbox.put(_HEADER.pack(job, len(payload)) + payload)
        return future

    def cpu_s(self) -> float:
        """CPU time [s] the running helper process has used (Linux; NaN elsewhere or with none running)."""
        proc = self._proc
        try:
            fields = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime
        except (AttributeError, OSError, ValueError, IndexError):
            return float("nan")

    def wait_idle(self, timeout_s: float | None = None) -> None:
        """Wait until every job submitted so far is answered (a benchmark's back-to-back frame loop: it
        outruns the stream time the engine gives a job, which a live stream gives in wall time)."""
        with self._lock:
            pending = list(self._pending.values())
        concurrent.futures.wait(pending, timeout=timeout_s)

    def close(self) -> None:
        """Stop the helper process (its pending jobs fail)."""
        with self._lock:
            proc, self._proc = self._proc, None
            if self._outbox is not None:
                self._outbox.put(None)
        if proc is not None:
            try:
                proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                proc.kill()

    def _running(self) -> subprocess.Popen:
        if self._proc is not None and self._proc.poll() is None:
            return self._proc
        read_fd, write_fd = os.pipe()  # results come back on a pipe of their own: stdout stays for prints
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(_REPO), env.get("PYTHONPATH", "")]))
        env.setdefault("OPENBLAS_NUM_THREADS", "1")
        env.setdefault("OMP_NUM_THREADS", "1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "service.worker", str(write_fd), self.cache_dir],
            stdin=subprocess.PIPE, pass_fds=(write_fd,), env=env, cwd=_REPO,
        )
        os.close(write_fd)
        self._proc = proc
        self._pending = {}  # its own: a dead child's reader fails its jobs, not its successor's
        self._outbox = queue.SimpleQueue()
        threading.Thread(target=self._write, args=(proc, self._outbox), name="mocap-worker-jobs", daemon=True).start()
        threading.Thread(target=self._read, args=(proc, os.fdopen(read_fd, "rb"), self._pending),
                         name="mocap-worker-results", daemon=True).start()
        return proc

    @staticmethod
    def _write(proc: subprocess.Popen, outbox: queue.SimpleQueue) -> None:
        """Feed the child its jobs; stop at None (close) or when it is gone (the reader fails the jobs)."""
        while (data := outbox.get()) is not None:
            try:
                proc.stdin.write(data)
                proc.stdin.flush()
            except (OSError, ValueError):
                return
        try:
            proc.stdin.close()
        except OSError:
            pass

    def _read(self, proc: subprocess.Popen, results, pending: dict) -> None:
        """Complete the futures as results arrive; when the child is gone, fail what is left."""
        with results:
            while True:
                head = results.read(_HEADER.size)
                if len(head) < _HEADER.size:
                    break
                job, n = _HEADER.unpack(head)
                ok, value = pickle.loads(results.read(n))
                with self._lock:
                    future = pending.pop(job, None)
                if future is not None:
                    future.set_result(value) if ok else future.set_exception(WorkerError(value))
        with self._lock:
            left = list(pending.values())
            pending.clear()
            # the next job starts a new child: its pipes are closed, but its exit may not be visible yet
            # (poll() still None), and a job written to it then was never answered nor failed
            if self._proc is proc:
                self._proc = None
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
        for future in left:
            future.set_exception(WorkerError(f"the helper process exited (status {proc.poll()})"))


_SHARED: Worker | None = None
_SHARED_LOCK = threading.Lock()


def shared() -> Worker:
    """The helper process of this process's engines (one for all: their jobs are few and short)."""
    global _SHARED
    with _SHARED_LOCK:
        if _SHARED is None:
            import jax

            _SHARED = Worker(jax.config.jax_compilation_cache_dir or "")
            atexit.register(_SHARED.close)
        return _SHARED


def _serve(result_fd: int, cache_dir: str) -> None:
    if cache_dir:
        from service.daemon import enable_compilation_cache

        enable_compilation_cache(cache_dir)
    jobs, results = sys.stdin.buffer, os.fdopen(result_fd, "wb")
    while True:
        head = jobs.read(_HEADER.size)
        if len(head) < _HEADER.size:
            return  # the parent closed our stdin (or died)
        job, n = _HEADER.unpack(head)
        try:
            fn, args = pickle.loads(jobs.read(n))
            out = (True, fn(*args))
        except Exception as e:  # noqa: BLE001 - a failed job is reported to its caller, the worker lives on
            out = (False, f"{type(e).__name__}: {e}")
        payload = pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            results.write(_HEADER.pack(job, len(payload)) + payload)
            results.flush()
        except BrokenPipeError:
            return  # the parent went away mid-job: nobody is left to answer


if __name__ == "__main__":
    _serve(int(sys.argv[1]), sys.argv[2] if len(sys.argv) > 2 else "")
