"""A Dask cluster of separate processes, as a user starts one beside ``aerocal process --dask ADDRESS``.

A ``dask scheduler`` and ``n`` ``dask worker`` processes on 127.0.0.1 (each in its own working folder, one
thread, its own process group), with the environment the product gives its own local workers (one BLAS
thread) and the repository on their path. Used by the cluster tests and by the benchmarks that compare such a
cluster with the local one.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent
REPOSITORY = Path(__file__).resolve().parents[1]
#: the environment of the worker processes: what :data:`aerocal.matching.cluster.WORKER_ENVIRONMENT` gives the
#: product's own workers (one BLAS thread, glibc's malloc left alone)
WORKER_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


@dataclass(frozen=True)
class ProcessCluster:
    """A running cluster: the scheduler's address and the worker processes (each its own process group, so
    that a test can kill one with its nanny)."""

    address: str
    workers: tuple[subprocess.Popen, ...]


def wait_for(what: str, ready: Callable[[], bool], timeout_s: float = 60.0,
             procs: Sequence[subprocess.Popen] = ()) -> None:
    """Poll ``ready`` every 0.2 s; raise naming ``what`` when a process of ``procs`` exits first or after
    ``timeout_s`` seconds."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"{what}: a process exited with {p.returncode} before it was ready")
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not ready after {timeout_s:.0f} s")
        time.sleep(0.2)


@contextmanager
def process_cluster(work: Path, n_workers: int = 2, memory_limit: str = "0") -> Iterator[ProcessCluster]:
    """Start a scheduler and ``n_workers`` single-threaded workers under ``work``; stop them (SIGTERM, then
    SIGKILL after 20 s) on exit.

    Args:
        work: an existing folder; the scheduler file and one working folder per worker go there.
        n_workers: worker processes.
        memory_limit: each worker's ``--memory-limit`` (``"0"``: none, so that a benchmark measures a
            worker's peak instead of Dask's spilling).

    Raises:
        RuntimeError, TimeoutError: a process exited, or the workers did not register within 60 s.
    """
    from distributed import Client  # lazy: distributed costs ~1 s to import

    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"} | WORKER_ENV
    # the repository on the workers' path too, for functions of the tests and benchmarks sent to them
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(REPOSITORY), env.get("PYTHONPATH"))))
    sched_file = work / "scheduler.json"
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)], env=env, cwd=work,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)]
    try:
        wait_for("dask scheduler", sched_file.is_file, procs=procs)
        address = json.loads(sched_file.read_text())["address"]
        for k in range(n_workers):
            folder = work / f"worker{k}"
            folder.mkdir()
            procs.append(subprocess.Popen(
                [str(BIN / "dask"), "worker", address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                 "--memory-limit", memory_limit, "--local-directory", str(folder), "--name", f"w{k}"],
                env=env, cwd=folder, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True))
        with Client(address, timeout=30) as client:
            wait_for(f"{n_workers} dask workers", lambda: len(client.scheduler_info()["workers"]) == n_workers,
                     procs=procs)
            pids = client.run(os.getpid)
        if os.getpid() in pids.values():
            raise RuntimeError("a dask worker runs in this process; the cluster is not of separate processes")
        yield ProcessCluster(address, tuple(procs[1:]))
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
