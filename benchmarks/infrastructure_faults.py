"""Faults of the infrastructure under `aerocal process`, at random moments: the fault corpus's second half.

Three kinds, each on the base flight of :mod:`benchmarks.fuzz_process_bench` with a store of its own (so no step
is cached and the fault lands mid-run), the moment drawn from the case's seed:

* ``worker-kill`` -- the run on a cluster of separate processes (a ``dask scheduler``, two ``dask worker``
  processes); one worker and its nanny killed (SIGKILL) after the drawn delay;
* ``database-drop`` -- the run on a PostgreSQL store of its own; every connection `aerocal` holds terminated
  (``pg_terminate_backend``) at the drawn moment and again 5 s later;
* ``disk-full`` -- the artifact store on a tmpfs of the drawn size (0.3-4 MB; mounting needs root).

A case is judged as a user would: no traceback; exit 0, or exit 1 with one ``error:`` line (a disk-full line
names ``--artifacts``); then the store: no run left ``running``, every certificate with its document, every
registered artifact's file whole (its size and SHA-256, read with SQL and hashlib, not by the store's code);
and the same command with the fault gone (the remaining worker, the server answering, a disk with room: the
same files copied) completes.

Run alone: ``python -m benchmarks.infrastructure_faults [N_PER_KIND]`` (default 3); ``fuzz_process_bench``
runs it after the input faults.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np

AEROCAL = str(Path(sys.executable).with_name("aerocal"))
KINDS = ("worker-kill", "database-drop", "disk-full")
#: an administrative URL of the PostgreSQL server the database-drop cases create their databases on
ADMIN_URL = os.environ.get("AEROCAL_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")


@dataclass
class InfraOutcome:
    """One case: the fault, the exit code of the faulted run, and what was wrong (empty: nothing)."""

    kind: str
    seed: int
    detail: str
    exit_code: int
    seconds: float
    problems: list[str] = field(default_factory=list)

    def line(self) -> str:
        verdict = "ok" if not self.problems else "; ".join(self.problems)
        return f"| {self.kind} | {self.seed} | {self.detail} | {self.exit_code} | {self.seconds:.1f} | {verdict} |"


def _process(flight: Path, out: Path, url: str, artifacts: Path, env: dict, dask: str | None = None,
             ) -> subprocess.Popen:
    args = [AEROCAL, "process", str(flight), "--out", str(out), "--database-url", url, "--artifacts",
            str(artifacts)] + (["--dask", dask] if dask else [])
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _said(proc: subprocess.Popen, timeout: float = 1800) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def _whole(uri: str, sha256: str, size: int, root: Path) -> bool:
    """Whether the artifact file of ``uri`` (or its copy under the store's ``root``, where the store looks when
    the recorded path is gone) holds exactly this content."""
    path = Path(unquote(urlsplit(uri).path))
    if not path.exists():
        path = root / sha256[:2] / path.name
    if not path.is_file() or path.stat().st_size != size:
        return False
    return hashlib.sha256(path.read_bytes()).hexdigest() == sha256


def judge_run(code: int, out: str, err: str, url: str, artifacts: Path, must_name: str | None = None) -> list[str]:
    """What was wrong with a faulted run's answer and with the store it leaves (read with SQL, as the store's own
    code is not the judge of itself)."""
    import sqlalchemy as sa

    problems = []
    if "Traceback" in out + err:
        problems.append("traceback printed")
    if code not in (0, 1):
        problems.append(f"exit code {code}")
    if code == 1:
        said = [line for line in err.splitlines() if line.strip()]
        if not said or not said[-1].startswith("error:"):
            problems.append(f"no one-line error (last line: {said[-1][:120] if said else 'none'!r})")
        elif must_name and must_name not in said[-1]:
            problems.append(f"the error does not name {must_name}: {said[-1][:160]}")
    engine = sa.create_engine(url.replace("postgresql://", "postgresql+psycopg://", 1))
    try:
        with engine.connect() as conn:
            running = conn.exec_driver_sql("SELECT count(*) FROM runs WHERE status = 'running'").scalar()
            if running:
                problems.append(f"{running} run(s) left running")
            if conn.exec_driver_sql("SELECT count(*) FROM certificates WHERE document IS NULL").scalar():
                problems.append("a certificate without its document")
            for uri, sha, size in conn.exec_driver_sql("SELECT uri, sha256, size_bytes FROM artifacts"):
                if not _whole(uri, sha, size, artifacts):
                    problems.append(f"artifact {uri} registered without its whole file")
                    break
    finally:
        engine.dispose()
    return problems


def worker_kill(base: Path, seed: int, work: Path, env: dict) -> InfraOutcome:
    from benchmarks.process_cluster import process_cluster

    delay = float(np.random.default_rng(seed).uniform(1.0, 20.0))
    url, artifacts = f"sqlite:///{work / 'aerocal.db'}", work / "artifacts"
    (work / "cluster").mkdir()
    t0 = time.perf_counter()
    with process_cluster(work / "cluster", n_workers=2) as cluster:
        proc = _process(base, work / "run", url, artifacts, env, cluster.address)
        try:
            proc.wait(timeout=delay)
            killed = "run ended first"
        except subprocess.TimeoutExpired:
            os.killpg(cluster.workers[0].pid, 9)
            killed = f"worker killed after {delay:.1f} s"
        code, out, err = _said(proc)
        seconds = time.perf_counter() - t0
        problems = judge_run(code, out, err, url, artifacts)
        again = _said(_process(base, work / "run2", url, artifacts, env, cluster.address))
    if again[0] != 0:
        problems.append(f"re-run on the remaining worker exited {again[0]}: {again[2][-300:]}")
    return InfraOutcome("worker-kill", seed, killed, code, seconds, problems)


def _terminate(url: str) -> int:
    import sqlalchemy as sa

    name = sa.engine.make_url(url).database
    admin = sa.create_engine(ADMIN_URL, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            rows = conn.execute(sa.text("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = :d "
                                        "AND application_name = 'aerocal'"), {"d": name}).all()
    finally:
        admin.dispose()
    return sum(bool(r[0]) for r in rows)


def database_drop(base: Path, seed: int, work: Path, env: dict) -> InfraOutcome:
    import sqlalchemy as sa

    delay = float(np.random.default_rng(seed).uniform(0.5, 15.0))
    name = f"aerocal_faults_{os.getpid()}_{seed}"
    admin = sa.create_engine(ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.exec_driver_sql(f'CREATE DATABASE "{name}"')
    url = sa.engine.make_url(ADMIN_URL).set(database=name).render_as_string(hide_password=False)
    artifacts = work / "artifacts"
    try:
        t0 = time.perf_counter()
        proc = _process(base, work / "run", url, artifacts, env)
        dropped: list[int] = []

        def drop() -> None:
            for wait in (delay, 5.0):
                time.sleep(wait)
                if proc.poll() is not None:
                    return
                dropped.append(_terminate(url))

        dropper = threading.Thread(target=drop, daemon=True)
        dropper.start()
        code, out, err = _said(proc)
        dropper.join()
        seconds = time.perf_counter() - t0
        problems = judge_run(code, out, err, url, artifacts)
        again = _said(_process(base, work / "run2", url, artifacts, env))
        if again[0] != 0:
            problems.append(f"re-run exited {again[0]}: {again[2][-300:]}")
        detail = f"connections dropped at {delay:.1f} s and 5 s later: {dropped or 'run ended first'}"
        return InfraOutcome("database-drop", seed, detail, code, seconds, problems)
    finally:
        with admin.connect() as conn:
            conn.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.dispose()


def disk_full(base: Path, seed: int, work: Path, env: dict) -> InfraOutcome:
    size_kb = int(np.random.default_rng(seed).uniform(300, 4096))
    mount = work / "small"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if done.returncode:
        return InfraOutcome("disk-full", seed, f"{size_kb} kB", -1, 0.0,
                            [f"cannot mount a tmpfs here ({done.stderr.strip()}); run as root"])
    url = f"sqlite:///{work / 'aerocal.db'}"
    try:
        t0 = time.perf_counter()
        code, out, err = _said(_process(base, work / "run", url, mount, env))
        seconds = time.perf_counter() - t0
        problems = judge_run(code, out, err, url, mount, must_name="--artifacts")
        roomy = work / "roomy"
        subprocess.run(["cp", "-a", f"{mount}/.", str(roomy)], check=True)
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)
    again = _said(_process(base, work / "run", url, roomy, env))
    if again[0] != 0:
        problems.append(f"re-run with room exited {again[0]}: {again[2][-300:]}")
    return InfraOutcome("disk-full", seed, f"{size_kb} kB artifact disk", code, seconds, problems)


CASES = {"worker-kill": worker_kill, "database-drop": database_drop, "disk-full": disk_full}


def run_cases(base: Path, n_per_kind: int, env: dict, seed: int = 5000, progress=print) -> list[InfraOutcome]:
    """``n_per_kind`` cases of each kind on the flight folder ``base``, in turn."""
    outcomes = []
    for k in range(n_per_kind):
        for kind in KINDS:
            with tempfile.TemporaryDirectory(prefix=f"aerocal-{kind}-") as work:
                out = CASES[kind](base, seed + k, Path(work), env)
            outcomes.append(out)
            progress(f"[{len(outcomes)}/{n_per_kind * len(KINDS)}] {out.line()}")
    return outcomes


def table(outcomes: list[InfraOutcome]) -> list[str]:
    bad = sum(bool(o.problems) for o in outcomes)
    return [f"{len(outcomes)} infrastructure cases ({', '.join(KINDS)}); **{bad} case(s) with a problem**", "",
            "| kind | seed | fault | exit | s | verdict |", "|---|---|---|---|---|---|", *[o.line() for o in outcomes]]


def main() -> None:
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    from benchmarks.common import record
    from benchmarks.fuzz_process_bench import make_base

    n = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 3
    root = Path(os.environ.get("AEROCAL_FUZZ_DIR", "/tmp/aerocal-fuzz-process"))
    root.mkdir(parents=True, exist_ok=True)
    with prefect_test_harness(server_startup_timeout=180):
        env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "COLUMNS": "250"}
        base = make_base(root, 7, env)
        outcomes = run_cases(base, n, env, progress=lambda line: print(line, flush=True))
    shutil.rmtree(root / "infrastructure", ignore_errors=True)
    record("Infrastructure faults through `aerocal process`", table(outcomes))


if __name__ == "__main__":
    main()
