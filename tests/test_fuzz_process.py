"""A fast subset of the fault corpus through `aerocal process` (the whole corpus: benchmarks/fuzz_process_bench.py).

One simulated flight (conte-calibration, 12 rendered frames, eo.csv, GCP files, camera.json, flight.json);
each case is a copy with one fault of :mod:`aerocal.simulate.faults`, processed by the CLI against one
shared store. What a user checks: no traceback, exit code 2 for input that must stop, the file (or the GCP)
named, and nothing stored or changed by a run that did not succeed. One case kills `aerocal process` with
SIGKILL midway: the store stays whole, `aerocal runs list` does not show the dead run as running, and a
re-run succeeds.
"""

from __future__ import annotations

import json
import os

import pytest

from benchmarks.fuzz_process_bench import make_base, run_case, run_kill

SEED = 7
#: (kind, seed): the preflight stops are fast; one image fault and one displaced GCP run the whole flight
CASES = [
    ("eo-cell", 1006),
    ("eo-header", 1010),
    ("eo-truncated", 1009),
    ("eo-row-missing", 1007),
    ("gcp-conflict", 1013),
    ("camera-json", 1016),
    ("camera-json", 1018),
    ("flight-json", 1017),
    ("flight-json", 1020),
    ("camera-json", 1106),  # f = 1e308: was a traceback from the control step's SVD
    ("flight-json", 1161),  # crs = EPSG:999999: was ignored (the images' UTM zone used)
    ("image-truncated", 1000),
    ("gcp-displaced", 1012),
]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    from prefect.settings import PREFECT_API_URL
    from prefect_harness import prefect_harness

    root = tmp_path_factory.mktemp("fuzz")
    with prefect_harness():
        env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "COLUMNS": "250"}
        base = make_base(root, SEED, env)
        yield base, root / "cases", root / "aerocal.db", root / "artifacts", env


@pytest.mark.parametrize("kind,seed", CASES)
def test_a_fault_is_stopped_or_said_and_changes_nothing(kind, seed, corpus):
    base, work, db, artifacts, env = corpus
    out = run_case(base, kind, seed, work, db, artifacts, env)
    assert not out.problems, (f"fault seed {seed}, flight seed {SEED}: {out.fault.detail}: {out.problems}\n"
                              f"{out.output[-3000:]}")


def test_sigkill_midway_leaves_the_store_whole_and_a_rerun_succeeds(corpus):
    base, work, db, artifacts, env = corpus
    out = run_kill(base, 4, work, env)
    assert not out.problems, f"seed 4, flight seed {SEED}: {out.fault.detail}: {out.problems}\n{out.output[-3000:]}"


def test_undecodable_pixels_stop_with_one_line_without_a_prefect_server(corpus):
    """As a user runs it, with no Prefect server configured (a temporary one starts): an image whose header
    reads but whose pixels do not is bad input named in one line, exit 2, no Prefect log or traceback."""
    base, work, db, artifacts, env = corpus
    env = {k: v for k, v in env.items() if k != "PREFECT_API_URL"}
    out = run_case(base, "image-header-bitflip", 1093, work, db, artifacts, env)
    # not a terminal: the steps started are logged ("processing FOLDER: match"), then the failure is one line
    steps = [line.rsplit(": ", 1)[1] for line in out.output.splitlines() if line.startswith("processing ")]
    lines = [line for line in out.output.splitlines() if line.strip() and not line.startswith("processing ")]
    assert out.exit_code == 2 and not out.problems, f"flight seed {SEED}: {out.problems}\n{out.output[-3000:]}"
    assert len(lines) == 1 and "IMG_0011.tif" in lines[0] and "Fix:" in lines[0], out.output
    assert steps[-1] == "match", out.output  # where the pixels are first decoded


def test_a_flight_whose_calibration_only_its_input_errors_reject_uses_it(corpus):
    """A measurement of gcp_list.txt that cannot be read is skipped at ingest and its error rejects the flight's
    calibration for later flights ("fix them and calibrate again"); the fit never saw it, so the flight's own
    block uses that calibration rather than the nominal camera, and the run says so. Its own store: no
    certificate of an earlier case is selected instead of a self-calibration."""
    base, work, _, _, env = corpus
    seed = 1015
    out = run_case(base, "gcp-measurement", seed, work, work / "own-calibration.db", work / "own-artifacts", env)
    assert out.exit_code == 0 and not out.problems, (f"fault seed {seed}, flight seed {SEED}: {out.fault.detail}: "
                                                    f"{out.problems}\n{out.output[-3000:]}")
    run = work / f"gcp-measurement-{seed}" / "run"
    made = json.loads((run / "calibration_certificate.json").read_text())
    used = json.loads((run / "certificate.json").read_text())
    summary = json.loads((run / "run.json").read_text())
    problems = made["review"]["problems"]
    assert made["review"]["status"] == "rejected" and len(problems) == 1 and "gcp_list.txt" in problems[0], problems
    assert used["id"] == made["id"] and used["camera"] == made["camera"], (used["id"], made["id"])
    assert "this flight's block uses it" in summary["certificate_reason"], summary["certificate_reason"]
