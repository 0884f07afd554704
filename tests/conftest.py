"""Session set-up shared by every test module."""

import os
import sys

import pytest


def pytest_configure(config):
    """The CLI's consoles (:mod:`flows.cli.console`) fix a COLUMNS they find when they are made, and later follow
    the terminal's width otherwise. Made here, outside any test's environment, they follow each test's COLUMNS;
    made inside a test that invokes the CLI at 60 columns, every later table of that process would be folded to
    60 (two test files in one process of ``pytest -n 2``)."""
    columns = os.environ.pop("COLUMNS", None)
    try:
        import flows.cli.console  # noqa: F401
    finally:
        if columns is not None:
            os.environ["COLUMNS"] = columns


#: the longest test files (minutes each), started first: the last file a process starts is then a short one, and
#: the two processes of ``make test`` finish together
FIRST = ("test_rendered_discovery.py", "test_seneca_process.py", "test_study_daakir2019.py",
         "test_study_conte2018.py", "test_flir_flight.py", "test_model_loop.py", "test_dask_cluster.py",
         "test_demo.py", "test_campaign_concurrency.py")


def pytest_collection_modifyitems(session, config, items):
    """Run the files of :data:`FIRST` first, in that order; the others keep theirs (the same order in every
    process, as pytest-xdist requires)."""
    rank = {name: k for k, name in enumerate(FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(FIRST)))


def pytest_sessionfinish(session, exitstatus):
    """The Prefect server the flow tests shared (:mod:`prefect_harness`), stopped while the streams are open."""
    harness = sys.modules.get("prefect_harness")
    if harness is not None:
        harness.stop_shared_server()


@pytest.fixture(scope="module")
def prefect_server():
    """A temporary Prefect server for a module's flow runs (tests/prefect_harness.py)."""
    from prefect_harness import prefect_harness

    with prefect_harness():
        yield
