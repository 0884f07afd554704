"""Daakir 2019's UAV corridor on a 24-image block: what the thermal correction can gain, and why."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _study():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return importlib.import_module("studies.daakir2019")


def test_daakir_gain_needs_the_full_field_and_stays_below_the_paper(tmp_path):
    study = _study()
    table = importlib.import_module("studies.papers").reference("daakir2019_results.csv")
    if table:  # the paper's Table 16 as the study quotes it
        rows = {r["variant"]: r for r in table if r["experiment"] == "UAV corridor"}
        for variant in ("original", "corrected"):
            assert float(rows[variant]["mean_mm"]) == study.PAPER[variant]["mean"]

    r = study.run(quick=True)
    text = study.markdown(r)
    study.figure(r, tmp_path / "daakir2019_quick.png")
    assert (tmp_path / "daakir2019_quick.png").stat().st_size > 10_000, "figure missing or empty"
    assert "| gain in the mean | 1.38x |" in text and "measured reason" in text
    g = study.gain
    t, w = r["today"], r["workflow"]
    orig, corr, corr_f = "original", "corrected, Eq. 2 model", "corrected, focal-only model"

    # today's set-up: a focal drift under GNSS/IMU priors is absorbed by the similarity (the 1.00x)
    assert abs(g(t["original"], t["corrected"]) - 1.0) < 0.02, t
    # a bent corridor of GCP residuals at the survey's 1 cm: tens of millimetres, as the paper's 21.4 mm
    assert 8e-3 < t["original"]["mean"] < 40e-3, t
    # noise-free, the paper's workflow: the focal drift alone leaves nothing to correct ...
    qf, qn = w["focal noise-free"], w["eq2 noise-free"]
    assert g(qf[orig], qf[corr_f]) < 1.15, qf
    # ... the Eq. 2 field (principal point, pre-calibration 10 degC warmer) bends the corridor, and only the
    # Eq. 2 correction takes most of it out
    assert qn[orig]["mean"] > 1.3 * qf[orig]["mean"], (qn, qf)
    assert g(qn[orig], qn[corr]) > 1.5 and g(qn[orig], qn[corr]) > g(qn[orig], qn[corr_f]), qn
    # the measured reason: that deformation is millimetres, far below the 14.8 mm the paper's 1.4x needs,
    # so under the survey noise the gain stays far from 1.4x
    assert qn[orig]["mean"] * 1000 < study.needed_thermal_mm() / 2
    assert g(w["eq2"][orig], w["eq2"][corr]) < 1.2, w["eq2"]
