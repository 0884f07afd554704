"""Conte 2018's study on its quick block: what a reader checks in its table.

One seed, 24-frame city blocks per year and the 44-image calibration subset. The extended model (a 33 ms row
readout, CAL4's free set for the certificate) must show the paper's contrasts: the certificate (STR1) keeps the
DSM on the ground, the self-calibration (STR2) runs away with the focal length while its check points stay
good, STR3 carries the other year's runaway, and a certificate without b1/b2 (CAL6) fits the GCPs worse than
CAL4; today's model (no readout) shows none of it. The same strategies through the product (the pipeline, a
certificate store across the flights, the diagnosis step) do not run away, and the diagnosis names the readout.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _study():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    import studies.conte2018 as study

    return study


def test_conte2018_quick_reproduces_the_papers_contrasts(tmp_path):
    study = _study()
    md = study.main(["--quick", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "conte2018_quick.json").read_text())
    today, ext = result["summary"]["today"], result["summary"]["extended"]
    H, f_true = result["height_m"], result["true_f"]

    # STR1: the certificate's affinity takes up the readout, the DSM stays within a few GSD of the ground
    for year in ("2016", "2017"):
        assert abs(ext[f"STR1 {year}"]["dod"]) < 3.0, ext[f"STR1 {year}"]
    assert ext["CAL4"]["b1"] < -5.0, f"CAL4 b1 {ext['CAL4']['b1']} px should absorb the 33 ms readout (~-14 px)"
    # STR2: the focal length runs away with the flying height (dZ = H df / f), check points stay good
    s2 = ext["STR2 2017"]
    assert abs(s2["dod"]) > 10.0 and abs(s2["dod"]) > 5 * abs(ext["STR1 2017"]["dod"]), s2
    assert abs(s2["dod"] + H * (s2["f"] - f_true) / f_true) < 0.3 * abs(s2["dod"]), s2
    assert s2["cp_mean"] < 0.1 * abs(s2["dod"]), s2
    # today's model has no readout: no runaway
    assert abs(today["STR2 2017"]["dod"]) < 0.2 * abs(s2["dod"]), today["STR2 2017"]
    # STR3 carries STR2-2016's focal length into 2017
    assert abs(ext["STR3 2017"]["dod"]) > 5 * abs(ext["STR1 2017"]["dod"]), ext["STR3 2017"]
    # Table 5's direction: without b1/b2 (CAL6) the GCPs fit worse, only when the frames are read out row by row
    assert ext["CAL6"]["gcp_rmse"] > 1.5 * ext["CAL4"]["gcp_rmse"], (ext["CAL4"], ext["CAL6"])
    assert today["CAL6"]["gcp_rmse"] < 1.3 * today["CAL4"]["gcp_rmse"], (today["CAL4"], today["CAL6"])

    # with the recorded attitude as an observation (as the product adjusts) the same self-calibration holds f
    assert abs(ext[study.ATTITUDE_ROW]["dod"]) < 0.1 * abs(s2["dod"]), ext[study.ATTITUDE_ROW]

    # through the product (aerocal.pipeline.process, one certificate store): no runaway, the readout named
    prod = result["product"]
    for year in ("2016", "2017"):
        row = prod["extended"]["1"][f"STR2 {year}"]
        assert row["status"] == "accepted" and abs(row["dod"]) < 10.0, row
    for model, per_seed in prod.items():
        for key in study.ROWS:
            named = per_seed["1"][key]["effects"].get("rolling_shutter")
            said = per_seed["1"][key]["diagnosis"] or ""
            assert "affinity_skew" not in per_seed["1"][key]["effects"], (key, said)  # never the one for the other
            if model == "extended" and key.startswith("STR3") and named is None:
                # 2016's certificate, self-calibrated on a block with the readout, carries part of it as b1: what
                # is left of the readout and the affinity are one deformation here, reported as such
                assert "rolling_shutter" in said and "not told apart" in said, (key, said)
            elif model == "extended":
                assert named and abs(named[0] - 0.033) < 0.15 * 0.033, (key, said)
            else:
                assert named is None, (key, per_seed["1"][key]["diagnosis"])
    # the calibration flight has no GNSS time lag: the readout that mimics one is not removed as one
    cal_notes = prod["extended"]["1"]["CAL"]["notes"]
    assert not any(n.startswith("GNSS time lag") and "removed" in n for n in cal_notes), cal_notes

    text = md.read_text()
    assert "through the product" in text
    first_table = text.split("### The strategies through the product")[0]
    rows = [line for line in first_table.splitlines() if re.match(r"\| STR[123] 201[67] \|", line)]
    assert [r.split("|")[1].strip() for r in rows] == list(study.ROWS), text
    assert "10.82" in text and "39.07" in text, "the paper's STR2 DoD means are in the table"
    assert (tmp_path / "conte2018_quick.png").stat().st_size > 10_000
