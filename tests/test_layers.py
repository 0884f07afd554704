"""Dependencies point one way: the engine never imports the platform."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"prefect", "prefect_dask", "sqlalchemy", "alembic", "psycopg", "flows", "tasks", "storage"}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_engine_does_not_import_platform():
    offenders = {}
    for path in (ROOT / "aerocal").rglob("*.py"):
        if path.name == "cli.py" and path.parent.name == "aerocal":
            continue  # the one module allowed to reach flows, and only lazily (checked below)
        bad = _imports(path) & FORBIDDEN
        if bad:
            offenders[str(path.relative_to(ROOT))] = sorted(bad)
    assert not offenders, f"engine modules import the platform layer: {offenders}"


def test_cli_imports_flows_only_lazily():
    tree = ast.parse((ROOT / "aerocal" / "cli.py").read_text())
    top_level = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            top_level.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            top_level.add(node.module.split(".")[0])
    assert not (top_level & FORBIDDEN), f"aerocal/cli.py imports {top_level & FORBIDDEN} at module level"


def test_tasks_do_not_import_flows_and_storage_does_not_import_tasks_or_flows():
    for folder, bad in (("tasks", {"flows"}), ("storage", {"flows", "tasks"})):
        for path in (ROOT / folder).rglob("*.py"):
            assert not (_imports(path) & bad), f"{path.relative_to(ROOT)} imports {_imports(path) & bad}"


def test_processing_code_never_reads_the_truth():
    for folder in ("aerocal", "flows", "tasks", "storage"):
        for path in (ROOT / folder).rglob("*.py"):
            if "simulate" in path.parts or path.name == "cli.py":
                continue
            assert "truth.json" not in path.read_text(), f"{path.relative_to(ROOT)} mentions truth.json"


def test_processing_never_imports_the_simulator():
    """Diagnosis, adjustment and products must work from measurements alone, never from the simulator
    (imports anywhere in a module, lazy ones included)."""
    offenders = []
    for path in (ROOT / "aerocal").rglob("*.py"):
        if "simulate" in path.parts or path.name == "cli.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.startswith("aerocal.simulate") for n in names):
                offenders.append(str(path.relative_to(ROOT)))
    assert not offenders, f"processing modules import the simulator: {offenders}"


def _imported_modules(path: Path) -> set[str]:
    """Full dotted names of every module ``path`` imports (lazy imports included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def test_studies_and_benchmarks_use_the_pipeline_not_the_platform():
    """Studies and benchmarks run flights through :mod:`aerocal.pipeline` and the engine's public names: never
    Prefect tasks or flows, nor the storage layer (but the storage benchmark, which measures it)."""
    offenders = {}
    for folder in ("studies", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            allowed = {"storage"} if path.name == "storage_bench.py" else set()
            bad = {m.split(".")[0] for m in _imported_modules(path)} & ({"flows", "tasks", "storage"} - allowed)
            private = {m for m in _imported_modules(path)
                       if m.startswith("aerocal.") and m.rsplit(".", 1)[-1].startswith("_")}
            if bad or private:
                offenders[str(path.relative_to(ROOT))] = sorted(bad | private)
    assert not offenders, f"studies/benchmarks reach past the pipeline: {offenders}"


def test_tasks_are_thin_wrappers():
    """A module under tasks/ is a thin wrapper (config, one engine call, retries, storage), never a pipeline."""
    long = {str(p.relative_to(ROOT)): n for p in (ROOT / "tasks").rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 150}
    assert not long, f"tasks modules over 150 lines: {long}"
