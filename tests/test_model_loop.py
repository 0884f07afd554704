"""The loop in the product: an effect hidden in a simulated flight is found by the pipeline a user runs, applied to
the block and to the camera's certificate, and confirmed on data the fit did not use.

Every flight is processed by :func:`aerocal.pipeline.process` (what ``aerocal process`` runs, without the
platform's storage) with the camera the product would have: its own self-calibration, or a certificate made on
another simulated flight of the same camera. Never the truth: the simulated camera and effects are used only to
judge the answer. Each case asserts what a user checks in the run's summary: the effect found (by the
self-calibration, the recorded-EO check or the diagnosis), its size within 25 % along the truth, its gain on data the
fit did not use, and, where the diagnosis found it, the block adjusted again with it and nothing named again.

The flights fly in a wind, as real ones do (the real seneca flight: 5-8 m/s over the ground one way, 11-15 m/s the
other): at one ground speed a readout is an affinity and a lag a lever arm, which the diagnosis reports as groups it
cannot separate (tests/test_diagnose.py). Seeds are printed in every assertion.
"""

from __future__ import annotations

import dataclasses
import html
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from tolerance import assert_within_sigma

from aerocal.pipeline import ProcessConfig, RunSummary, process
from aerocal.pipeline.certificates import MemoryCertificates
from aerocal.pipeline.config import ReportStepConfig
from aerocal.pipeline.findings import Finding
from aerocal.simulate import PRESETS, simulate_flight
from aerocal.simulate.sensors import TemperatureCurve
from aerocal.simulate.simulator import as_dataset
from benchmarks.detection_rate_bench import with_strips

WIND = (9.0, 4.0)  # m/s east, north: ground speeds 51-69 m/s at the presets' 60 m/s airspeed


def conte(warming: bool = True):
    """conte-calibration in a wind, the camera warming from 10 to ~23 degC (thermal effects observable)."""
    return PRESETS["conte-calibration"].flown(
        WIND, TemperatureCurve(start_c=10.0, equilibrium_c=30.0, tau_s=400.0) if warming else None)


def mitishita():
    return PRESETS["mitishita-block"]


def refraction_block():
    """The UltraCam block with dense, precise tie points and 20 GCPs: refraction is 0.36 px at its corners."""
    m = PRESETS["mitishita-block"]
    return m.replace(n_gcp=20, n_check=10, points_per_image=1000, sensors=dataclasses.replace(m.sensors,
                                                                                              tie_sigma_px=0.3))


#: what these tests judge is the loop (the diagnosis, the extension, the certificates), not the report: its
#: figures, most of a small flight's report time, are not drawn (their captions and numbers are)
CONFIG = ProcessConfig(report=ReportStepConfig(figures=False))


def run(spec, seed: int, effects: dict, store: MemoryCertificates | None = None, max_images: int | None = None,
        name: str | None = None):
    sim = simulate_flight(spec, seed=seed, effects=effects, max_images=max_images)
    store = store if store is not None else MemoryCertificates()
    return process(as_dataset(sim, name=name), CONFIG, certificates=store), store


def found(summary: RunSummary, name: str) -> Finding | None:
    return summary.finding(name)


def along(estimate, truth) -> float:
    """The relative error of ``estimate`` along the direction of ``truth``."""
    truth = np.asarray(truth, dtype=float)
    u = truth / np.linalg.norm(truth)
    return abs(float(np.asarray(estimate, dtype=float) @ u) - np.linalg.norm(truth)) / np.linalg.norm(truth)


def daakir():
    return PRESETS["daakir-uav"]


#: (effect, magnitude, flight, seed, who finds it, max images); each found with the product's own calibration. A
#: focal drift of 0.15 px/degC over the 13 degC of the warming block (2 px of f) is at the limit of the held-out
#: tests' power there: kept by the calibration on one seed, a signal without held-out gain on another; 0.3 px/degC
#: (0.018 % of f per degC, a non-athermalised germanium lens's) is not
SELF_CALIBRATED = [
    ("rolling_shutter", (0.006,), conte, 301, "diagnosis", None),
    ("affinity_skew", (-3.0, 1.0), conte, 302, "diagnosis", None),
    ("thermal_principal_point", (0.08, -0.06), conte, 303, "diagnosis", None),
    ("thermal_rotation", (0.05,), conte, 304, "diagnosis", None),
    ("thermal_focal", (0.3,), conte, 305, "self-calibration", None),
    ("gnss_time_offset", (0.05,), conte, 306, "recorded-EO check", None),
    ("gnss_bias", (0.4, -0.3, 0.0), conte, 307, "recorded-EO check", None),
    ("lever_arm", (-0.05, 0.0, 0.0), daakir, 309, "diagnosis", 40),
]

#: (effect, magnitude, flight, seed, who finds it); found on a flight that uses the certificate an effect-free
#: flight of the same camera made (seed + 100): what a self-calibration on the same images would absorb (a boresight
#: about the camera's x and y axes is a principal point offset; refraction at one flying height is f and k1)
WITH_CERTIFICATE = [
    ("boresight", (0.03, -0.025, 0.0), lambda: conte(warming=False), 308, "recorded-EO check"),
    ("refraction", "on", refraction_block, 311, "diagnosis"),
]


def _check_found(fr, store, name, value, by, seed) -> None:
    s = fr.summary
    f = found(s, name)
    assert f is not None, f"seed {seed}: hid {name}={value}; found {s.findings}; diagnosis {s.diagnosis}"
    assert f.found_by.startswith(by), f"seed {seed}: {f}"  # with "and diagnosis": the rest found afterwards
    err = along(f.values, value)
    assert err < 0.25, f"seed {seed}: hid {name}={value}, found {f.values} +- {f.sigmas} ({err:.0%} off)"
    assert "gain +" in f.evidence or f.found_by == "self-calibration", f"seed {seed}: {f}"
    if by == "diagnosis":
        # the block was adjusted again with it, and its diagnosis does not name it again
        ext = s.model_extension
        assert name in [t["name"] for t in ext["terms"]], f"seed {seed}: {ext}"
        assert name not in (s.diagnosis_after_extension or ""), f"seed {seed}: {s.diagnosis_after_extension}"
        assert "adjust_extended" in s.steps and s.steps["adjust_extended"].status == "computed"
        if name in ("rolling_shutter", "affinity_skew", "thermal_principal_point", "thermal_rotation", "radial_k3"):
            # a camera term: the camera's next certificate carries it, with the flight that found it
            cert = fr.json("certificate")
            assert name in (cert.get("effects") or {}), f"seed {seed}: {cert.get('effects')}"
            assert store.documents[-1]["id"] == cert["id"] and cert["version"] == len(store.documents)


@pytest.mark.parametrize("name,value,flight,seed,by,max_images", SELF_CALIBRATED,
                         ids=[c[0] for c in SELF_CALIBRATED])
def test_a_hidden_effect_is_found_applied_and_predicts_held_out_data(name, value, flight, seed, by, max_images):
    fr, store = run(flight(), seed, {name: value}, max_images=max_images)
    _check_found(fr, store, name, value, by, seed)


@pytest.mark.parametrize("name,value,flight,seed,by", WITH_CERTIFICATE, ids=[c[0] for c in WITH_CERTIFICATE])
def test_an_effect_a_self_calibration_absorbs_is_found_with_a_certificate_from_another_flight(name, value, flight,
                                                                                              seed, by):
    _, store = run(flight(), seed + 100, {}, name="calibration flight")
    fr, store = run(flight(), seed, {name: value}, store, name="survey")
    assert fr.summary.certificate_id == store.documents[0]["id"] or "extended" in fr.summary.certificate_reason
    notes = " ".join(fr.summary.recorded_eo_corrections)
    if name == "boresight" and "not told apart" in notes:
        # a tilt about the camera's x axis (across the track) moves the image as a GNSS lag moves the camera along
        # it; where the block fits both alike, what both readings agree on is removed and nothing else
        f = found(fr.summary, name)
        assert f is not None and f.values[0] == 0.0, f"seed {seed}: {f}; {notes}"
        assert abs(f.values[1] - value[1]) < 0.25 * abs(value[1]), f"seed {seed}: {f}"
        assert not found(fr.summary, "gnss_time_offset"), f"seed {seed}: {fr.summary.findings}"
        return
    _check_found(fr, store, name, (1.0,) if value == "on" else value, by, seed)


def test_a_third_radial_term_is_held_by_the_self_calibrations_lens_model():
    """A radial term in r^6 (k3 = 20, 1.5 px at the image corner) is part of the Brown model the camera is
    calibrated with. On this block k3 and k2 correlate beyond 0.95, so the self-calibration keeps k1 and k2 and
    drops k3 (and says so); the lens profile it certifies is the true one within 25 % of the r^6 term over the
    whole image, and the diagnosis has nothing left to name."""
    seed = 310
    spec = conte(warming=False)
    fr, _ = run(spec, seed, {"radial_k3": (20.0,)})
    cert = fr.json("certificate")
    p, t = cert["model"]["params"], spec.camera_true
    r = np.linspace(0.0, np.hypot(t.width / 2, t.height / 2) / t.f, 50)  # normalised radius to the corner

    def radial_px(f, k1, k2, k3):
        return f * r * (k1 * r**2 + k2 * r**4 + k3 * r**6)

    truth = radial_px(t.f, t.k1, t.k2, t.k3 + 20.0)
    term = np.abs(radial_px(t.f, 0.0, 0.0, 20.0)).max()
    miss = np.abs(radial_px(p["f"], p["k1"], p["k2"], p.get("k3", 0.0)) - truth).max()
    assert miss < 0.25 * term, f"seed {seed}: the certified profile misses the true one by {miss:.2f} px " \
                               f"(the k3 term: {term:.2f} px); {p}"
    if "k3" not in cert["estimated"]:
        assert "corr(k2, k3)" in (cert["significance"]["k3"]["dropped"] or ""), cert["significance"]["k3"]
    assert not fr.summary.findings, f"seed {seed}: {fr.summary.findings}"


def test_a_camera_term_from_one_flight_is_applied_on_the_next_which_names_nothing_for_it():
    """The readout found on a first flight goes into the camera's certificate; a second flight of the camera uses
    it, corrects its measurements for it and its diagnosis names nothing for it. Without the readout the second
    flight's own diagnosis would (the first flight shows that it can)."""
    seed = 311
    first, store = run(conte(warming=False), seed, {"rolling_shutter": (0.010,)}, name="first")
    assert found(first.summary, "rolling_shutter"), f"seed {seed}: {first.summary.diagnosis}"
    second, _ = run(conte(warming=False), seed + 1, {"rolling_shutter": (0.010,)}, store, name="second")
    s = second.summary
    assert s.certificate_id == store.documents[-1]["id"], f"seed {seed}: {s.certificate_reason}"
    assert second.json("adjustment")["camera_terms"], "the readout of the certificate is applied"
    assert not s.findings, f"seed {seed + 1}: found {s.findings} with the readout applied"
    rs = next(h for h in second.json("diagnosis")["hypotheses"] if h["name"] == "rolling_shutter" and h["round"] == 1)
    assert_within_sigma(rs["estimate"][0], rs["sigma"][0], 3, 0.002, f"seed {seed + 1}: residual readout (s)")


@pytest.mark.parametrize("seed", range(320, 328))
def test_an_effect_free_flight_names_nothing_and_is_not_extended(seed):
    fr, store = run(conte(warming=seed % 2 == 0), seed, {})
    s = fr.summary
    assert not s.findings, f"seed {seed}: found {s.findings} on an effect-free flight"
    assert s.model_extension is None and len(store.documents) == 1, f"seed {seed}: {s.diagnosis}"


def test_a_recorded_yaw_offset_is_found_within_half_a_degree_and_removed():
    """The recorded attitudes turned by 4 deg about the camera axis (a gimbal's yaw recorded for the camera's): the
    block observes them, so the offset is measured against the orientation the images and the recorded positions
    give without them, removed from the records before the adjustment, and the diagnosis finds nothing left. (On a
    small drone block with consumer GNSS the same check knows the yaw to about a degree only: the rendered XT2
    survey's 160 m block, 1.5 m GNSS, 4.45 +- 1.0 deg.)"""
    seed = 331
    fr, _ = run(conte(warming=False), seed, {"boresight": (0.0, 0.0, 4.0)})
    f = found(fr.summary, "boresight")
    assert f is not None and f.found_by == "recorded-EO check", f"seed {seed}: {fr.summary.findings}"
    assert abs(f.values[2] - 4.0) < 0.5 and abs(f.values[0]) < 0.5 and abs(f.values[1]) < 0.5, f
    check = fr.json("diagnosis")["recorded_eo"]["attitude_offset"]
    assert check["status"] == "consistent with the adjusted attitudes", f"seed {seed}: {check}"


def test_a_gnss_offset_too_few_control_points_test_is_measured_on_the_check_points():
    """mitishita-block has one control point and 29 check points: the offset of the block against its check points
    is measured by leave-one-out and reported, not applied (the check points stay independent)."""
    seed = 332
    fr, _ = run(mitishita(), seed, {"gnss_bias": (0.4, -0.3, 0.0)})
    d = fr.json("diagnosis_before_extension") if "diagnosis_before_extension" in fr.outputs else fr.json("diagnosis")
    check = d["recorded_eo"]["gnss_bias_check_points"]
    assert check["n_check_points"] >= 20, f"seed {seed}: {check}"
    # the single control point holds the block back against most of the offset; what is left shows on the check
    # points, in the offset's direction, with a gain on each check point predicted from the others
    assert "an offset of the block" in check["status"] and "not applied" in check["status"], f"seed {seed}: {check}"
    assert np.sign(check["estimate"][0]) == 1 and np.sign(check["estimate"][1]) == -1, f"seed {seed}: {check}"


def test_a_readout_is_told_from_an_affinity_where_ingest_left_a_strips_first_frame_out():
    """A DJI XT2 survey in a wind (2.5, 1) m/s: the aircraft crabs, 7.4 m/s over the ground one way and 2.4 the other;
    a 30 ms readout, no ground control, consumer GNSS. From noisy GNSS, ingest leaves the first frame of a strip out of
    it (strip -1, as it did on a rendered survey of this camera). That frame's pixels still carry the readout's 2.8 px
    shear, so its signature must still be modelled: with none, an affinity explained the block better and was named
    (-1.41, 3.53 px, told apart from the readout), and the readout left after it was 3.3 ms."""
    seed = 340
    sim = simulate_flight(PRESETS["xt2-survey"].flown((2.5, 1.0)), seed=seed, effects={"rolling_shutter": (0.030,)})
    strip = sim.images.column("strip").to_numpy().copy()
    firsts = np.flatnonzero(np.r_[True, strip[1:] != strip[:-1]] & (strip >= 0))
    strip[firsts] = -1
    images = sim.images.set_column(sim.images.schema.get_field_index("strip"), "strip", pa.array(strip, pa.int32()))
    sim = dataclasses.replace(sim, images=images)
    fr = process(as_dataset(sim), CONFIG, certificates=MemoryCertificates())
    s = fr.summary
    f = found(s, "rolling_shutter")
    assert f is not None, f"seed {seed}: found {s.findings}; diagnosis {s.diagnosis}"
    assert abs(f.values[0] - 0.030) < 0.25 * 0.030, f"seed {seed}: {f}"
    assert not found(s, "affinity_skew"), f"seed {seed}: {s.findings}"


@pytest.mark.parametrize("seed,lag,warming,max_images", [(508, 0.3, False, 16), (956, 0.05, True, None)])
def test_a_lags_remainder_is_removed_with_it_and_not_named_a_boresight(seed, lag, warming, max_images):
    """A lag's first estimate leaves a few percent of it in the records, which tilts the cameras about their x axis
    as a boresight of a few hundredths of a degree would. That remainder is refined away or, where a tilt within
    the lag's sigma stands for it, removed with the lag from the positions, never named a boresight: seed 508 (a
    0.3 s lag, 18 m along the track) named a 0.067 deg boresight beside a lag of 0.272 s; seed 956 (0.05 s), with the
    tilt held back and not removed as lag, lost the comparison of the two orders to a 0.22 deg boresight and a GNSS
    offset that nothing hid."""
    fr, _ = run(conte(warming=warming), seed, {"gnss_time_offset": (lag,)}, max_images=max_images)
    f = found(fr.summary, "gnss_time_offset")
    assert f is not None and abs(f.values[0] - lag) < 0.25 * lag, f"seed {seed}: {fr.summary.findings}"
    assert [g.name for g in fr.summary.findings] == ["gnss_time_offset"], f"seed {seed}: {fr.summary.findings}"


def test_a_lag_and_a_real_boresight_are_both_found():
    """The rule above must not take a real mounting tilt for a lag's remainder: a 0.3 s lag and a boresight of
    (0.2, -0.1, 0) deg (3 m along the track at 850 m, ten times the lag's sigma in time), on a flight that uses the
    certificate an effect-free flight of the camera made (a self-calibration would take the tilt for cx, cy)."""
    seed = 601
    _, store = run(conte(warming=False), seed + 100, {}, max_images=16, name="calibration flight")
    fr, _ = run(conte(warming=False), seed, {"gnss_time_offset": (0.3,), "boresight": (0.2, -0.1, 0.0)}, store,
                max_images=16, name="survey")
    lag, bore = found(fr.summary, "gnss_time_offset"), found(fr.summary, "boresight")
    assert lag is not None and abs(lag.values[0] - 0.3) < 0.25 * 0.3, f"seed {seed}: {fr.summary.findings}"
    assert bore is not None and along(bore.values, (0.2, -0.1, 0.0)) < 0.25, f"seed {seed}: {fr.summary.findings}"


def test_a_thermal_rotations_zero_point_is_reported_with_it_not_as_a_boresight():
    """A thermal rotation of 0.05 px/degC on a camera warming 10 -> 23 degC: the simulated frames are unturned at
    20 degC, the block's model at its mean temperature, so the frames' turn there (-0.02 deg) is a constant rotation
    about the optical axis that the recorded attitudes see as a boresight about z. One flight cannot tell it from a
    yaw mounting offset: it stays applied, and is reported as the rotation's zero point, not as a second effect."""
    seed = 904
    fr, _ = run(conte(), seed, {"thermal_rotation": (0.05,)})
    s = fr.summary
    f = found(s, "thermal_rotation")
    assert f is not None and along(f.values, (0.05,)) < 0.25, f"seed {seed}: {s.findings}"
    assert [g.name for g in s.findings] == ["thermal_rotation"], f"seed {seed}: {s.findings}"
    if "about the optical axis" in f.applied:  # the turn was large enough to be named on this seed
        assert "boresight 0, 0" not in (s.diagnosis or "") and "zero point" in (s.diagnosis or ""), s.diagnosis
        terms = [t["name"] for t in s.model_extension["terms"]]
        assert "boresight" in terms, f"seed {seed}: the turn is applied to the block: {terms}"


def test_the_zero_point_rule_leaves_a_tilted_boresight_and_a_lone_one_alone():
    """A boresight with a component about x or y beyond two sigmas is a boresight, and so is one found without a
    thermal rotation."""
    from aerocal.effects import rotation_zero_point

    assert rotation_zero_point({"thermal_rotation", "boresight"}, (0.0, 0.0, -0.02), (0.05, 0.05, 0.003))
    assert rotation_zero_point({"thermal_rotation"}, (0.01, 0.0, -0.02), (0.05, None, 0.003))
    assert not rotation_zero_point({"thermal_rotation"}, (0.2, 0.0, -0.02), (0.05, 0.05, 0.003))
    assert not rotation_zero_point({"boresight"}, (0.0, 0.0, 4.0), (0.05, 0.05, 0.01))
    assert not rotation_zero_point({"thermal_rotation"}, (0.0, 0.0, 0.0), (0.05, 0.05, 0.01))


def test_refraction_is_never_named_as_a_third_radial_term():
    """Refraction (0.36 px at the corners of the UltraCam's frame) on a flight that uses the certificate of an
    effect-free flight at the same height: on this seed a third radial term explained the residuals a little better
    (statistic 38.1 against 30.2, neither remaining significant given the other) and was named and written into
    the certificate. Now the two are tested given each other, reported as a pair, and neither is applied."""
    seed = 982
    _, store = run(refraction_block(), seed + 100, {}, name="calibration flight")
    fr, store = run(refraction_block(), seed, {"refraction": "on"}, store, name="survey")
    s = fr.summary
    assert not found(s, "radial_k3"), f"seed {seed}: {s.findings}"
    f = found(s, "refraction")
    assert f is not None or "refraction" in (s.diagnosis or ""), f"seed {seed}: {s.findings}; {s.diagnosis}"
    if f is not None:
        assert along(f.values, (1.0,)) < 0.25, f"seed {seed}: {f}"
    assert len(store.documents) == 1 or "radial_k3" not in (fr.json("certificate").get("effects") or {})


def test_a_look_alike_too_small_to_name_is_still_a_rival(monkeypatch):
    """A significant hypothesis whose size is under the floor of what can be named (``MATERIAL_SHIFT_PX``) still
    explains the signal it shares with a look-alike: the two are not told apart, and the larger is never named alone.
    Found on the second rendered XT2 flight reusing a certificate whose readout was 2 % low: the readout's remainder
    (0.98 ms, 0.048 px) was dropped before the contest and the affinity that mimics it (0.125 px) was named.

    Here on observations: a 6 ms readout on an XT2 block whose camera turns with the aircraft (the readout and an
    affinity alike), with the certificate of an effect-free flight of the camera; the floor is put between the
    sizes the two hypotheses have on the block, so that the smaller one is too small to name."""
    from aerocal.diagnose import engine

    spec = with_strips(PRESETS["xt2-survey"].flown((2.5, 1.0)), 6)
    seed = 701
    _, store = run(spec, seed - 1, {})
    fr, _ = run(spec, seed, {"rolling_shutter": (0.006,)}, store=store)
    shift = {h["name"]: h["shift_px"] for h in fr.json("diagnosis")["hypotheses"]
             if h["name"] in ("rolling_shutter", "affinity_skew")}
    assert not fr.summary.findings and len(shift) == 2, f"seed {seed}: {fr.summary.diagnosis}; {shift}"
    monkeypatch.setattr(engine, "MATERIAL_SHIFT_PX", float(np.mean(list(shift.values()))))
    fr, _ = run(spec, seed, {"rolling_shutter": (0.006,)}, store=store)
    s = fr.summary
    pairs = [set(p["effects"]) for p in fr.json("diagnosis")["pairs"]]
    assert not s.findings and {"rolling_shutter", "affinity_skew"} in pairs, (
        f"seed {seed}: sizes {shift}, floor {engine.MATERIAL_SHIFT_PX:.3f} px; found {s.findings}; {s.diagnosis}")


def test_a_certificates_readout_is_checked_by_every_flight_that_applies_it():
    """A readout a flight wrote into the camera's certificate is applied by later flights, and each says whether it
    holds there: the remainder its diagnosis finds of the readout (named or not), against the certificate's sigma
    and its own. A later flight whose camera reads out as the certificate says: it holds; one whose readout is half
    as long again: it does not, by many sigmas (and the new remainder, named, is not compared with the whole
    readout as if it were another flight's value)."""
    seed = 1311
    first, store = run(conte(), seed, {"rolling_shutter": (0.006,)})
    assert found(first.summary, "rolling_shutter") is not None, f"seed {seed}: {first.summary.diagnosis}"
    for k, readout, verdict in ((1, 0.006, "holds on this flight"), (2, 0.009, "does not hold on this flight")):
        later, _ = run(conte(), seed + k, {"rolling_shutter": (readout,)}, store=store)
        s = later.summary
        lines = [x for x in s.certificate_terms if x.startswith("rolling_shutter of certificate")]
        assert len(lines) == 1 and verdict in lines[0], (
            f"seeds {seed}, {seed + k}: readout {readout} s; {s.certificate_terms}; {s.diagnosis}")
        agreement = (s.model_extension or {}).get("agreement") or []
        assert not any(x.startswith("rolling_shutter") for x in agreement), agreement
        # the report says it too, in its calibration section and its summary.json
        files = later.runner.inputs({"r": later.outputs["report"], "s": later.outputs["report_summary"]})
        summary_json = json.loads(Path(files.path("s")).read_text())
        assert summary_json["summary"]["certificate_terms"] == list(s.certificate_terms)
        page = Path(files.path("r")).read_text()
        assert "camera terms on this flight" in page and html.escape(lines[0], quote=False) in page
