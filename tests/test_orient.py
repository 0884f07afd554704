"""Initial orientation: from recorded GNSS/IMU, or by incremental SfM on our own matches."""

import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.geometry import rotvec_from_matrix
from aerocal.orient import georeference, has_priors, orient_from_priors, orient_incremental, poses_arrays
from aerocal.simulate import simulate_flight
from aerocal.simulate.simulator import recorded_R_cw


def keypoints_and_matches(sim) -> tuple[pa.Table, pa.Table]:
    """The simulated measurements as keypoints and verified matches (what matching would hand over)."""
    o = sim.observations.to_pydict()
    img, trk = np.asarray(o["image_id"]), np.asarray(o["track_id"])
    kid = np.zeros(len(img), dtype=np.int32)
    for i in np.unique(img):
        sel = np.flatnonzero(img == i)
        kid[sel] = np.arange(len(sel))
    keypoints = tables.from_columns("keypoints", {"image_id": img, "keypoint_id": kid, "x": o["x"], "y": o["y"]})
    order = np.lexsort((img, trk))
    rows = {"image_id1": [], "image_id2": [], "keypoint_id1": [], "keypoint_id2": []}
    t_sorted = trk[order]
    starts = np.flatnonzero(np.r_[True, t_sorted[1:] != t_sorted[:-1]])
    for s, e in zip(starts, np.r_[starts[1:], len(order)], strict=True):
        members = order[s:e]
        for a in range(len(members)):
            for b in range(a + 1, len(members)):
                p, q = members[a], members[b]
                rows["image_id1"].append(img[p])
                rows["image_id2"].append(img[q])
                rows["keypoint_id1"].append(kid[p])
                rows["keypoint_id2"].append(kid[q])
    return keypoints, tables.from_columns("matches", rows)


def test_priors_become_the_initial_poses():
    sim = simulate_flight("conte-calibration", seed=1, max_images=10)
    assert has_priors(sim.images)
    ids, R, C = poses_arrays(orient_from_priors(sim.images))
    assert np.allclose(R, recorded_R_cw(sim.images), atol=1e-9)
    assert np.allclose(C[:, 2], sim.images.column("gnss_z").to_numpy())


def test_incremental_sfm_registers_every_image_and_georeferences_with_gcps():
    seed = 2
    sim = simulate_flight("conte-calibration", seed=seed)
    images = sim.images.drop_columns(["gnss_x"]).append_column(
        "gnss_x", pa.nulls(sim.images.num_rows, pa.float64())).select(sim.images.schema.names)
    assert not has_priors(images), "a block without GNSS (like the copr images)"
    keypoints, matches = keypoints_and_matches(sim)
    done = []
    poses, points, observations = orient_incremental(images, keypoints, matches, sim.spec.camera_true,
                                                     progress=lambda d, t: done.append((d, t)))
    assert poses.num_rows == 44, f"seed {seed}: registered {poses.num_rows} of 44"
    assert done and done[-1][1] == 44
    assert points.num_rows > 1000 and np.median(points.column("error").to_numpy()) < 1.0
    geo, _ = georeference(poses, sim.spec.camera_true, sim.gcps, sim.gcp_observations)
    ids, R, C = poses_arrays(geo)
    true_C = np.stack([sim.exposures[i - 1].C for i in ids])
    true_R = np.stack([sim.exposures[i - 1].R_cw for i in ids])
    d = np.linalg.norm(C - true_C, axis=1)
    ang = np.degrees([np.linalg.norm(rotvec_from_matrix(a @ b.T)) for a, b in zip(R, true_R, strict=True)])
    # starting values for the adjustment: the similarity rests on 11 control points triangulated in a
    # 60 %-overlap block whose height precision is ~2 m each, so the block is placed to a few metres
    assert np.median(d) < 10.0, f"seed {seed}: centres {np.median(d):.2f} m from truth (GSD 0.5 m at 850 m)"
    assert np.median(ang) < 0.5, f"seed {seed}: rotations {np.median(ang):.3f} deg from truth"

    # the adjustment then starts from these poses, its datum from the control points alone
    from aerocal.adjust import AdjustConfig, adjust

    res = adjust(images, sim.observations, sim.spec.camera_true, AdjustConfig(free=(), gnss_sigma_m=None),
                 sim.gcps, sim.gcp_observations, initial_poses=geo)
    ids2, R2, C2 = poses_arrays(res.poses)
    d2 = np.linalg.norm(C2 - np.stack([sim.exposures[i - 1].C for i in ids2]), axis=1)
    assert res.converged and abs(res.sigma0 - 1.0) < 0.1, f"seed {seed}: sigma0 {res.sigma0:.3f}"
    assert np.median(d2) < np.median(d), f"seed {seed}: adjusted centres {np.median(d2):.2f} m"
    # without GNSS the centres of a narrow-angle block at 850 m trade off against its attitudes (metres per
    # tenth of a degree); what must hold is that the check points are as accurate as the adjustment says
    rho = np.asarray(res.rho)
    assert np.all((rho > 0.4) & (rho < 2.0)), f"seed {seed}: check-point rho {rho}"
