"""Dependencies point one way: the engine never imports the platform."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"prefect", "prefect_dask", "sqlalchemy", "alembic", "psycopg", "flows", "tasks", "storage"}


#: the one engine module allowed to reach ``flows`` (lazily, checked below); it is the command line, not processing
COMMAND_LINE = ROOT / "aerocal" / "cli.py"


def _imports(path: Path) -> set[str]:
    """Top-level packages ``path`` imports (relative imports resolved, lazy imports included)."""
    return {name.split(".")[0] for name in _imported_modules(path)}


def test_engine_does_not_import_platform():
    offenders = {}
    for path in (ROOT / "aerocal").rglob("*.py"):
        if path == COMMAND_LINE:
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
            if "simulate" in path.parts or path == COMMAND_LINE:
                continue
            assert "truth.json" not in path.read_text(), f"{path.relative_to(ROOT)} mentions truth.json"


def test_processing_never_imports_the_simulator():
    """Diagnosis, adjustment and products must work from measurements alone, never from the simulator
    (imports anywhere in a module, lazy and relative ones included). Only the command line, which is not
    processing and sits above the simulator in :data:`ENGINE_LAYERS`, is exempt, by its exact path."""
    offenders = []
    for path in sorted((ROOT / "aerocal").rglob("*.py")):
        if "simulate" in path.parts or path == COMMAND_LINE:
            continue
        if any(n == "aerocal.simulate" or n.startswith("aerocal.simulate.") for n in _imported_modules(path)):
            offenders.append(str(path.relative_to(ROOT)))
    assert not offenders, f"processing modules import the simulator: {offenders}"


def _imported_modules(path: Path, source: str | None = None) -> set[str]:
    """Full dotted names of every module ``path`` imports (lazy imports included), and of every name a
    ``from`` import takes from a module (it may be a submodule). A relative import is resolved against the
    package of ``path`` (its folder relative to the repository root), as Python resolves it: ``from ..simulate
    import x`` in ``aerocal/diagnose/twin.py`` is ``aerocal.simulate``. ``source`` replaces the file's text
    (for tests of this function); one that climbs above the top-level package raises ValueError."""
    package = path.relative_to(ROOT).parts[:-1]
    names = set()
    for node in ast.walk(ast.parse(path.read_text() if source is None else source, filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                module = node.module or ""
            else:
                if node.level > len(package):
                    raise ValueError(f"{path.relative_to(ROOT)}:{node.lineno}: relative import beyond the "
                                     f"top-level package")
                base = package[: len(package) - node.level + 1]
                module = ".".join((*base, node.module) if node.module else base)
            names.add(module)
            names.update(f"{module}.{a.name}" for a in node.names if a.name != "*")
    return names


def test_relative_imports_are_resolved_against_the_package():
    twin = ROOT / "aerocal" / "diagnose" / "twin.py"
    source = (
        "from ..simulate import simulate_flight\n"
        "from . import model\n"
        "from .engine import Evidence\n"
        "def f():\n    from ...aerocal.io import write_text_atomic\n"
    )
    with pytest.raises(ValueError, match="beyond the top-level package"):
        _imported_modules(twin, source)
    assert _imported_modules(twin, source.split("def f")[0]) == {
        "aerocal.simulate", "aerocal.simulate.simulate_flight", "aerocal.diagnose", "aerocal.diagnose.model",
        "aerocal.diagnose.engine", "aerocal.diagnose.engine.Evidence",
    }
    init = ROOT / "aerocal" / "diagnose" / "__init__.py"
    assert _imported_modules(init, "from .engine import diagnose\n") == {
        "aerocal.diagnose.engine", "aerocal.diagnose.engine.diagnose"}


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


#: where every function-local import must say why it is not at module level
LOCAL_IMPORT_ROOTS = ("aerocal", "storage", "flows", "tasks")
LOCAL_IMPORT_EXEMPT: tuple[str, ...] = ()
#: the reasons a function-local import may have: a measured start-up cost, or an import cycle
LOCAL_IMPORT_REASONS = ("# lazy:", "# import cycle:")


def _function_local_imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    found = []
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            for stmt in fn.body:
                found.extend(n for n in ast.walk(stmt) if isinstance(n, ast.Import | ast.ImportFrom))
    return sorted(set(found), key=lambda n: n.lineno)


def _unexplained_local_imports(source: str) -> list[int]:
    """Line numbers of function-local imports without a reason: a comment starting with one of
    :data:`LOCAL_IMPORT_REASONS` on the import's own line or on the line above it (above the first import of
    a run of consecutive imports, blank lines between them included, which it covers)."""
    lines = source.splitlines()
    imports = _function_local_imports(ast.parse(source))
    import_lines = {k for n in imports for k in range(n.lineno, n.end_lineno + 1)}
    bad = []
    for node in imports:
        own = [lines[k - 1] for k in range(node.lineno, node.end_lineno + 1)]
        if any(reason in line for line in own for reason in LOCAL_IMPORT_REASONS):
            continue
        above = node.lineno - 1
        while above in import_lines or (above > 1 and not lines[above - 1].strip() and above - 1 in import_lines):
            above -= 1
        if above < 1 or not lines[above - 1].strip().startswith(LOCAL_IMPORT_REASONS):
            bad.append(node.lineno)
    return bad


def test_unexplained_local_import_is_found():
    source = (
        "import os\n\n\n"
        "def f():\n    import json\n\n    return json\n\n\n"
        "def g():\n    # lazy: pyarrow costs 0.1 s at start-up\n    import pyarrow\n    import pyarrow.parquet\n\n"
        "    return pyarrow\n\n\n"
        "def h():\n    # a remark that gives no reason\n    import csv\n\n    return csv\n\n\n"
        "def k():\n    if os.name:\n        from io import BytesIO  # import cycle: io imports this module\n"
        "        return BytesIO\n"
    )
    assert _unexplained_local_imports(source) == [5, 20]


def test_every_function_local_import_says_why():
    """Imports belong at the top of a module, where they show what it depends on; one inside a function is
    kept only for a measured start-up cost or an import cycle, and says so."""
    offenders = []
    for folder in LOCAL_IMPORT_ROOTS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel.startswith(LOCAL_IMPORT_EXEMPT):
                continue
            offenders += [f"{rel}:{line}" for line in _unexplained_local_imports(path.read_text())]
    assert not offenders, (
        "function-local imports without a '# lazy: ...' or '# import cycle: ...' comment (move them to the top "
        f"of the module, or say why not): {offenders}"
    )


#: the engine's units (top-level modules and packages of ``aerocal``), lowest first: a unit imports only units
#: of lower layers, never one of its own layer or above (``cli`` reaches ``flows`` lazily, checked above)
ENGINE_LAYERS: tuple[tuple[str, ...], ...] = (
    ("io",),
    ("tables", "geometry", "camera", "effects", "targets"),
    ("poses",),
    ("certificates",),
    ("formats", "ingest"),
    ("adjust", "matching", "enhance"),
    ("orient",),
    ("diagnose",),
    ("calibrate",),
    ("products", "assess"),
    ("report",),
    ("pipeline",),
    ("simulate",),
    ("cli",),
)
MAX_TOP_LEVEL_MODULES = 12


def _engine_unit_edges() -> dict[tuple[str, str], list[str]]:
    """(importing unit, imported unit) -> the files with such an import (lazy imports included)."""
    edges: dict[tuple[str, str], list[str]] = {}
    for path in sorted((ROOT / "aerocal").rglob("*.py")):
        rel = path.relative_to(ROOT / "aerocal")
        src = rel.parts[0].removesuffix(".py")
        for name in _imported_modules(path):
            parts = name.split(".")
            if parts[0] != "aerocal" or len(parts) < 2:
                continue
            dst = parts[1]
            if dst != src and ((ROOT / "aerocal" / dst).is_dir() or (ROOT / "aerocal" / f"{dst}.py").is_file()):
                edges.setdefault((src, dst), []).append(rel.as_posix())
    return edges


def test_engine_units_import_only_lower_layers():
    rank = {unit: k for k, layer in enumerate(ENGINE_LAYERS) for unit in layer}
    units = {p.name.removesuffix(".py") for p in (ROOT / "aerocal").iterdir()
             if (p.suffix == ".py" and p.name != "__init__.py") or (p.is_dir() and (p / "__init__.py").exists())}
    assert units == set(rank), f"units missing from ENGINE_LAYERS (place them): {sorted(units ^ set(rank))}"
    bad = {f"{src} -> {dst}": files for (src, dst), files in _engine_unit_edges().items() if rank[dst] >= rank[src]}
    assert not bad, f"sideways or upward imports between engine units (see ENGINE_LAYERS): {bad}"


def test_engine_top_level_is_small_and_every_package_says_what_it_owns():
    modules = sorted(p.name for p in (ROOT / "aerocal").glob("*.py") if p.name != "__init__.py")
    assert len(modules) <= MAX_TOP_LEVEL_MODULES, f"aerocal/ holds {len(modules)} modules: {modules}"
    thin = []
    for init in [ROOT / "aerocal" / "__init__.py", *sorted((ROOT / "aerocal").glob("*/__init__.py"))]:
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        if len(doc.split()) < 25:
            thin.append(init.relative_to(ROOT).as_posix())
    assert not thin, f"package docstrings that do not say what the package owns: {thin}"


def _named_tests(doc: str) -> list[str] | None:
    """The test files named by the last paragraph of a package docstring when it starts with ``Tests:``
    (``tests/...py`` paths separated by commas, ending with a full stop), else ``None``."""
    last = doc.strip().split("\n\n")[-1]
    if not last.startswith("Tests:"):
        return None
    return [name.strip() for name in last.removeprefix("Tests:").strip().rstrip(".").split(",")]


def test_every_package_names_the_tests_that_cover_it():
    """A reader of a package's ``__init__`` learns where its tests are: the docstring ends with a paragraph
    ``Tests: tests/test_a.py, tests/test_b.py.`` naming at least one file, and every file it names exists."""
    missing, wrong = [], {}
    for init in sorted((ROOT / "aerocal").glob("*/__init__.py")):
        rel = init.relative_to(ROOT).as_posix()
        named = _named_tests(ast.get_docstring(ast.parse(init.read_text())) or "")
        if not named:
            missing.append(rel)
            continue
        bad = [n for n in named if not (n.startswith("tests/test_") and n.endswith(".py") and (ROOT / n).is_file())]
        if bad:
            wrong[rel] = bad
    assert not missing, f"package docstrings without a final 'Tests: tests/test_....py.' paragraph: {missing}"
    assert not wrong, f"package docstrings name test files that do not exist: {wrong}"


def test_named_tests_are_read_from_the_last_paragraph():
    assert _named_tests("Owns x.\n\nTests: tests/test_a.py,\ntests/test_b.py.") == ["tests/test_a.py",
                                                                                    "tests/test_b.py"]
    assert _named_tests("Owns x.\n\nTests: tests/test_a.py.\n\nMore words.") is None
    assert _named_tests("Owns x.") is None


#: :mod:`aerocal.certificates.identity` may import, of the engine, the certificate errors only
IDENTITY = ROOT / "aerocal" / "certificates" / "identity.py"
IDENTITY_MAY_IMPORT = "aerocal.certificates.errors"


def _identity_engine_imports(source: str | None = None) -> list[str]:
    """Engine modules the identity module imports beyond :data:`IDENTITY_MAY_IMPORT` and the packages that
    hold it (``source`` replaces the file's text, for the test of this check)."""
    parents = {"aerocal", "aerocal.certificates"}
    return sorted(n for n in _imported_modules(IDENTITY, source) if n.split(".")[0] == "aerocal"
                  and n not in parents and n != IDENTITY_MAY_IMPORT and not n.startswith(IDENTITY_MAY_IMPORT + "."))


def test_camera_identity_depends_on_the_certificate_errors_only():
    """:class:`~aerocal.certificates.identity.CameraIdentity` is the one class the certificate document, ingest,
    the exchange formats and the database (``storage``) name a camera with, so it stays a leaf: its error lives
    in :mod:`aerocal.certificates.errors` so that it needs no schema. Importing the schema (or the document)
    would make a camera's name carry pydantic and the whole certificate validation, and would close an import
    cycle as soon as the schema checks an identity with this class."""
    extra = _identity_engine_imports()
    assert not extra, f"aerocal/certificates/identity.py imports {extra}; it may import {IDENTITY_MAY_IMPORT} only"
    assert _identity_engine_imports("from .schema import SCHEMA\n") == [
        "aerocal.certificates.schema", "aerocal.certificates.schema.SCHEMA"]
    assert _identity_engine_imports("from aerocal.certificates import errors, schema\n") == [
        "aerocal.certificates.schema"]
