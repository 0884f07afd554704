"""Adaptive selection of the self-calibration parameters (``AdjustConfig(adaptive=True)``).

conte-calibration's true camera has k3 = b1 = b2 = 0, tiny decentring (p1 2e-4, p2 -1.5e-4), and a
clear radial distortion (k1 -0.08); its k1, k2, k3 are strongly correlated on a nadir block.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from aerocal.adjust import AdjustConfig, adjust
from aerocal.adjust.selection import choose_drop
from aerocal.camera import PARAM_NAMES
from aerocal.simulate import simulate_flight

SEED = 0
CORR = re.compile(
    r"dropped (\w+): \|corr\((\w+), (\w+)\)\| = ([\d.]+) > ([\d.]+) \(t\((\w+)\) = ([\d.]+), t\((\w+)\) = ([\d.]+)\)$"
)
TEST = re.compile(r"dropped (\w+): t = ([\d.]+) < ([\d.]+) \(not significant at 95 %\)$")
KEPT = re.compile(r"kept (.+): all significant, no \|correlation\| above ([\d.]+)$")


@pytest.fixture(scope="module")
def sim():
    return simulate_flight("conte-calibration", seed=SEED)


def _config(sim, free, adaptive: bool) -> AdjustConfig:
    s = sim.spec.sensors
    return AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                        attitude_sigma_deg=s.imu_sigma_deg, free=tuple(free), adaptive=adaptive)


def _run(sim, free, adaptive: bool):
    return adjust(sim.images, sim.observations, sim.camera_nominal, _config(sim, free, adaptive), sim.gcps,
                  sim.gcp_observations)


def _parse(reasons: list[str]) -> tuple[list[tuple], list[str]]:
    """(dropped: (name, kind, match), kept names) from the selection sentences; every sentence must parse."""
    dropped = []
    for r in reasons[:-1]:
        m = CORR.match(r) or TEST.match(r)
        assert m, f"seed {SEED}: reason does not name the parameter and the number: {r!r}"
        dropped.append((m.group(1), "corr" if m.re is CORR else "t", m))
    k = KEPT.match(reasons[-1])
    assert k, f"seed {SEED}: last reason should list what was kept: {reasons[-1]!r}"
    kept = [part.split(" t=")[0] for part in k.group(1).split(", ")]
    return dropped, kept


def test_adaptive_selection_drops_zero_parameters_keeps_f_cx_cy_and_k1(sim):
    full = _run(sim, PARAM_NAMES, adaptive=False)
    res = _run(sim, PARAM_NAMES, adaptive=True)
    for r in res.selection:
        print(r)
    dropped, kept = _parse(res.selection)
    names = [d[0] for d in dropped]
    assert kept == res.names, f"seed {SEED}: kept {kept}, result has {res.names}"
    assert set(names) | set(res.names) == set(PARAM_NAMES) and not set(names) & set(res.names)
    assert {"f", "cx", "cy"} <= set(res.names) and "k1" in res.names, f"seed {SEED}: kept {res.names}"
    assert {"k3", "b1", "b2"} <= set(names), f"seed {SEED}: parameters with zero truth kept: {res.names}"
    cfg = res.config
    for name, kind, m in dropped:
        if kind == "t":
            assert float(m.group(2)) < cfg.t_limit, f"seed {SEED}: {m.string}"
        else:
            assert float(m.group(4)) > cfg.corr_limit and name in (m.group(2), m.group(3)), m.string
            t = {m.group(6): float(m.group(7)), m.group(8): float(m.group(9))}
            assert t[name] == min(t.values()), f"seed {SEED}: the better determined one was dropped: {m.string}"
    # the first decision is taken on the full model: its numbers are the full adjustment's
    name, kind, m = dropped[0]
    i = full.names.index(name)
    if kind == "t":
        assert float(m.group(2)) == pytest.approx(full.t_values[i], abs=0.006)
    else:
        a, b = full.names.index(m.group(2)), full.names.index(m.group(3))
        assert float(m.group(4)) == pytest.approx(abs(full.correlation[a, b]), abs=6e-4)
    # what is left is significant and not near-singular
    t = dict(zip(res.names, res.t_values, strict=True))
    assert all(t[n] >= cfg.t_limit for n in res.names if n not in cfg.always_keep), f"seed {SEED}: {t}"
    c = np.abs(res.correlation - np.eye(len(res.names)))
    assert c.max() <= cfg.singular_corr, f"seed {SEED}: |correlation| {c.max():.3f} left among {res.names}"
    for a, b in zip(*np.nonzero(np.triu(c) > cfg.corr_limit), strict=True):  # correlated, but both determined
        assert min(t[res.names[a]], t[res.names[b]]) >= cfg.t_limit, f"seed {SEED}: {res.names[a]}, {res.names[b]}"


def test_near_singular_pair_drops_the_weaker_member_and_names_the_correlation(sim):
    radial = ("f", "cx", "cy", "k1", "k2", "k3")
    full = _run(sim, radial, adaptive=False)
    a, b = full.names.index("k2"), full.names.index("k3")
    r = abs(full.correlation[a, b])
    print(f"|corr(k2, k3)| = {r:.4f} on the full radial model; t(k2) = {full.t_values[a]:.2f}, "
          f"t(k3) = {full.t_values[b]:.2f}")
    assert r > 0.95, f"seed {SEED}: the radial terms are expected near-singular here, |corr| = {r:.3f}"
    res = _run(sim, radial, adaptive=True)
    for line in res.selection:
        print(line)
    dropped, _ = _parse(res.selection)
    name, kind, m = dropped[0]
    weaker = "k2" if full.t_values[a] < full.t_values[b] else "k3"
    assert kind == "corr" and name == weaker, f"seed {SEED}: first decision {m.string!r}, expected {weaker}"
    assert {m.group(2), m.group(3)} == {"k2", "k3"} and float(m.group(4)) == pytest.approx(r, abs=6e-4)
    assert "k1" in res.names and weaker not in res.names


def test_pair_of_kept_parameters_is_left_and_the_next_pair_decides():
    names = ["f", "cx", "k1", "k2"]
    corr = np.eye(4)
    corr[0, 1] = corr[1, 0] = 0.99  # f and cx: both always kept
    corr[2, 3] = corr[3, 2] = 0.97
    t = np.array([50.0, 40.0, 8.0, 1.5])
    name, why = choose_drop(names, corr, t, AdjustConfig())
    assert name == "k2" and "|corr(k1, k2)| = 0.970 > 0.95" in why and "t(k2) = 1.50" in why
    name, why = choose_drop(names[:2], corr[:2, :2], t[:2], AdjustConfig())
    assert name is None and why.startswith("kept f t=50.0, cx t=40.0")


def test_radial_terms_are_dropped_from_the_highest_order_down():
    cfg = AdjustConfig()
    names = ["f", "cx", "cy", "k1", "k2", "k3"]
    corr = np.eye(6)
    corr[4, 5] = corr[5, 4] = 0.985  # k2 and k3 nearly collinear in a narrow field
    t = np.array([30.0, 40.0, 40.0, 75.0, 0.95, 1.06])  # k2 the less significant of the pair
    name, why = choose_drop(names, corr, t, cfg)
    assert name == "k3" and "corr(k2, k3)" in why
    # no correlation: k2 is not dropped for insignificance while k3 is free, whatever their t values
    name, why = choose_drop(names, np.eye(6), np.array([30.0, 40.0, 40.0, 75.0, 0.5, 1.5]), cfg)
    assert name == "k3" and "t = 1.50" in why
    name, _ = choose_drop(names[:5], np.eye(5), np.array([30.0, 40.0, 40.0, 75.0, 0.5]), cfg)
    assert name == "k2"


@pytest.mark.parametrize("seed", [0, 3])
def test_sigmas_of_kept_parameters_are_marginal_over_the_dropped_ones(seed):
    """A dropped parameter is held exactly, and the kept ones' sigmas given its value are too small: on the
    narrow-field conte-calibration block (tie noise 0.15 px, a priori 0.5, the pipeline's selection) k2 (true
    0.12) or p1/p2 go, and k1, cx or cy then miss the truth by 4-11 of those sigmas. The result's sigmas are
    marginal over the dropped parameters (free again at the solution): every kept parameter is within 3 of
    them, the conditional ones are kept beside them, and a note says over which parameters."""
    import dataclasses

    import pyarrow as pa

    from aerocal.pipeline.config import ProcessConfig, effective_adjustments
    from aerocal.simulate.presets import PRESETS

    spec = PRESETS["conte-calibration"]
    spec = dataclasses.replace(spec, sensors=dataclasses.replace(spec.sensors, tie_sigma_px=0.15))
    sim = simulate_flight(spec, seed=seed)
    obs = sim.observations
    k = obs.schema.get_field_index("sigma")
    field = obs.schema.field("sigma")
    obs = obs.set_column(k, field, pa.array(np.full(obs.num_rows, 0.5), field.type))
    cfg = dataclasses.replace(effective_adjustments(ProcessConfig(), {}, matched=True).calibration, thermal=())
    res = adjust(sim.images, obs, sim.camera_nominal, cfg, sim.gcps, sim.gcp_observations)
    dropped_io = [n for n in res.dropped if n in PARAM_NAMES]
    assert dropped_io and set(res.conditional_sigmas) == set(res.names), f"seed {seed}: {res.dropped}"
    true, got = sim.spec.camera_true.params(), res.camera.params()
    z_marginal = {n: (got[PARAM_NAMES.index(n)] - true[PARAM_NAMES.index(n)]) / res.sigmas[n] for n in res.names}
    z_given = {n: (got[PARAM_NAMES.index(n)] - true[PARAM_NAMES.index(n)]) / res.conditional_sigmas[n]
               for n in res.names}
    assert max(abs(z) for z in z_marginal.values()) < 3.0, f"seed {seed}: {z_marginal}"
    assert max(abs(z) for z in z_given.values()) > 3.0, f"seed {seed}: the case shows nothing: {z_given}"
    assert all(res.sigmas[n] >= 0.999 * res.conditional_sigmas[n] for n in res.names), f"seed {seed}"
    assert np.allclose(np.sqrt(np.diag(res.covariance)), [res.sigmas[n] for n in res.names])
    assert res.marginal_note.startswith("sigmas marginal over"), f"seed {seed}: {res.marginal_note}"
    assert all(n in res.marginal_note for n in dropped_io), f"seed {seed}: {res.marginal_note}"
