"""Peak memory of `aerocal process` on every simulator preset at its full size (target: under 4 GB).

Each preset is simulated through the CLI (observations mode, every image of the preset; seneca reads its
stations from ../shared/data/seneca) and processed by ``aerocal process`` in its own process with a local
Dask cluster; the resident memory of the whole process tree (the command, its Dask workers) is sampled
every 0.2 s with psutil and its peak reported with the time. ``mitishita-block`` (72 UltraCam frames) was
killed by the OOM killer at 23 GB before the DSM grid followed the tie-point density.

Run: ``python -m benchmarks.presets_memory_bench [PRESET ...]``. Results go to RESULTS.md.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
from prefect.settings import PREFECT_API_URL
from prefect.testing.utilities import prefect_test_harness

from aerocal.simulate.presets import preset_names
from benchmarks.common import record

AEROCAL = str(Path(sys.executable).with_name("aerocal"))
TARGET_GB = 4.0
SEED = 21


def tree_rss(pid: int) -> int:
    """Resident bytes of a process and all its descendants (0 once it is gone)."""
    try:
        proc = psutil.Process(pid)
        procs = [proc, *proc.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.NoSuchProcess:
            pass
    return total


def run_sampled(args: list[str], env: dict, cwd: Path) -> tuple[int, float, float, str]:
    """(exit code, seconds, peak tree RSS in GB, output tail) of one command."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, env=env, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    peak = [0]

    def sample() -> None:
        while proc.poll() is None:
            peak[0] = max(peak[0], tree_rss(proc.pid))
            time.sleep(0.2)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    out, _ = proc.communicate()
    thread.join()
    return proc.returncode, time.perf_counter() - t0, peak[0] / 1e9, out[-600:]


def main(presets: list[str] | None = None) -> None:
    presets = presets or [a for a in sys.argv[1:] if not a.startswith("-")] or preset_names()
    root = Path(os.environ.get("AEROCAL_BENCH_DIR", "/tmp/aerocal-presets-memory"))
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    seneca = Path(__file__).resolve().parents[2] / "shared" / "data" / "seneca" / "images"
    rows = ["| preset | images | exit | seconds | peak memory (GB, process tree) | under 4 GB |",
            "|---|---|---|---|---|---|"]
    with prefect_test_harness(server_startup_timeout=180):
        env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "COLUMNS": "250"}
        for name in presets:
            flight = root / name
            args = [AEROCAL, "simulate", name, "--out", str(flight), "--seed", str(SEED)]
            if name == "seneca":
                if not seneca.is_dir():
                    rows.append(f"| {name} | - | - | - | not run: {seneca} missing | - |")
                    continue
                args += ["--source", str(seneca)]
            sim = subprocess.run(args, env=env, cwd=root, capture_output=True, text=True)
            if sim.returncode:
                rows.append(f"| {name} | - | simulate {sim.returncode} | - | - | - |")
                continue
            n = json.loads((flight / "flight.json").read_text()).get("n_images")
            code, seconds, peak, tail = run_sampled(
                [AEROCAL, "process", str(flight), "--out", str(root / f"{name}-run"), "--database-url",
                 f"sqlite:///{root / 'aerocal.db'}", "--artifacts", str(root / "artifacts")], env, root)
            rows.append(f"| {name} | {n} | {code} | {seconds:.0f} | {peak:.2f} | "
                        f"{'yes' if peak < TARGET_GB else '**no**'} |")
            print(rows[-1], flush=True)
            if code:
                print(tail, flush=True)
    record("`aerocal process` on every preset: peak memory", rows)


if __name__ == "__main__":
    main()
