"""The Docker set-up is consistent: the compose file parses and every name it uses resolves.

The static checks are what `docker compose config` and a first `up` would trip over: unknown services in
depends_on, undeclared volumes, missing build context or bind-mounted files, clashing host ports, URLs that
point at the wrong service, port or credentials. Bringing the stack up for real needs a Docker daemon, which the
machines that run this suite lack: that check is ``docker/smoke.py`` (``make docker-smoke``), run on demand, not a
test that would skip here and prove nothing.
"""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import urlsplit

import pytest
import yaml

DOCKER = Path(__file__).resolve().parents[1] / "docker"
COMPOSE = DOCKER / "compose.yaml"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _env(service: dict) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {k: str(v) for k, v in env.items()}


def _command_option(service: dict, key: str, option: str) -> str | None:
    cmd = service.get(key) or []
    return cmd[cmd.index(option) + 1] if option in cmd else None


def test_compose_services_and_references_resolve(compose):
    services = compose["services"]
    assert {"postgres", "prefect-server", "dask-scheduler", "dask-worker", "aerocal-worker"} <= set(services)
    declared_volumes = set(compose.get("volumes") or {})
    host_ports = []
    for name, svc in services.items():
        assert "image" in svc or "build" in svc, f"service {name} has neither image nor build"
        deps = svc.get("depends_on") or []
        for dep in deps if isinstance(deps, list) else deps.keys():
            assert dep in services, f"service {name} depends on unknown service {dep}"
        for vol in svc.get("volumes", []):
            source = vol.split(":")[0]
            if source.startswith((".", "/")):
                assert (COMPOSE.parent / source).exists(), f"{name}: bind-mounted {source} does not exist"
            else:
                assert source in declared_volumes, f"{name}: volume {source} is not declared under volumes"
        for port in svc.get("ports", []):
            host_ports.append(str(port).split(":")[0])
    assert len(host_ports) == len(set(host_ports)), f"host ports clash: {host_ports}"
    used = {v.split(":")[0] for s in services.values() for v in s.get("volumes", [])}
    assert declared_volumes <= used, f"declared but unused volumes: {declared_volumes - used}"


def test_aerocal_image_is_built_from_this_repository(compose):
    built = [s for s in compose["services"].values() if "build" in s]
    assert built, "no service builds the aerocal image"
    for svc in built:
        context = (COMPOSE.parent / svc["build"]["context"]).resolve()
        dockerfile = context / svc["build"]["dockerfile"]
        assert (context / "pyproject.toml").is_file(), f"build context {context} is not the repository root"
        assert dockerfile.is_file(), f"{dockerfile} does not exist"
        image = svc["image"]
    users = {s["image"] for s in compose["services"].values() if "aerocal" in s.get("image", "")}
    assert users == {image}, f"aerocal services use several image names: {users}"

    text = (DOCKER / "Dockerfile").read_text()
    stages = re.findall(r"^FROM\s+\S+\s+AS\s+(\S+)", text, flags=re.M | re.I)
    assert len(stages) >= 2, f"Dockerfile is not multi-stage: stages {stages}"
    for src in re.findall(r"^COPY\s+(?!--from)(.+?)\s+\S+$", text, flags=re.M):
        for item in src.split():
            assert (context / item).exists(), f"Dockerfile copies {item}, missing from the build context"
    user = re.findall(r"^USER\s+(\S+)", text, flags=re.M)
    assert user and user[-1] not in ("root", "0"), f"the runtime stage runs as {user or 'root'}"


def test_urls_point_at_the_right_services(compose):
    services = compose["services"]
    pg = _env(services["postgres"])
    prefect_port = _command_option(services["prefect-server"], "command", "--port")
    databases = {pg["POSTGRES_DB"]} | set(
        re.findall(r"CREATE DATABASE (\w+)", (DOCKER / "postgres-init.sql").read_text())
    )

    prefect_db = urlsplit(_env(services["prefect-server"])["PREFECT_API_DATABASE_CONNECTION_URL"])
    assert prefect_db.scheme == "postgresql+asyncpg"
    assert prefect_db.hostname == "postgres" and (prefect_db.port or 5432) == 5432
    assert prefect_db.username == pg["POSTGRES_USER"] and prefect_db.password == pg["POSTGRES_PASSWORD"]
    assert prefect_db.path.lstrip("/") in databases

    scheduler_port = _command_option(services["dask-scheduler"], "entrypoint", "--port")
    for name, svc in services.items():
        env = _env(svc)
        if "AEROCAL_DATABASE_URL" in env:
            url = urlsplit(env["AEROCAL_DATABASE_URL"])
            assert url.hostname == "postgres", f"{name}: database host {url.hostname}"
            assert url.username == pg["POSTGRES_USER"] and url.password == pg["POSTGRES_PASSWORD"], name
            assert url.path.lstrip("/") in databases, f"{name}: database {url.path} is never created"
            assert url.path.lstrip("/") != prefect_db.path.lstrip("/"), f"{name} shares Prefect's database"
        if "PREFECT_API_URL" in env:
            url = urlsplit(env["PREFECT_API_URL"])
            assert url.hostname == "prefect-server" and str(url.port) == prefect_port, (
                f"{name}: {url.geturl()}"
            )
            assert url.path == "/api"
        for key in ("command", "entrypoint"):
            for arg in svc.get(key) or []:
                if str(arg).startswith("tcp://"):
                    url = urlsplit(arg)
                    assert url.hostname in services, f"{name}: {arg} names no service"
                    assert str(url.port) == scheduler_port, f"{name}: {arg} is not the scheduler's port"
    assert f"{prefect_port}:{prefect_port}" in services["prefect-server"]["ports"]


def test_workers_share_the_data_volume_and_artifact_root(compose):
    services = compose["services"]
    for name in ("dask-worker", "aerocal-worker"):
        mounts = dict(v.split(":")[:2] for v in services[name]["volumes"])
        assert mounts.get("data") == "/data", f"{name} does not mount the data volume at /data"
        assert _env(services[name])["AEROCAL_ARTIFACT_ROOT"].startswith("/data/")
    assert (Path(__file__).resolve().parents[1] / "docker" / "README.md").read_text().count("compose") >= 2


def test_image_workers_get_the_same_environment_as_local_clusters():
    """The image's Dask configuration unsets Dask's MALLOC_TRIM_THRESHOLD_ like aerocal's local clusters."""
    from aerocal.matching.cluster import WORKER_ENVIRONMENT

    assert "COPY docker/dask.yaml /etc/dask/" in (DOCKER / "Dockerfile").read_text()
    config = yaml.safe_load((DOCKER / "dask.yaml").read_text())
    assert config["distributed"]["nanny"]["pre-spawn-environ"] == WORKER_ENVIRONMENT
