"""Running matching work on a Dask cluster, or serially when there is none.

The science functions know nothing of Dask: they are plain functions of arrays. This module submits
them to a ``distributed.Client`` (imported lazily, so the engine works without Dask installed) and
reports progress through an optional ``progress(done, total)`` callback.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2

Progress = Callable[[int, int], None]


#: Environment of the worker processes (Dask's ``distributed.nanny.pre-spawn-environ``): one BLAS/OpenMP
#: thread each, as Dask sets by default, but glibc's malloc left alone. Dask's default
#: ``MALLOC_TRIM_THRESHOLD_=65536`` also freezes glibc's mmap threshold at 128 kB, so every numpy temporary
#: above it (a 256 x 256 float64 tile plane, a descriptor distance matrix) is mapped and zeroed afresh, which
#: made an orthomosaic tile several times slower (``benchmarks/history/engine_measurements.md``). A cluster
#: started elsewhere (``--dask ADDRESS``) should unset it too.
WORKER_ENVIRONMENT = {"MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1,
                      "OPENBLAS_NUM_THREADS": 1}


@contextlib.contextmanager
def local_client(n_workers: int = 2, threads_per_worker: int = 1) -> Iterator[object]:
    """A ``distributed.Client`` on a fresh ``LocalCluster`` of worker processes, closed on exit.

    One thread per worker process: OpenCV and numpy then use one core each (the workers call
    ``cv2.setNumThreads(1)``), and the GIL does not serialise the Python parts. No dashboard. The worker
    processes get :data:`WORKER_ENVIRONMENT`.

    Args:
        n_workers: worker processes to start (default 2).
        threads_per_worker: threads of each worker process (default 1).

    Returns:
        A context manager whose ``with`` value is the ``distributed.Client``; the cluster starts on entering it.
        On exit the workers' heartbeats are silenced, the cluster is scaled to no workers (waiting at most
        :data:`WORKER_CLOSE_TIMEOUT_S` seconds for them to leave), then the client and the cluster are closed.

    Raises:
        ImportError: ``dask``/``distributed`` is not installed (imported on entering the context, not with this
            module).
    """
    # lazy: dask + distributed are slow to import; only runs on a cluster need them
    import dask
    from distributed import Client, LocalCluster

    with dask.config.set({"distributed.nanny.pre-spawn-environ": WORKER_ENVIRONMENT}):
        cluster = LocalCluster(
            n_workers=n_workers, threads_per_worker=threads_per_worker, dashboard_address=None, processes=True
        )
    try:
        client = Client(cluster)
        try:
            yield client
        finally:
            _quiet_teardown(client)
            _close_workers(cluster)
            client.close()
    finally:
        cluster.close()


#: seconds to wait for the workers to leave before the scheduler closes anyway
WORKER_CLOSE_TIMEOUT_S = 10.0


def _stop_heartbeat(dask_worker: object) -> None:
    """On a worker (through ``Client.run``): stop its heartbeat to the scheduler and raise its logger's
    threshold to CRITICAL, for the teardown only."""
    callback = dask_worker.periodic_callbacks.get("heartbeat")  # type: ignore[attr-defined]
    if callback is not None:
        callback.stop()
    logging.getLogger("distributed.worker").setLevel(logging.CRITICAL)


def _quiet_teardown(client: object) -> None:
    """Silence the workers' heartbeats before the cluster is taken down, the work being done.

    Scaling to no workers first (:func:`_close_workers`) was not enough: a heartbeat that found its stream
    closed while the scheduler retired the worker still logged "Failed to communicate with scheduler during
    heartbeat" with a traceback on the user's terminal (seen in an `aerocal process` of the fuzz tests)."""
    try:
        client.run(_stop_heartbeat)  # type: ignore[attr-defined]
    except Exception:  # teardown of workers that may already be gone: closing still runs
        pass


def _close_workers(cluster: object) -> None:
    """Scale ``cluster`` to no workers and wait until they are gone, so that the scheduler closes after them.

    Closed the other way round, a worker whose heartbeat finds the scheduler gone logs "Failed to communicate
    with scheduler during heartbeat" with a traceback on the user's terminal, at the end of a successful match
    step. Retiring the workers through the client instead printed two INFO lines per worker."""
    try:
        cluster.scale(0)  # type: ignore[attr-defined]
        deadline = time.monotonic() + WORKER_CLOSE_TIMEOUT_S
        while cluster.workers and time.monotonic() < deadline:  # type: ignore[attr-defined]
            time.sleep(0.05)
    except Exception:  # teardown of a cluster that may already be gone: cluster.close() still runs
        pass


def n_workers(client: object) -> int:
    """Number of workers currently attached to ``client`` (at least 1)."""
    info = client.scheduler_info()  # type: ignore[attr-defined]
    return max(1, len(info.get("workers", {})))


_WORKER_READY = False


def single_threaded_opencv() -> None:
    """``cv2.setNumThreads(1)`` once per Dask worker process: parallelism comes from the cluster.

    Outside a worker (serial runs) nothing is changed: the caller keeps its OpenCV threads.
    """
    global _WORKER_READY
    if _WORKER_READY:
        return
    try:
        # lazy: distributed is slow to import; a serial run must not pay it
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return

    cv2.setNumThreads(1)
    _WORKER_READY = True


def run_all(
    fn: Callable,
    args: Sequence[tuple],
    client: object | None = None,
    progress: Progress | None = None,
    weights: Sequence[int] | None = None,
) -> list:
    """``[fn(*a) for a in args]``, on ``client`` when given; results in the order of ``args``.

    Arguments may hold Dask futures (they are resolved on the workers). ``progress(done, total)`` is
    called after every finished call; each call counts 1, or ``weights[i]`` (e.g. the number of pairs
    in a batch) when given.
    """
    w = [1] * len(args) if weights is None else [int(v) for v in weights]
    total = sum(w)
    results: list = [None] * len(args)
    done = 0
    if client is None:
        for i, a in enumerate(args):
            results[i] = fn(*a)
            done += w[i]
            if progress is not None:
                progress(done, total)
        return results
    # lazy: distributed is slow to import; only the Dask path needs it
    from distributed import as_completed

    futures = [client.submit(fn, *a, pure=False) for a in args]  # type: ignore[attr-defined]
    index = {f.key: i for i, f in enumerate(futures)}
    for fut in as_completed(futures):
        i = index[fut.key]
        results[i] = fut.result()
        done += w[i]
        if progress is not None:
            progress(done, total)
    return results


@dataclass(frozen=True)
class ExecutionConfig:
    """Where the steps' tile work runs (matching, the partitioned adjustment, the mosaic tiles): on the Dask
    scheduler at ``dask_address`` (e.g. ``"tcp://host:8786"``) when one is given, else on a local cluster of
    ``local_workers`` processes started for a step whose work pays for it (2, one per core of the machines the
    platform is sized for; 0: everything in the calling process).

    Not part of any step's configuration or cache key: where the work ran does not change what it computed
    (``tests/test_dask_cluster.py`` compares the poses of a cluster run with a local one to 1e-6 m), so a step
    computed on one cluster is reused on another.
    """

    dask_address: str | None = None
    local_workers: int = 2

    def __post_init__(self) -> None:
        if self.local_workers < 0:
            raise ValueError(f"ExecutionConfig.local_workers must be 0 or more, got {self.local_workers}")
        if self.dask_address is not None and not self.dask_address.strip():
            raise ValueError("ExecutionConfig.dask_address is empty; give a scheduler address or None")

    def client(self, serial: bool = False) -> contextlib.AbstractContextManager:
        """:func:`dask_client` for a step: ``serial`` when the step's work is too small for a local cluster."""
        return dask_client(self.dask_address, self.local_workers, serial)


def dask_client(address: str | None, n_workers: int, serial: bool) -> contextlib.AbstractContextManager:
    """The Dask client a step's tile work runs on, as a context manager.

    Args:
        address: the address of a running Dask scheduler (e.g. ``"tcp://host:8786"``); when given (not empty),
            ``n_workers`` and ``serial`` are ignored.
        n_workers: worker processes of the local cluster started when there is no ``address``; ``<= 0``: none,
            the work runs serially in this process.
        serial: without ``address``, run serially in this process (a step whose work is too small for a local
            cluster).

    Returns:
        A context manager whose ``with`` value is: a ``distributed.Client`` of the scheduler at ``address`` when
        one is given (connected by this call, closed on exit); else ``None`` (serial, in this process) when
        ``serial`` or ``n_workers <= 0``; else the client of a fresh :func:`local_client` of ``n_workers``
        processes, started on entering and closed on exit.

    Raises:
        OSError: (from ``distributed``) the scheduler at ``address`` cannot be reached.
    """
    if address:
        from distributed import Client  # lazy: the engine works without Dask installed

        return Client(address)
    if serial or n_workers <= 0:
        return contextlib.nullcontext(None)
    return local_client(n_workers=n_workers)
