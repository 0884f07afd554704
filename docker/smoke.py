"""The compose stack brought up for real: ``python docker/smoke.py`` (or ``make docker-smoke``) on a machine with a
Docker daemon.

``docker compose up`` on ``docker/compose.yaml``, then ``aerocal simulate`` and ``aerocal process --dask`` inside
the stack: the run must complete on the stack's Dask workers and be stored in its PostgreSQL as ``completed``. The
stack is taken down with its volumes whatever happens. Exit status 0 when it holds, 1 when a step fails (its
output's tail printed), 2 when no Docker daemon answers.

Not part of ``make test``: the developers' and CI machines have no Docker daemon, and a skipped test would prove
nothing there; ``tests/test_docker.py`` checks the compose file statically on every run.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import uuid
from pathlib import Path

COMPOSE = Path(__file__).resolve().parent / "compose.yaml"


def docker_daemon() -> str | None:
    """Why no Docker daemon can be used here, or ``None`` when one answers."""
    if shutil.which("docker") is None:
        return "no docker client on PATH"
    try:
        info = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"], capture_output=True,
                              text=True, timeout=30)
    except subprocess.TimeoutExpired:
        return "`docker info` did not answer within 30 s"
    if info.returncode != 0 or not info.stdout.strip():
        lines = (info.stderr or info.stdout).strip().splitlines()
        return lines[-1] if lines else f"`docker info` exited {info.returncode}"
    return None


class StepFailed(RuntimeError):
    """A compose step exited non-zero or answered other than expected; the message holds its output's tail."""


def smoke() -> None:
    """Bring the stack up, process a 10-frame simulated flight through its scheduler, check its database.

    Raises:
        StepFailed: a step failed (the message names it and ends with its output).
    """
    project = f"aerocal-smoke-{uuid.uuid4().hex[:8]}"
    compose_cmd = ["docker", "compose", "-f", str(COMPOSE), "-p", project]

    def step(name: str, *args: str, timeout: float = 1800) -> subprocess.CompletedProcess:
        print(f"{name} ...", flush=True)
        done = subprocess.run([*compose_cmd, *args], capture_output=True, text=True, timeout=timeout)
        if done.returncode != 0:
            raise StepFailed(f"{name}: exited {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
        return done

    try:
        step("up", "up", "--build", "--detach", "--wait", "postgres", "prefect-server", "dask-scheduler",
             "dask-worker")
        step("init", "run", "--rm", "aerocal-init")
        step("simulate", "run", "--rm", "--no-deps", "aerocal-init", "simulate", "conte-calibration", "--out",
             "/data/flights/compose", "--seed", "5", "--max-images", "10")
        step("process", "run", "--rm", "--no-deps", "aerocal-init", "process", "/data/flights/compose", "--dask",
             "tcp://dask-scheduler:8786", "--out", "/data/runs/compose")
        runs = step("runs", "exec", "-T", "postgres", "psql", "-U", "aerocal", "-d", "aerocal", "-tAc",
                    "select status from runs where kind = 'process_flight'")
        if runs.stdout.split() != ["completed"]:
            raise StepFailed(f"runs: expected one completed process_flight run, got {runs.stdout!r} {runs.stderr}")
    finally:
        subprocess.run([*compose_cmd, "down", "--volumes", "--remove-orphans"], capture_output=True, timeout=300)


def main() -> int:
    reason = docker_daemon()
    if reason is not None:
        print(f"no Docker daemon: {reason}", file=sys.stderr)
        return 2
    try:
        smoke()
    except StepFailed as exc:
        print(f"compose stack smoke test failed at {exc}", file=sys.stderr)
        return 1
    print("compose stack: the flight was processed on its Dask workers and stored in its PostgreSQL")
    return 0


if __name__ == "__main__":
    sys.exit(main())
