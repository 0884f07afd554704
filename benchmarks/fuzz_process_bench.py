"""Fault corpus through `aerocal process`: >= 200 faulty copies of one simulated flight, as a user runs them.

Each case copies the base flight (``aerocal simulate conte-calibration --mode images``, 12 frames), applies
one fault of :mod:`aerocal.simulate.faults` (seeded), runs ``aerocal process`` in its own process against
one shared database and artifact store, and checks what a user must see: no traceback; exit code 0 or 2
(never 1 for bad input); for a ``stop`` fault exit 2; for a ``said`` fault the output names the file or
point; after a run that did not succeed, no stored certificate changed, no artifact file changed and the
run folder is absent or says it failed; after a run that succeeded on input with ingest errors, every
certificate it stored is rejected. ``kill`` cases send SIGKILL at a random moment, then check that the
store holds no half-made certificate, that ``aerocal runs list`` shows no dead run as running, and that a
re-run succeeds. Then the infrastructure's faults at random moments (:mod:`benchmarks.infrastructure_faults`:
a Dask worker killed, the PostgreSQL connections dropped, the artifact disk full), three of each.

Run: ``python -m benchmarks.fuzz_process_bench [N_CASES]`` (default 220). Results go to RESULTS.md.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from prefect.settings import PREFECT_API_URL
from prefect.testing.utilities import prefect_test_harness

from aerocal.ingest import ingest_folder
from aerocal.simulate.faults import FAULTS, AppliedFault, apply_fault
from benchmarks.common import record
from benchmarks.infrastructure_faults import run_cases, table

AEROCAL = str(Path(sys.executable).with_name("aerocal"))
BASE_PRESET, BASE_IMAGES = "conte-calibration", 12


@dataclass
class Outcome:
    """What one case gave and what was wrong with it (``problems`` empty = the product behaved)."""

    fault: AppliedFault
    seed: int
    exit_code: int
    seconds: float
    problems: list[str] = field(default_factory=list)
    output: str = ""

    def line(self) -> str:
        verdict = "ok" if not self.problems else "; ".join(self.problems)
        return (f"| {self.fault.kind} | {self.seed} | {self.fault.detail} | {self.exit_code} | {self.seconds:.1f} | "
                f"{verdict} |")


def aerocal(args: list[str], env: dict, cwd: Path, timeout: float = 1800) -> subprocess.CompletedProcess:
    return subprocess.run([AEROCAL, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def make_base(root: Path, seed: int, env: dict) -> Path:
    """The base flight (images mode, with eo.csv, GCP files, camera.json, flight.json)."""
    base = root / "base"
    if not base.exists():
        done = aerocal(["simulate", BASE_PRESET, "--out", str(base), "--seed", str(seed), "--mode", "images",
                        "--max-images", str(BASE_IMAGES)], env, root)
        if done.returncode:
            raise RuntimeError(f"simulate failed: {done.stdout}\n{done.stderr}")
    return base


def store_snapshot(db: Path, artifacts: Path) -> tuple[list[tuple], dict[str, int]]:
    """(certificate rows: id, version, status, camera; artifact files and their sizes)."""
    rows: list[tuple] = []
    if db.exists():
        with sqlite3.connect(db) as con:
            try:
                rows = sorted(con.execute("SELECT id, version, status, camera_id FROM certificates").fetchall())
            except sqlite3.OperationalError:
                rows = []
    files = {str(p.relative_to(artifacts)): p.stat().st_size for p in artifacts.rglob("*") if p.is_file()} \
        if artifacts.exists() else {}
    return rows, files


def ingest_errors(folder: Path) -> int:
    try:
        return len(ingest_folder(folder).errors)
    except Exception:  # a fault may make ingest itself refuse the folder: count it as an error
        return 1


def judge(fault: AppliedFault, code: int, output: str, before, after, run_dir: Path, errors: int) -> list[str]:
    """What was wrong with the product's answer to one fault (empty list: nothing)."""
    problems = []
    if "Traceback" in output:
        problems.append("traceback printed")
    if code not in (0, 2):
        problems.append(f"exit code {code} for bad input")
    if fault.expect == "stop" and code != 2:
        problems.append(f"not stopped (exit {code})")
    flat = " ".join(output.split())
    if fault.expect in ("stop", "said") and not any(name in flat for name in fault.names):
        problems.append(f"output does not name {' or '.join(fault.names)}")
    if code != 0:
        if before[0] != after[0]:
            problems.append("certificates changed by a run that did not succeed")
        changed = [k for k, size in before[1].items() if after[1].get(k) != size]
        if changed:
            problems.append(f"{len(changed)} artifact file(s) changed or removed")
        if run_dir.exists():
            left = sorted(p.name for p in run_dir.iterdir())
            status = json.loads((run_dir / "run.json").read_text()).get("status") if "run.json" in left else None
            if status in (None, "succeeded"):
                problems.append(f"run folder left without a failed run.json: {left}")
    elif errors:
        new = [r for r in after[0] if r not in before[0]]
        accepted = [r for r in new if r[2] != "rejected"]
        if accepted:
            problems.append(f"input had {errors} ingest error(s) and {len(accepted)} certificate(s) were accepted")
    return problems


def run_case(base: Path, kind: str, seed: int, work: Path, db: Path, artifacts: Path, env: dict) -> Outcome:
    case = work / f"{kind}-{seed}"
    shutil.rmtree(case, ignore_errors=True)
    shutil.copytree(base, case / "flight", ignore=shutil.ignore_patterns("truth*", "reference"))
    fault = apply_fault(kind, case / "flight", seed)
    errors = ingest_errors(case / "flight")
    before = store_snapshot(db, artifacts)
    t0 = time.perf_counter()
    done = aerocal(["process", "flight", "--out", "run", "--database-url", f"sqlite:///{db}", "--artifacts",
                    str(artifacts)], env, case)
    seconds = time.perf_counter() - t0
    output = done.stdout + done.stderr
    after = store_snapshot(db, artifacts)
    problems = judge(fault, done.returncode, output, before, after, case / "run", errors)
    return Outcome(fault, seed, done.returncode, seconds, problems, output)


def run_kill(base: Path, seed: int, work: Path, env: dict) -> Outcome:
    """SIGKILL `aerocal process` after a random delay, on a store of its own (so no step is cached and the
    kill lands mid-run); the store must stay whole, the dead run not be listed as running, a re-run succeed."""
    rng = np.random.default_rng(seed)
    delay = float(rng.uniform(1.0, 25.0))
    case = work / f"kill-{seed}"
    shutil.rmtree(case, ignore_errors=True)
    db, artifacts = case / "aerocal.db", case / "artifacts"
    shutil.copytree(base, case / "flight", ignore=shutil.ignore_patterns("truth*", "reference"))
    fault = AppliedFault("kill", "-", "quiet", (), f"SIGKILL after {delay:.1f} s")
    args = [AEROCAL, "process", "flight", "--out", "run", "--database-url", f"sqlite:///{db}", "--artifacts",
            str(artifacts)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, env=env, cwd=case, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        proc.wait(timeout=delay)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    problems = []

    if db.exists():
        with sqlite3.connect(db) as con:
            try:
                bad = con.execute("SELECT count(*) FROM certificates WHERE document IS NULL").fetchone()[0]
            except sqlite3.OperationalError:
                bad = 0
        if bad:
            problems.append(f"{bad} certificate(s) without a document")
    listed = aerocal(["runs", "list", "--database-url", f"sqlite:///{db}"], env, case)
    if not db.exists():
        pass  # killed before the database was made: nothing to list, and `runs list` says so
    elif listed.returncode:
        problems.append(f"runs list exited {listed.returncode}: {listed.stderr[-300:]}")
    elif " running" in listed.stdout.replace("\n", " ") and proc.returncode and proc.returncode < 0:
        problems.append("the killed run is listed as running")
    again = aerocal(["process", "flight", "--out", "run2", "--database-url", f"sqlite:///{db}", "--artifacts",
                     str(artifacts)], env, case)
    if again.returncode:
        problems.append(f"re-run after the kill exited {again.returncode}: {again.stderr[-300:]}")
    return Outcome(fault, seed, proc.returncode or 0, time.perf_counter() - t0, problems,
                   again.stdout + again.stderr)


def corpus(n: int, seed: int) -> list[tuple[str, int]]:
    """``n`` (kind, seed) cases: every kind in turn, then kills (one in 20)."""
    kinds = list(FAULTS)
    out = []
    for k in range(n):
        out.append(("kill", seed + k) if k % 20 == 19 else (kinds[k % len(kinds)], seed + k))
    return out


def main(n_cases: int | None = None) -> None:
    if n_cases is None:
        n_cases = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 220
    root = Path(os.environ.get("AEROCAL_FUZZ_DIR", "/tmp/aerocal-fuzz-process"))
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    with prefect_test_harness(server_startup_timeout=180):
        env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "COLUMNS": "250"}
        base = make_base(root, 7, env)
        db, artifacts, work = root / "aerocal.db", root / "artifacts", root / "cases"
        clean = aerocal(["process", str(base), "--out", str(root / "clean"), "--database-url", f"sqlite:///{db}",
                         "--artifacts", str(artifacts)], env, root)
        if clean.returncode:
            raise RuntimeError(f"the base flight does not process: {clean.stdout}\n{clean.stderr}")
        outcomes = []
        t0 = time.perf_counter()
        for i, (kind, seed) in enumerate(corpus(n_cases, 1000)):
            out = run_kill(base, seed, work, env) if kind == "kill" else \
                run_case(base, kind, seed, work, db, artifacts, env)
            outcomes.append(out)
            print(f"[{i + 1}/{n_cases}] {out.line()}", flush=True)
            shutil.rmtree(work / f"{kind}-{seed}", ignore_errors=True)
        infrastructure = run_cases(base, 3, env, progress=lambda line: print(line, flush=True))
        total = time.perf_counter() - t0
    bad = [o for o in outcomes if o.problems]
    codes = Counter((o.fault.kind, o.exit_code) for o in outcomes)
    lines = [f"{len(outcomes)} cases ({len(FAULTS)} fault kinds and SIGKILL), base flight {BASE_PRESET} "
             f"{BASE_IMAGES} frames (images mode), {total / 60:.1f} min; **{len(bad)} case(s) with a problem**", "",
             "| kind | exit codes |", "|---|---|"]
    for kind in [*FAULTS, "kill"]:
        per = {code: c for (k, code), c in codes.items() if k == kind}
        lines.append(f"| {kind} | {', '.join(f'{c}x exit {code}' for code, c in sorted(per.items()))} |")
    if bad:
        lines += ["", "Cases with a problem:", "", "| kind | seed | fault | exit | s | problem |",
                  "|---|---|---|---|---|---|", *[o.line() for o in bad]]
    lines += ["", *table(infrastructure)]
    record("Fault corpus through `aerocal process`", lines)


if __name__ == "__main__":
    main()
