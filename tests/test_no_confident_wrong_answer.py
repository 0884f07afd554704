"""No confident wrong answer, through `aerocal process` as a user runs it.

* A flat nadir block without GCPs and with consumer GNSS cannot determine the focal length: the product
  keeps the nominal f and says why, instead of certifying one.
* A calibration that is implausible against the nominal camera is stored as rejected, with its reasons,
  the flight goes on with the nominal camera, and no later flight ever selects it.
* A corridor (two strips, no calibration sub-block of parallel strips) is calibrated whole and says so.

Every flight is simulated (seeds in the assertions), written as a flight folder and processed through the
CLI with a fresh SQLite database and artifact store.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from aerocal.certificates.document import Certificate
from aerocal.simulate import PRESETS, simulate_flight, write_flight


def _cli(*args: str):
    from aerocal.cli import app

    return CliRunner().invoke(app, list(args), env={"COLUMNS": "250"})  # rich tables unfolded


def _process(flight: Path, out: Path, store: Path, certificate: str = "none") -> dict:
    result = _cli("process", str(flight), "--certificate", certificate, "--out", str(out), "--json", "--no-figures",
                  "--database-url", f"sqlite:///{store / 'aerocal.db'}", "--artifacts", str(store / "art"))
    assert result.exit_code == 0, result.output
    return json.loads((out / "run.json").read_text())  # the summary --json prints, as the run folder keeps it


def test_a_flat_block_without_gcps_keeps_the_nominal_focal_length(tmp_path, prefect_server):
    seed = 7
    base = PRESETS["conte-calibration"]
    spec = base.replace(n_gcp=0, n_check=0, sensors=dataclasses.replace(base.sensors, gnss_sigma_h_m=3.0,
                                                                          gnss_sigma_v_m=5.0))
    write_flight(simulate_flight(spec, seed=seed), tmp_path / "flight")
    summary = _process(tmp_path / "flight", tmp_path / "run", tmp_path)
    cert = Certificate.from_json(Path(summary["files"]["calibration_certificate"]).read_text())
    assert "f" not in cert.estimated, f"seed {seed}: f was freed: {cert.render_text()}"
    assert cert.camera.f == spec.camera_nominal.f
    assert "f not determined by this block" in cert.significance["f"].dropped, cert.significance
    assert cert.status == "accepted", cert.review
    calibration = json.loads(Path(summary["files"]["calibration"]).read_text())
    assert calibration["predicted_sigmas"]["f"] > 0.005 * spec.camera_nominal.f, calibration["predicted_sigmas"]
    assert "f" in calibration["held_at_nominal"]


def test_an_implausible_calibration_is_rejected_and_never_reused(tmp_path, prefect_server):
    """camera.json with a focal length 30 % off (a wrong pixel pitch): the block determines f, far from the
    nominal; the certificate is stored as rejected and a later `--certificate auto` does not pick it."""
    seed = 8
    spec = PRESETS["conte-calibration"]
    flight = tmp_path / "flight"
    write_flight(simulate_flight(spec, seed=seed), flight)
    doc = json.loads((flight / "camera.json").read_text())
    doc["camera"]["f"] *= 1.3
    (flight / "camera.json").write_text(json.dumps(doc))

    first = _process(flight, tmp_path / "run1", tmp_path)
    assert "REJECTED" in first["certificate_reason"] and "off the nominal" in first["certificate_reason"], first
    rejected = Certificate.from_json(Path(first["files"]["calibration_certificate"]).read_text())
    assert rejected.status == "rejected" and any("off the nominal" in p for p in rejected.review.problems)
    print(f"seed {seed}: rejected f {rejected.camera.f:.2f} +- {rejected.sigmas['f']:.3f} px, true "
          f"{spec.camera_true.f:.2f}, nominal {doc['camera']['f']:.2f}")
    assert abs(rejected.camera.f - spec.camera_true.f) < 5 * rejected.sigmas["f"], f"seed {seed}: {rejected.camera}"
    # and the block determines f, so that "within 5 sigma" says something (measured 0.56 px)
    assert rejected.sigmas["f"] < 1.5, f"seed {seed}: sigma of f {rejected.sigmas['f']:.3f} px above 1.5 px"
    used = Certificate.from_json(Path(first["files"]["certificate"]).read_text())
    assert used.estimated == () and used.camera.f == doc["camera"]["f"]  # the nominal, said in the reason

    # a later flight asks for the stored certificate: the rejected one is passed over (the self-calibration
    # step is reused from the cache, and its certificate is rejected again), and the block stays nominal
    second = _process(flight, tmp_path / "run2", tmp_path, certificate="auto")
    assert "was rejected by its review" in second["certificate_reason"], second["certificate_reason"]
    assert "REJECTED" in second["certificate_reason"]
    used = Certificate.from_json(Path(second["files"]["certificate"]).read_text())
    assert used.estimated == () and used.camera.f == doc["camera"]["f"]
    listing = _cli("certificates", "list", "--database-url", f"sqlite:///{tmp_path / 'aerocal.db'}")
    assert listing.exit_code == 0 and "rejected" in listing.output, listing.output
    pinned = _cli("process", str(flight), "--certificate", rejected.id, "--out", str(tmp_path / "run3"),
                  "--database-url", f"sqlite:///{tmp_path / 'aerocal.db'}", "--artifacts", str(tmp_path / "art"))
    assert pinned.exit_code != 0 and "rejected" in pinned.output, pinned.output


def test_a_corridor_is_calibrated_whole_and_says_why(tmp_path, prefect_server):
    seed = 9
    sim = _cli("simulate", "daakir-uav", "--out", str(tmp_path / "flight"), "--seed", str(seed))
    assert sim.exit_code == 0, sim.output
    summary = _process(tmp_path / "flight", tmp_path / "run", tmp_path)
    calibration = json.loads(Path(summary["files"]["calibration"]).read_text())
    reasons = " ".join(calibration["subset"]["reasons"])
    assert "no calibration sub-block of parallel strips" in reasons, reasons
    cert = Certificate.from_json(Path(summary["files"]["calibration_certificate"]).read_text())
    truth = json.loads((tmp_path / "flight" / "truth.json").read_text())
    assert cert.status == "accepted", cert.review
    assert abs(cert.camera.f - truth["camera_true"]["f"]) < 4 * cert.sigmas["f"], f"seed {seed}: {cert.camera}"
    assert cert.sigmas["f"] <= 0.01 * cert.camera.f, f"seed {seed}: {cert.sigmas}"  # the review's bound
    diagnosis = _cli("diagnose", summary["out_dir"], "--json")
    assert diagnosis.exit_code == 0, diagnosis.output


def test_the_nominal_camera_is_used_as_given_and_never_stored(tmp_path, prefect_server):
    """`--certificate nominal`: a metric camera's laboratory calibration (camera.json) adjusts the block as it is,
    nothing is calibrated or issued (not even a focal length 0.2 % short of the truth), and the run's record
    says so."""
    seed = 11
    spec = PRESETS["conte-calibration"]
    flight = tmp_path / "flight"
    write_flight(simulate_flight(spec, seed=seed), flight)
    doc = json.loads((flight / "camera.json").read_text())
    truth = json.loads((flight / "truth.json").read_text())
    doc["camera"]["f"] = truth["camera_true"]["f"] * 0.998
    (flight / "camera.json").write_text(json.dumps(doc))

    summary = _process(flight, tmp_path / "run", tmp_path, certificate="nominal")
    assert "nominal" in summary["certificate_reason"] and "calibrate" not in summary["steps"], summary
    used = Certificate.from_json(Path(summary["files"]["certificate"]).read_text())
    assert used.estimated == () and used.camera.f == doc["camera"]["f"], used.camera
    assert "calibration_certificate" not in summary["files"]
    listing = _cli("certificates", "list", "--database-url", f"sqlite:///{tmp_path / 'aerocal.db'}")
    assert listing.exit_code == 0 and used.id not in listing.output, listing.output
    runs = _cli("runs", "show", summary["run_id"], "--database-url", f"sqlite:///{tmp_path / 'aerocal.db'}")
    assert runs.exit_code == 0 and "nominal" in runs.output, runs.output

    # a calibration flight makes a certificate: asking it for the nominal camera is refused, naming the fix
    from aerocal.pipeline import process
    from aerocal.pipeline.dataset import FlightInputError

    with pytest.raises(FlightInputError, match="give auto or none"):
        process(flight, certificate="nominal", calibrate_only=True)
