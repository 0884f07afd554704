"""Robust loss of the bundle adjustment (``AdjustConfig.robust_loss``) against gross tie-point blunders.

2 % of the tie observations of a small conte-calibration block (24 frames) are displaced by 20-50 px
(40-100 times the 0.5 px noise) in random directions. Least squares is pulled off by them; a Huber or
Cauchy pass finds them, they are rejected (weight 0) and the least-squares re-adjustment lands where the
clean block lands, with an honest sigma0 and honest sigmas. With ``reject_chi2=None`` the robust solution
itself is kept and gives the blunders small weights.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pyarrow as pa
import pytest
from tolerance import assert_within_sigma

from aerocal.adjust import AdjustConfig, adjust, scale_tie_sigma
from aerocal.simulate import simulate_flight

SEED = 0
FRACTION = 0.02
IO = ("f", "cx", "cy", "k1")


def _with_blunders(observations: pa.Table, rng: np.random.Generator) -> tuple[pa.Table, np.ndarray]:
    """The table with ``FRACTION`` of its rows moved 20-50 px in random directions, and those rows."""
    n = observations.num_rows
    bad = np.sort(rng.choice(n, int(FRACTION * n), replace=False))
    angle = rng.uniform(0.0, 2 * np.pi, len(bad))
    size = rng.uniform(20.0, 50.0, len(bad))
    out = observations
    for col, d in (("x", size * np.cos(angle)), ("y", size * np.sin(angle))):
        v = observations.column(col).to_numpy().copy()
        v[bad] += d
        i = out.schema.get_field_index(col)
        out = out.set_column(i, out.schema.field(i), pa.array(v, out.schema.field(i).type))
    return out, bad


@pytest.fixture(scope="module")
def runs():
    sim = simulate_flight("conte-calibration", seed=SEED, max_images=24)
    dirty, bad = _with_blunders(sim.observations, np.random.default_rng(SEED))
    s = sim.spec.sensors

    def run(obs, loss, **extra):
        cfg = AdjustConfig(**extra, gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                           attitude_sigma_deg=s.imu_sigma_deg, free=("f", "cx", "cy", "k1", "k2", "p1", "p2"),
                           robust_loss=loss)
        return adjust(sim.images, obs, sim.camera_nominal, cfg, sim.gcps, sim.gcp_observations)

    out = {"clean": run(sim.observations, "none")}
    for loss in ("none", "huber", "cauchy"):
        out[loss] = run(dirty, loss)
    out["huber-weights"] = run(dirty, "huber", reject_chi2=None)
    return sim, bad, out


def _describe(sim, res) -> str:
    true = sim.spec.camera_true
    io = ", ".join(f"{n} {getattr(res.camera, n) - getattr(true, n):+.4g} +- {res.sigmas[n]:.2g}" for n in IO)
    return (f"errors {io}; sigma0 {res.sigma0:.2f}; check RMSE {np.round(res.check_rmse, 3)} m, "
            f"{res.iterations} iterations")


def test_least_squares_is_pulled_off_by_blunders(runs):
    sim, bad, out = runs
    clean, ls = out["clean"], out["none"]
    print(f"{len(bad)} blunders in {sim.observations.num_rows} tie observations")
    print("clean:", _describe(sim, clean))
    print("none: ", _describe(sim, ls))
    shift = {n: (getattr(ls.camera, n) - getattr(clean.camera, n)) / clean.sigmas[n] for n in IO}
    print("shift from the clean solution in clean sigmas:", {n: round(v, 2) for n, v in shift.items()})
    assert max(abs(v) for v in shift.values()) > 3, f"seed {SEED}: blunders did not move the IO: {shift}"
    ratio = np.linalg.norm(ls.check_rmse) / np.linalg.norm(clean.check_rmse)
    print(f"check-point RMSE {ratio:.3f} x the clean block's")
    assert ratio > 1.05, f"seed {SEED}: check-point RMSE only {ratio:.3f} x the clean block's"
    assert ls.sigma0 > 5, f"seed {SEED}: sigma0 {ls.sigma0:.2f} does not show the blunders"


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_robust_loss_recovers_the_clean_solution_and_flags_the_blunders(runs, loss):
    sim, bad, out = runs
    clean, res = out["clean"], out[loss]
    true = sim.spec.camera_true
    print(f"{loss}:", _describe(sim, res))
    for n in IO:
        err = getattr(res.camera, n) - getattr(true, n)
        # bounded: f, cx, cy to 0.2 % of f, k1 to 0.02 (a blunder that bends the block widens them past it)
        assert_within_sigma(err, res.sigmas[n], 3, 0.02 if n == "k1" else 0.002 * true.f, f"seed {SEED} {loss}: {n}")
        # and where the clean block is, to within its own precision
        d = getattr(res.camera, n) - getattr(clean.camera, n)
        assert abs(d) < clean.sigmas[n], f"seed {SEED} {loss}: {n} {d:+.4g} from the clean solution"
    ratio = np.linalg.norm(res.check_rmse) / np.linalg.norm(clean.check_rmse)
    assert ratio < 1.03, f"seed {SEED} {loss}: check-point RMSE {ratio:.3f} x the clean block's"
    # the blunders are removed before the final least squares: its precision is the clean block's
    assert 0.9 < res.sigma0 < 1.1, f"seed {SEED} {loss}: sigma0 {res.sigma0:.3f} after rejecting the blunders"
    for n in IO:
        assert res.sigmas[n] < 1.2 * clean.sigmas[n], f"seed {SEED} {loss}: sigma of {n} inflated"
    assert res.selection and "rejected" in res.selection[0], res.selection
    w = res.obs_weight
    rejected = np.flatnonzero(w == 0)
    caught = np.isin(bad, rejected).mean()
    # a clean observation sharing a track with a blunder may go with it (a two-ray track shows the error
    # in both rays); elsewhere only the chi-square tail (0.1 %) should go
    track = sim.observations.column("track_id").to_numpy()
    elsewhere = ~np.isin(track, track[bad])
    false = np.isin(np.flatnonzero(elsewhere), rejected).mean()
    print(f"{loss}: {res.selection[0]}; blunders caught {caught:.3f}, clean observations outside blunder "
          f"tracks rejected {false:.4f}")
    assert caught > 0.95, f"seed {SEED} {loss}: only {caught:.3f} of the blunders rejected"
    assert false < 0.005, f"seed {SEED} {loss}: {false:.4f} of the clean observations rejected"


def test_robust_weights_without_rejection_flag_the_blunders(runs):
    sim, bad, out = runs
    res, loss = out["huber-weights"], "huber"
    print(f"{loss} (no rejection):", _describe(sim, res))

    # A blunder is identifiable when its track has three or more rays. In a two-ray track only the part
    # across the epipolar line shows, and it shows equally in both rays: the loss blames one of the two
    # (Cauchy, redescending, picks either), so there the track, not the blunder, is flagged.
    w = res.obs_weight
    track = sim.observations.column("track_id").to_numpy()
    rays = np.bincount(track)[track]
    blunder = np.zeros(len(w), bool)
    blunder[bad] = True
    ok = np.isfinite(w)
    wb, wc = w[blunder & ok & (rays >= 3)], w[~blunder & ok]
    two = np.array([w[track == track[k]].min() for k in bad[rays[bad] == 2]])
    print(f"{loss}: {len(wb)} blunders in tracks of >= 3 rays: weights median {np.median(wb):.4f}, 95th "
          f"percentile {np.quantile(wb, 0.95):.4f}, max {wb.max():.3f}; {len(two)} in two-ray tracks: smallest "
          f"weight of the track median {np.median(two):.3f}; clean weights median {np.median(wc):.3f}, "
          f"5th percentile {np.quantile(wc, 0.05):.3f}")
    assert np.quantile(wb, 0.95) < 0.1, f"seed {SEED} {loss}: blunders keep weights {np.quantile(wb, 0.95):.3f}"
    assert np.median(wc) > 0.9, f"seed {SEED} {loss}: clean observations down-weighted ({np.median(wc):.3f})"
    assert np.all(out["none"].obs_weight[ok] == 1.0), "without a robust loss every weight is 1"


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_least_squares_after_screening_starts_from_the_robust_pass_and_lands_where_a_cold_start_lands(runs,
                                                                                                      loss):
    sim, _, out = runs
    warm = out[loss]
    kept = np.flatnonzero(warm.obs_weight != 0)
    s = sim.spec.sensors
    cfg = AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                       attitude_sigma_deg=s.imu_sigma_deg, free=("f", "cx", "cy", "k1", "k2", "p1", "p2"))
    dirty, _ = _with_blunders(sim.observations, np.random.default_rng(SEED))
    clean = scale_tie_sigma(dirty.take(pa.array(kept, pa.int64())), warm.tie_sigma_scale)  # as the warm run had
    cold = adjust(sim.images, clean, sim.camera_nominal, cfg, sim.gcps, sim.gcp_observations)
    print(f"{loss}: least squares after screening {warm.iterations} iterations from the robust pass, "
          f"{cold.iterations} from the recorded poses; sigma0 {warm.sigma0:.4f} / {cold.sigma0:.4f}")
    assert warm.converged and cold.converged
    assert warm.iterations <= cold.iterations, (warm.iterations, cold.iterations)
    assert set(warm.sigmas) == set(cold.sigmas), (warm.selection, cold.selection)
    for name in warm.sigmas:
        diff = getattr(warm.camera, name, None)
        if diff is None:
            continue
        assert abs(getattr(warm.camera, name) - getattr(cold.camera, name)) < 0.01 * cold.sigmas[name], name
    assert abs(warm.sigma0 - cold.sigma0) < 1e-3 * cold.sigma0
    assert np.allclose(warm.check_errors, cold.check_errors, atol=1e-3, equal_nan=True)


def test_a_model_started_from_the_one_it_extends_keeps_its_screening_and_lands_where_a_cold_start_lands(runs):
    """``adjust(..., initial=...)``: the model with k2 and the decentring terms freed, started from the fit of the
    model without them, leaves out the same observations (no robust pass of its own), converges in no more
    iterations than from the records (2 against 3 on this easy block), and ends where least squares on those
    observations ends from the records."""
    sim, bad, out = runs
    s = sim.spec.sensors
    cfg = AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                       attitude_sigma_deg=s.imu_sigma_deg, free=IO, robust_loss="cauchy")
    dirty, _ = _with_blunders(sim.observations, np.random.default_rng(SEED))
    simple = adjust(sim.images, dirty, sim.camera_nominal, cfg, sim.gcps, sim.gcp_observations)
    extended_cfg = dataclasses.replace(cfg, free=("f", "cx", "cy", "k1", "k2", "p1", "p2"))
    nested = adjust(sim.images, dirty, sim.camera_nominal, extended_cfg, sim.gcps, sim.gcp_observations,
                    initial=simple)
    assert simple.kept_rows is not None and np.array_equal(nested.kept_rows, simple.kept_rows)
    assert np.isin(bad, nested.kept_rows).mean() < 0.05, f"seed {SEED}: the blunders were kept"
    assert "screened them" in nested.selection[0], nested.selection
    # least squares from the records on the observations the nested fit used, with its tie sigma
    used = scale_tie_sigma(dirty.take(pa.array(nested.kept_rows, pa.int64())), nested.tie_sigma_scale)
    cold = adjust(sim.images, used, sim.camera_nominal, dataclasses.replace(extended_cfg, robust_loss="none"),
                  sim.gcps, sim.gcp_observations)
    print(f"nested: {nested.iterations} iterations from the simpler model, {cold.iterations} from the records; "
          f"sigma0 {nested.sigma0:.4f} / {cold.sigma0:.4f}")
    assert nested.converged and cold.converged
    assert nested.iterations <= cold.iterations, (nested.iterations, cold.iterations)
    for name in extended_cfg.free:
        d = getattr(nested.camera, name) - getattr(cold.camera, name)
        assert abs(d) < 0.05 * cold.sigmas[name], f"seed {SEED}: {name} {d:+.3g} from the cold start"
    assert abs(nested.sigma0 - cold.sigma0) < 1e-3 * cold.sigma0
