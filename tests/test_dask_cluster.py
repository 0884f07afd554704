"""A Dask cluster of separate processes, as a user runs one beside `aerocal process --dask ADDRESS`: a
``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1, each in its own working folder with one
thread. What a flight gives on it is what it gives on the local cluster the product starts itself.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

AEROCAL = str(Path(sys.executable).with_name("aerocal"))


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """``(address, worker processes)`` of a scheduler and two single-threaded workers, each its own process."""
    from benchmarks.process_cluster import process_cluster

    with process_cluster(tmp_path_factory.mktemp("dask"), n_workers=2) as running:
        yield running.address, running.workers


@pytest.fixture(scope="module")
def prefect_api():
    from prefect.settings import PREFECT_API_URL
    from prefect_harness import prefect_harness

    with prefect_harness():
        yield PREFECT_API_URL.value()


#: the rendered flight of the image-mode tests (conte-calibration frames)
SEED, N_FRAMES = 41, 10


@pytest.fixture(scope="module")
def on_cluster(cluster, prefect_api, tmp_path_factory):
    """``(flight folder, work folder, run summary)``: the rendered flight processed on the whole cluster."""
    from aerocal.simulate import simulate_flight, write_flight

    work = tmp_path_factory.mktemp("on-cluster")
    folder = write_flight(simulate_flight("conte-calibration", seed=SEED, max_images=N_FRAMES), work / "flight",
                          mode="images")
    return folder, work, _process(folder, work / "remote", prefect_api, cluster[0])


def _process(folder: Path, out: Path, api: str, dask: str | None) -> dict:
    args = [AEROCAL, "process", str(folder), "--certificate", "none", "--out", str(out), "--database-url",
            f"sqlite:///{out.parent / (out.name + '.db')}", "--artifacts", str(out.parent / (out.name + '-art'))]
    done = subprocess.run(args + (["--dask", dask] if dask else []), capture_output=True, text=True, timeout=900,
                          env={**os.environ, "PREFECT_API_URL": api, "COLUMNS": "200"})
    assert done.returncode == 0, f"aerocal process exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
    return json.loads((out / "run.json").read_text())


def test_an_image_flight_on_a_cluster_of_separate_processes_gives_the_local_clusters_answer(cluster, on_cluster,
                                                                                          prefect_api):
    """`aerocal process --dask tcp://...` on rendered frames: matching (SIFT and pairs on the workers, the frames
    read by path from the flight folder), orientation, calibration, block and mosaic tiles on both workers; the
    same tie points and poses (1e-6 m) and the same orthomosaic as the product's own run without one (a block
    this small is matched in the process itself)."""
    import rasterio
    from distributed import Client

    address, _ = cluster
    with Client(address, timeout=30) as client:  # the workers did the cluster run's work, both of them
        executed = client.run(lambda dask_worker: dask_worker.state.executed_count)
    assert len(executed) == 2 and all(n > 0 for n in executed.values()), executed
    folder, work, remote = on_cluster
    local = _process(folder, work / "local", prefect_api, None)
    assert remote["steps"]["match"]["extra"] == local["steps"]["match"]["extra"], f"seed {SEED}"
    a, b = (pq.read_table(work / name / "poses.parquet") for name in ("local", "remote"))
    assert a.column("image_id").to_pylist() == b.column("image_id").to_pylist()
    for col in ("X", "Y", "Z"):
        np.testing.assert_allclose(b.column(col).to_numpy(), a.column(col).to_numpy(), rtol=0, atol=1e-6,
                                   err_msg=f"seed {SEED}: {col}")
    with rasterio.open(work / "local" / "orthomosaic.tif") as x, \
            rasterio.open(work / "remote" / "orthomosaic.tif") as y:
        assert x.transform == y.transform and x.crs == y.crs
        np.testing.assert_array_equal(x.read(1), y.read(1))


def test_the_partitioned_adjustment_runs_on_the_separate_workers_with_the_single_adjustments_poses(cluster,
                                                                                                 tmp_path):
    """A block cut into sub-blocks (forced below its size) adjusted on the separate-process workers: its poses
    are the single adjustment's within 1e-6 m, and the adjustment says how it was cut."""
    from aerocal.matching.cluster import ExecutionConfig
    from aerocal.pipeline import LocalRunner, MemoryCertificates, process
    from aerocal.pipeline.config import BlockStepConfig, ProcessConfig
    from aerocal.simulate import simulate_flight, write_flight

    address, _ = cluster
    seed = 7
    folder = write_flight(simulate_flight("conte-city", seed=seed, max_images=40), tmp_path / "city",
                          mode="observations")
    runner, store = LocalRunner(), MemoryCertificates()
    single = process(folder, certificate="none", runner=runner, certificates=store)
    cut = ProcessConfig(block=BlockStepConfig(partition_min_images=30, partition_max_images=15))
    parted = process(folder, cut, certificate="auto", runner=runner, certificates=store,
                     execution=ExecutionConfig(address))
    info = parted.json("adjustment")["partitioned"]
    assert info is not None and info["sub_blocks"] == 3, info
    a, b = single.table("poses"), parted.table("poses")
    for col in ("X", "Y", "Z"):
        np.testing.assert_allclose(b.column(col).to_numpy(), a.column(col).to_numpy(), rtol=0, atol=1e-6,
                                   err_msg=f"seed {seed}: {col}")


def test_a_worker_killed_during_the_partitioned_adjustment_leaves_the_solve_to_the_other(tmp_path, monkeypatch):
    """One of two workers (nanny and process, SIGKILL) killed once its sub-blocks are built, before the first
    iteration: the partitioned solve starts again on the worker left and gives the single adjustment's poses,
    and the adjustment says it was restarted and why. A cluster of its own (the kill leaves it one worker
    short)."""
    import aerocal.adjust.partition as partition
    from aerocal.matching.cluster import ExecutionConfig
    from aerocal.pipeline import LocalRunner, MemoryCertificates, process
    from aerocal.pipeline.config import BlockStepConfig, ProcessConfig
    from aerocal.simulate import simulate_flight, write_flight
    from benchmarks.process_cluster import process_cluster

    seed = 8
    folder = write_flight(simulate_flight("conte-city", seed=seed, max_images=40), tmp_path / "city",
                          mode="observations")
    runner, store = LocalRunner(), MemoryCertificates()
    single = process(folder, certificate="none", runner=runner, certificates=store)
    (tmp_path / "dask").mkdir()
    with process_cluster(tmp_path / "dask", n_workers=2) as running:
        iterate, killed = partition.levenberg_marquardt, []

        def kill_then_iterate(*args, **kwargs):
            if not killed:  # the sub-blocks are on the workers now: one of them goes, with its actors
                os.killpg(running.workers[0].pid, signal.SIGKILL)
                killed.append(running.workers[0].pid)
            return iterate(*args, **kwargs)

        monkeypatch.setattr(partition, "levenberg_marquardt", kill_then_iterate)
        cut = ProcessConfig(block=BlockStepConfig(partition_min_images=30, partition_max_images=15))
        parted = process(folder, cut, certificate="auto", runner=runner, certificates=store,
                         execution=ExecutionConfig(running.address))
    info = parted.json("adjustment")["partitioned"]
    assert killed and info["sub_blocks"] == 3, info
    assert info["restarted"] and "worker was lost" in info["restarted"] and "1 worker" in info["restarted"], info
    a, b = single.table("poses"), parted.table("poses")
    for col in ("X", "Y", "Z"):
        np.testing.assert_allclose(b.column(col).to_numpy(), a.column(col).to_numpy(), rtol=0, atol=1e-6,
                                   err_msg=f"seed {seed}: {col}")


def test_a_worker_killed_during_matching_leaves_the_run_to_the_other_worker(cluster, on_cluster, prefect_api,
                                                                           tmp_path):
    """One of the two workers (its nanny and its process) killed while the flight's frames are being matched: the
    run completes on the other worker, with the tie points and poses of the run on the whole cluster. (Last in
    this file: it leaves the cluster one worker short.)"""
    from distributed import Client

    address, workers = cluster
    folder, work, whole = on_cluster
    out = tmp_path / "killed"
    args = [AEROCAL, "process", str(folder), "--certificate", "none", "--out", str(out), "--database-url",
            f"sqlite:///{tmp_path / 'killed.db'}", "--artifacts", str(tmp_path / "killed-art"), "--dask", address]
    run = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env={**os.environ, "PREFECT_API_URL": prefect_api, "COLUMNS": "200",
                                "PYTHONUNBUFFERED": "1"})
    lines = []
    for line in run.stdout:  # killed once the matching has started on the cluster
        lines.append(line)
        if line.rstrip().endswith("flight: match"):
            os.killpg(workers[0].pid, signal.SIGKILL)
            break
    lines += run.stdout.readlines()
    assert run.wait(timeout=900) == 0, "".join(lines)
    with Client(address, timeout=30) as client:
        assert len(client.scheduler_info()["workers"]) == 1, "".join(lines)  # the run finished on the one left
    summary = json.loads((out / "run.json").read_text())
    assert summary["steps"]["match"]["extra"] == whole["steps"]["match"]["extra"], f"seed {SEED}"
    a, b = (pq.read_table(path / "poses.parquet") for path in (work / "remote", out))
    for col in ("X", "Y", "Z"):
        np.testing.assert_allclose(b.column(col).to_numpy(), a.column(col).to_numpy(), rtol=0, atol=1e-6,
                                   err_msg=f"seed {SEED}: {col}")
