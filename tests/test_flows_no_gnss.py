"""A flight without GNSS/IMU (like the copr images) through ``process_flight``: rendered frames stripped of
every metadata field, matched on the pairs a coarse match of all pairs retrieves, oriented by incremental SfM
on our matches, georeferenced on the control points and adjusted without position or attitude observations;
the blunders of the matching are removed by the robust screening before the least-squares adjustment."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import rasterio
import tifffile

SEED = 4
N_IMAGES = 16


@pytest.fixture(scope="module")
def bare_flight(tmp_path_factory):
    """Rendered thermal frames with no position, attitude, time or camera tags, and no EO file."""
    from aerocal.simulate import simulate_flight, write_flight

    sim = simulate_flight("conte-calibration", seed=SEED, max_images=N_IMAGES)
    folder = write_flight(sim, tmp_path_factory.mktemp("flights") / "bare", mode="images")
    (folder / "eo.csv").unlink()
    for frame in (folder / "images").glob("*.tif"):
        tifffile.imwrite(frame, tifffile.imread(frame))  # pixels only: every tag is gone
    return folder, sim


def test_flight_without_gnss_is_oriented_by_sfm_and_georeferenced_on_control(prefect_server, bare_flight,
                                                                               tmp_path):
    from flows.process import process_flight
    from storage.database import connect
    from storage.provenance import provenance

    folder, sim = bare_flight
    url = f"sqlite:///{tmp_path / 'aerocal.db'}"
    out = tmp_path / "run"
    summary = process_flight(folder, out, "none", database_url=url, artifact_root=str(tmp_path / "art"))
    orient = summary.steps["orient"]
    print("orient:", orient.extra)
    assert orient.extra["method"] == "incremental", f"seed {SEED}: {orient}"
    assert orient.extra["registered"] == N_IMAGES, f"seed {SEED}: {orient.extra}"
    # the pairs matched in full were retrieved by a coarse match of all pairs, not all of them
    match = summary.steps["match"].extra
    print("match:", match)
    assert match["pairs_from"].startswith("a coarse match of all 120 pairs"), match
    assert match["pairs"] < 120, f"seed {SEED}: every pair matched in full: {match}"

    with connect(url).session() as session:
        conf = provenance(session, summary.run_id).to_dict()["configuration"]
    for which in ("calibration_adjust", "block_adjust"):
        eff = conf["effective"][which]
        assert eff["gnss_sigma_m"] is None and eff["attitude_sigma_deg"] is None, (which, eff)

    adj = json.loads((out / "adjustment.json").read_text())
    gsd = sim.trajectory.gsd_m
    rmse = np.asarray(adj["check_rmse_m"])
    rho = np.asarray(adj["rho"])
    print(f"sigma0 {adj['sigma0']:.3f}, reprojection RMS {adj['reprojection_rms_px']:.3f} px, check RMSE "
          f"{np.round(rmse, 3)} m (GSD {gsd:.3f} m), rho {np.round(rho, 2)}")
    # matched thermal frames: blunders screened out, the least-squares residuals are sub-pixel
    assert adj["reprojection_rms_px"] < 0.5, f"seed {SEED}: reprojection RMS {adj['reprojection_rms_px']:.3f} px"
    assert np.hypot(rmse[0], rmse[1]) < 1.0 * gsd, f"seed {SEED}: planimetric check RMSE {rmse[:2]} m"
    # the check points are as accurate as the adjustment says (loose band: a handful of check points)
    assert np.all((rho > 0.3) & (rho < 2.5)), f"seed {SEED}: rho {rho}"
    with rasterio.open(summary.files["orthomosaic"]) as ds:
        assert ds.crs.to_string() == sim.crs and ds.count >= 1
    # the diagnosis leaves out the blunders the block adjustment rejected instead of screening again
    selection = " ".join(adj.get("selection") or [])
    rejected = re.search(r"rejected (\d+) of \d+ tie observations.*?(\d+) more left alone", selection)
    screening = json.loads((out / "diagnosis.json").read_text())["screening"]
    print("diagnosis:", screening)
    left_out = re.match(r"the block adjustment's screening: (\d+) of", screening or "")
    assert rejected and left_out, f"seed {SEED}: block {selection!r}, diagnosis {screening!r}"
    # with the tracks intersected after a thinned adjustment (matched flights), their blunders too
    thinned = re.search(r"tie points thinned.*?, (\d+) of their observations rejected as blunders", selection)
    assert thinned, f"seed {SEED}: a matched flight's adjustment did not thin its tracks: {selection!r}"
    # and, beyond those, the observations it could not place (tracks that did not intersect) and the ones
    # whose residual exceeds the blunder threshold at the block's tie sigma: the diagnosis baseline must fit
    # its weights like the block it repeats
    screened = int(rejected.group(1)) + int(rejected.group(2)) + int(thinned.group(1))
    n_obs = int(re.search(r"screening: \d+ of (\d+)", screening).group(1))
    assert screened <= int(left_out.group(1)) <= screened + 0.05 * n_obs, (selection, screening)
    sigma0 = json.loads((out / "diagnosis.json").read_text())["sigma0"]["before"]
    assert sigma0 < 1.5, f"seed {SEED}: diagnosis baseline sigma0 {sigma0:.2f}, the block's {adj['sigma0']:.2f}"
