"""Calibration certificates: JSON document shape, lossless round trip, content hash, strict validation."""

from __future__ import annotations

import copy
import dataclasses
import datetime as dt
import hashlib
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from aerocal.camera import (
    Camera,
    LinearThermalModel,
    PolynomialThermalModel,
    SimilarityThermalModel,
)
from aerocal.certificates.document import (
    SCHEMA,
    CameraIdentity,
    Certificate,
    CertificateError,
    Conditions,
    Correlation,
    ParameterSignificance,
    Provenance,
    Quality,
    ThermalCalibration,
    sigmas_and_correlation,
)

ESTIMATED = ("f", "cx", "cy", "k1", "k2", "p1", "p2", "b1")


def make_certificate(thermal: ThermalCalibration | None = None, **overrides) -> Certificate:
    """A fully populated certificate of a 640x512 thermal camera (values as a self-calibration gives)."""
    camera = Camera(width=640, height=512, f=1711.7647, cx=322.41, cy=254.87, k1=-0.2, k2=0.05, k3=0.0,
                    p1=1e-4, p2=-2e-4, b1=0.8, b2=0.0, pixel_size_mm=0.017)
    sig = np.array([0.42, 0.31, 0.29, 1.1e-3, 4e-3, 2e-5, 3e-5, 0.05])
    corr = np.eye(len(sig))  # disjoint pairs: positive definite
    corr[0, 3] = corr[3, 0] = 0.93  # f and k1 strongly correlated
    corr[1, 5] = corr[5, 1] = 0.61  # cx and p1
    corr[2, 6] = corr[6, 2] = -0.47  # cy and p2
    corr[4, 7] = corr[7, 4] = -0.12  # k2 and b1
    cov = corr * np.outer(sig, sig)
    sigmas, correlation = sigmas_and_correlation(ESTIMATED, cov)
    if thermal is None:
        thermal = ThermalCalibration(
            LinearThermalModel(t0=25.0, df_dt=0.29, dcx_dt=0.011, dcy_dt=-0.02, valid_range=(8.0, 41.5)),
            sigmas={"df_dt": 0.012, "dcx_dt": 0.004, "dcy_dt": 0.004},
        )
    values = [getattr(camera, n) for n in ESTIMATED]
    significance = {n: ParameterSignificance(t=float(v / s), significant=abs(v / s) > 1.96)
                    for n, v, s in zip(ESTIMATED, values, sig, strict=True)}
    significance["k3"] = ParameterSignificance(t=0.7, significant=False, dropped="|t| 0.7 < 1.96 at 95 %")
    significance["b2"] = ParameterSignificance(t=1.2, significant=False, dropped="|t| 1.2 < 1.96 at 95 %")
    kwargs = dict(
        identity=CameraIdentity("FLIR", "Vue Pro R 640", "SN-47110", "13 mm"),
        camera=camera,
        sigmas=sigmas,
        estimated=ESTIMATED,
        correlation=correlation,
        significance=significance,
        thermal=thermal,
        conditions=Conditions(
            date="2017-03-14", temperature_range=(9.5, 40.0), n_images=4, strips=5, transversal_strip=True,
            n_gcp=3, priors={"gnss_position_m": 0.05, "imu_attitude_deg": 0.02},
            images=("IMG_0001.tif", "IMG_0002.tif", "IMG_0107.tif", "IMG_0108.tif"),
        ),
        quality=Quality(sigma0=1.04, reprojection_rms_px=0.287, dof=18211),
        provenance=Provenance(flow_run="8f9d3e4c-run", code_version="0.1.0",
                              inputs={"images": hashlib.sha256(b"images").hexdigest(),
                                      "observations": hashlib.sha256(b"observations").hexdigest()}),
    )
    kwargs.update(overrides)
    return Certificate(**kwargs)


THERMAL_VARIANTS = {
    "linear": None,
    "similarity": ThermalCalibration(
        SimilarityThermalModel(temperatures=(10.0, 20.0, 30.0), tx=(0.1, 0.0, -0.1), ty=(0.0, 0.0, 0.2),
                               scale=(1.0002, 1.0, 0.9998), theta=(1e-5, 0.0, -1e-5), centre=(320.0, 256.0)),
        sigmas={"tx": 0.01}),
    "polynomial": ThermalCalibration(
        PolynomialThermalModel(t0=20.0, centre=(320.0, 256.0), norm=320.0, degree=1,
                               coefficients=tuple(tuple(tuple(tuple(0.001 * (a + k + i + j) for j in range(2))
                                                                for i in range(2)) for k in range(3))
                                                  for a in range(2))),
        sigmas={}, valid_range=(5.0, 35.0)),
    "none": "none",
}


def _variant(name: str) -> Certificate:
    th = THERMAL_VARIANTS[name]
    if th is None:
        return make_certificate()
    if th == "none":
        return dataclasses.replace(make_certificate(), thermal=None)
    return make_certificate(thermal=th)


# ----------------------------------------------------------------------------- document shape
def test_document_has_the_fixed_shape_the_store_indexes():
    doc = make_certificate().to_dict()
    assert list(doc) == ["schema", "id", "camera", "version", "supersedes", "issued", "model", "sigmas",
                         "estimated", "correlation", "significance", "thermal", "conditions", "quality",
                         "provenance"]
    assert doc["schema"] == SCHEMA == "aerocal.certificate/1"
    assert len(doc["id"]) == 32 and int(doc["id"], 16) >= 0
    assert doc["camera"] == {"make": "FLIR", "model": "Vue Pro R 640", "serial": "SN-47110", "lens": "13 mm"}
    assert doc["version"] is None and doc["supersedes"] is None
    assert doc["issued"].endswith("Z")
    assert dt.datetime.fromisoformat(doc["issued"]).utcoffset() == dt.timedelta(0)
    assert set(doc["model"]) == {"kind", "width", "height", "pixel_size_mm", "params"}
    assert list(doc["model"]["params"]) == ["f", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "b1", "b2"]
    assert set(doc["significance"]["k3"]) == {"t", "significant", "dropped"}
    assert doc["thermal"]["kind"] == "linear" and doc["thermal"]["valid_range"] == [8.0, 41.5]
    assert doc["thermal"]["sigmas"]["df_dt"] == 0.012
    assert set(doc["conditions"]) == {"date", "temperature_range", "n_images", "strips", "transversal_strip",
                                      "n_gcp", "priors", "images"}
    assert set(doc["quality"]) == {"sigma0", "reprojection_rms_px", "dof"}
    assert set(doc["provenance"]) == {"flow_run", "code_version", "inputs"}
    json.dumps(doc, allow_nan=False)  # plain, strict JSON


def test_sigmas_and_correlation_recover_the_covariance():
    cert = make_certificate()
    names = cert.correlation.names
    sig = np.array([cert.sigmas[n] for n in names])
    np.testing.assert_allclose(sig, [0.42, 0.31, 0.29, 1.1e-3, 4e-3, 2e-5, 3e-5, 0.05], rtol=1e-12)
    assert cert.correlation.value("f", "k1") == pytest.approx(0.93, abs=1e-12)
    m = cert.correlation.array()
    np.testing.assert_allclose(m, m.T, atol=0)
    np.testing.assert_allclose(np.diag(m), 1.0, atol=0)


# ----------------------------------------------------------------------------- round trip and hash
@pytest.mark.parametrize("variant", list(THERMAL_VARIANTS))
def test_json_round_trip_preserves_everything_and_the_content_hash(variant):
    cert = _variant(variant)
    back = Certificate.from_json(cert.to_json())
    assert back == cert
    assert back.to_dict() == cert.to_dict()
    assert back.content_hash() == cert.content_hash()
    assert back.id == cert.id and back.issued == cert.issued
    if cert.thermal is not None:
        assert back.thermal.model == cert.thermal.model
        assert back.thermal.valid_range == cert.thermal.valid_range
    # and through pickle (certificates cross process boundaries on a Dask cluster)
    assert pickle.loads(pickle.dumps(back)) == cert
    assert hash(back) == hash(cert)


#: documents written by aerocal before the certificate schema (commit 8244184, the hand-written validator):
#: self-calibrations with each thermal model kind, a rejected review with held-out gains, a nominal camera with
#: a serial-less identity, and imports from the four foreign formats, each with its content hash of then
WRITTEN_BEFORE = Path(__file__).with_name("certificate_documents_8244184.json")


@pytest.mark.parametrize("entry", json.loads(WRITTEN_BEFORE.read_text())["documents"], ids=lambda e: e["name"])
def test_documents_written_before_the_schema_load_unchanged(entry):
    doc = entry["document"]
    cert = Certificate.from_dict(doc)
    assert cert.to_dict() == doc
    assert cert.content_hash() == entry["content_hash"]
    assert Certificate(**{f.name: getattr(cert, f.name) for f in dataclasses.fields(cert)}) == cert


def test_calibration_date_is_the_data_s_date_else_the_issue_date():
    cert = make_certificate()
    assert cert.calibration_date == dt.date(2017, 3, 14)
    undated = dataclasses.replace(cert, conditions=Conditions(),
                                  issued=dt.datetime(2024, 5, 17, 23, 30, tzinfo=dt.timezone(dt.timedelta(hours=-2))))
    assert undated.calibration_date == dt.date(2024, 5, 18)  # the UTC date


def test_content_hash_ignores_issue_identity_but_not_content():
    cert = make_certificate()
    h = cert.content_hash()
    assert len(h) == 64
    again = dataclasses.replace(cert, id="0" * 32, issued=dt.datetime(2030, 1, 1, tzinfo=dt.UTC))
    assert again.content_hash() == h
    assert cert.with_version(3, "a" * 32).content_hash() == h
    changed = dataclasses.replace(cert, camera=cert.camera.replace(k1=cert.camera.k1 + 1e-12))
    assert changed.content_hash() != h
    # a document whose float fields are written as integers hashes the same (canonical numbers)
    doc = cert.to_dict()
    doc["model"]["params"]["b2"] = 0
    assert Certificate.from_dict(doc).content_hash() == h


def test_with_version_returns_a_new_numbered_certificate():
    cert = make_certificate()
    v2 = cert.with_version(2, "b" * 32)
    assert (v2.version, v2.supersedes) == (2, "b" * 32)
    assert (cert.version, cert.supersedes) == (None, None)
    assert v2.id == cert.id and v2.camera == cert.camera
    assert Certificate.from_json(v2.to_json()) == v2


def test_certificate_is_immutable():
    cert = make_certificate()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cert.version = 4  # type: ignore[misc]
    with pytest.raises(TypeError, match="immutable"):
        cert.sigmas["f"] = 0.0  # type: ignore[index]
    with pytest.raises(TypeError, match="immutable"):
        cert.conditions.priors.update({"x": 1.0})  # type: ignore[attr-defined]
    assert isinstance(cert.conditions.images, tuple) and isinstance(cert.estimated, tuple)


# ----------------------------------------------------------------------------- validation
def _mutate(path: str, value):
    """A document with the value at a dotted ``path`` replaced (``...`` deletes the key)."""
    doc = copy.deepcopy(make_certificate().to_dict())
    *parents, last = path.split(".")
    node = doc
    for p in parents:
        node = node[int(p)] if isinstance(node, list) else node[p]
    if value is ...:
        del node[last]
    elif isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return doc


MALFORMED = [
    ("model.params.f", "abc", 'model.params.f: expected a positive number, got "abc"'),
    ("model.params.f", -3.0, "model.params.f: expected a positive number, got -3.0"),
    ("model.width", 640.5, "model.width: expected an integer >= 1, got 640.5"),
    ("model.kind", "fisheye", 'model.kind: expected "brown"'),
    ("schema", "aerocal.certificate/2", 'schema: expected "aerocal.certificate/1"'),
    ("id", "not-a-uuid", "id: expected 32 lowercase hex digits"),
    ("camera.serial", 12345, "camera.serial: expected a non-empty string, got 12345"),
    ("issued", "2024-05-17T09:30:00", "issued: expected a UTC time (Z suffix)"),
    ("version", 0, "version: expected an integer >= 1 or null, got 0"),
    ("model.params.k3", 1e6, "model.params.k3: expected a coefficient that alone moves the farthest image corner "
     "by at most 1 x its radius (|k3| <= 5.11e+03 for this camera), got 1000000.0"),
    ("model.params.p1", 2.0, "model.params.p1: expected a coefficient that alone moves the farthest image corner "
     "by at most 1 x its radius (|p1| <= 1.38 for this camera)"),
    ("sigmas.q1", 0.1, "sigmas.q1: unknown name"),
    ("sigmas.k3", 0.1, "sigmas.k3: k3 has a sigma but is not in estimated"),
    ("sigmas.f", -0.1, "sigmas.f: expected a non-negative number, got -0.1"),
    ("estimated.0", "focal", "estimated[0]: expected one of f, cx"),
    ("correlation.matrix.0.1", 0.5, "correlation.matrix[0][1]: expected the same value as [1][0]"),
    ("correlation.matrix.1.1", 0.9, "correlation.matrix[1][1]: expected 1 on the diagonal"),
    ("significance.f.dropped", "weak",
     "significance.f.dropped: f is marked dropped but is listed in estimated"),
    ("significance.k3.significant", "no", 'significance.k3.significant: expected true or false, got "no"'),
    ("thermal.kind", "cubic", 'thermal.kind: expected "linear", "similarity" or "polynomial", got "cubic"'),
    ("thermal.valid_range", [40.0, 10.0], "thermal.valid_range: expected [lo, hi] with lo <= hi"),
    ("thermal.sigmas.dk1_dt", 0.1, "thermal.sigmas.dk1_dt: unknown name"),
    ("conditions.date", "2017-13-40", 'conditions.date: expected a date "YYYY-MM-DD" or null'),
    ("conditions.n_images", 5, "conditions.n_images: expected 4 (the number of names in conditions.images)"),
    ("conditions.n_gcp", ..., "conditions.n_gcp: missing"),
    ("conditions.transversal_strip", 1,
     "conditions.transversal_strip: expected true or false or null, got 1"),
    ("conditions.priors.gnss_position_m", 0, "conditions.priors.gnss_position_m: expected a positive number"),
    ("quality.dof", -1, "quality.dof: expected an integer >= 0 or null, got -1"),
    ("provenance.inputs.images", "abc", "provenance.inputs.images: expected a sha256 as 64 lowercase hex"),
    ("colour", "blue", "colour: unknown field"),
]


@pytest.mark.parametrize(("path", "value", "message"), MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_document_names_the_field_and_the_fix(path, value, message):
    with pytest.raises(CertificateError) as info:
        Certificate.from_dict(_mutate(path, value))
    text = str(info.value)
    assert text.startswith(message), text
    assert "; " in text and "\n" not in text  # one line: problem; fix


def test_error_message_for_a_bad_focal_length_reads_as_documented():
    with pytest.raises(CertificateError) as info:
        Certificate.from_dict(_mutate("model.params.f", "abc"))
    assert str(info.value) == ('model.params.f: expected a positive number, got "abc"; '
                               "write f as a JSON number (pixels)")


def test_distortion_is_bounded_by_what_it_does_at_the_corners_not_by_its_coefficient():
    """Brown coefficients act on normalised coordinates: a narrow field (640 x 512 at f 1712 px, corner radius
    0.24) takes a k3 of -202 for 4 % of the corner's radius, and such a certificate is a camera; the same k3
    on a wide field (f 500 px, corner radius 0.82) moves the corners by 6 times their radius, and is refused."""
    narrow = make_certificate(camera=make_certificate().camera.replace(k3=-201.77))
    assert Certificate.from_json(narrow.to_json()) == narrow
    with pytest.raises(CertificateError, match=r"^model\.params\.k3: expected a coefficient that alone moves"):
        make_certificate(camera=narrow.camera.replace(f=500.0))


def test_invalid_json_text_names_line_and_column_and_nan_is_refused():
    text = make_certificate().to_json().replace('"kind": "brown",', '"kind": "brown"', 1)
    with pytest.raises(CertificateError, match=r"line \d+ column \d+: invalid JSON"):
        Certificate.from_json(text)
    text = make_certificate().to_json().replace('"sigma0": 1.04', '"sigma0": NaN')
    with pytest.raises(CertificateError, match="NaN is not allowed"):
        Certificate.from_json(text)
    with pytest.raises(CertificateError, match="document: expected a JSON object"):
        Certificate.from_json("[1, 2]")


def test_invalid_construction_is_refused_with_the_field_path():
    with pytest.raises(CertificateError, match="sigmas.q: unknown name"):
        make_certificate(sigmas={"q": 1.0})
    with pytest.raises(CertificateError, match="conditions.temperature_range"):
        make_certificate(conditions=Conditions(temperature_range=(30.0, 10.0)))
    with pytest.raises(CertificateError, match="camera.make: expected one line of text without '\\|'"):
        make_certificate(identity=CameraIdentity("A|B", "m", "s", "l"))
    with pytest.raises(CertificateError, match="camera.serial: expected one line of text"):
        make_certificate(identity=CameraIdentity("A", "m", "1\n2 FULL_OPENCV", "l"))


# ----------------------------------------------------------------------------- temperature coverage
def test_covers_uses_the_thermal_range_then_the_calibration_range():
    cert = make_certificate()  # thermal valid 8.0-41.5, images 9.5-40.0
    assert cert.valid_temperature_range == (8.0, 41.5)
    assert cert.covers((8.0, 41.5)) and cert.covers((20.0, 30.0)) and cert.covers(None)
    assert not cert.covers((7.9, 30.0)) and not cert.covers((20.0, 41.6))
    assert cert.covers((7.0, 42.0), margin=1.0)
    no_thermal = dataclasses.replace(cert, thermal=None)
    assert no_thermal.valid_temperature_range == (9.5, 40.0)
    assert no_thermal.covers((9.5, 40.0)) and not no_thermal.covers((8.0, 40.0))
    unknown = dataclasses.replace(no_thermal, conditions=Conditions())
    assert unknown.covers(None) and not unknown.covers((20.0, 21.0))
    with pytest.raises(CertificateError, match="temperature_range"):
        cert.covers((30.0, 10.0))


# ----------------------------------------------------------------------------- rendering, identity
def test_render_text_shows_sigmas_units_significance_and_strong_correlations():
    text = make_certificate().render_text()
    assert "FLIR|Vue Pro R 640|SN-47110|13 mm" in text
    assert "1711.76 ± 0.42 px" in text  # f rounded to its sigma's second digit
    assert "-0.2000 ± 0.0011" in text  # k1, dimensionless (no unit)
    assert "dropped: |t| 0.7 < 1.96 at 95 %" in text  # k3
    assert "f-k1 +0.930" in text
    strong = [p for p in make_certificate().correlation.high_pairs(0.9)]
    assert [(a, b) for a, b, _ in strong] == [("f", "k1")]
    assert "df_dt 0.290 ± 0.012 px/degC" in text and "valid 8.0 to 41.5 degC" in text
    assert "5 strips (transversal: yes)" in text and "sigma0 1.040" in text


def test_camera_identity_key_round_trip():
    ident = CameraIdentity("DJI", "ZH20T", "1ZNBJ7", "DL 4.5mm")
    assert ident.key == "DJI|ZH20T|1ZNBJ7|DL 4.5mm"
    assert CameraIdentity.from_key(ident.key) == ident
    assert CameraIdentity.unknown().key == "unknown|unknown|unknown|unknown"
    with pytest.raises(CertificateError, match="expected 4 parts"):
        CameraIdentity.from_key("DJI|ZH20T")


def test_correlation_rejects_a_matrix_of_the_wrong_size():
    with pytest.raises(CertificateError, match="correlation.matrix: expected 2 x 2"):
        Correlation(("f", "k1"), [[1.0, 0.2, 0.1]])


def test_a_nominal_value_held_carries_its_prior_sigma_into_the_diagnosis():
    """f held at the nominal because the block could not determine it: the certificate records the nominal's
    own sigma, the JSON round trip keeps it, and the diagnosis's IO covariance includes it (uncorrelated)."""
    from aerocal.diagnose.io_uncertainty import IOUncertainty

    base = make_certificate()
    est = tuple(n for n in base.estimated if n != "f")
    sig = dict(base.significance)
    sig["f"] = ParameterSignificance(0.0, False, "f not determined by this block; the nominal f is kept",
                                     prior_sigma=17.1)
    cert = dataclasses.replace(base, estimated=est, sigmas={n: s for n, s in base.sigmas.items() if n != "f"},
                               correlation=Correlation(), significance=sig)
    back = Certificate.from_json(cert.to_json())
    assert back.significance["f"].prior_sigma == 17.1
    io = IOUncertainty.from_certificate(back)
    assert io.names[-1] == "f" and io.covariance[-1, -1] == pytest.approx(17.1**2)
    assert np.all(io.covariance[-1, :-1] == 0.0)
    assert set(io.names[:-1]) == set(est)


def test_calibrated_sigmas_are_printed_and_carried_once_into_the_diagnosis():
    """A certificate whose block measured an overdispersion of 100 holds sigmas 10x its adjustment's formal
    ones: it says so when printed, the JSON round trip keeps it, and the diagnosis takes those sigmas as they
    are. A document written before the overdispersion was recorded holds formal sigmas: the diagnosis still
    inflates them by the ratio of formal to calibrated t."""
    from aerocal.diagnose.io_uncertainty import IOUncertainty

    base = make_certificate()
    sig = {n: dataclasses.replace(s, calibrated_t=s.t / 10.0) for n, s in base.significance.items()}
    old = dataclasses.replace(base, significance=sig)
    new = dataclasses.replace(old, sigmas={n: 10.0 * s for n, s in base.sigmas.items()},
                              quality=dataclasses.replace(base.quality, overdispersion=100.0))
    back = Certificate.from_json(new.to_json())
    assert back.quality.overdispersion == 100.0 and back.quality.sigma_scale == pytest.approx(10.0)
    text = back.render_text()
    assert "sigma, calibrated: formal x 10, the square root of the block's measured overdispersion 100" in text
    assert "1711.8 ± 4.2 px" in text  # 10 x the formal 0.42 px
    io_new = IOUncertainty.from_certificate(back)
    io_old = IOUncertainty.from_certificate(Certificate.from_json(old.to_json()))
    assert io_new.names == io_old.names
    np.testing.assert_allclose(io_new.covariance, io_old.covariance, rtol=1e-12)
    f = io_new.names.index("f")
    assert np.sqrt(io_new.covariance[f, f]) == pytest.approx(4.2)
    assert "overdispersion" not in json.loads(old.to_json())["quality"]  # a document without it reads as before


def test_a_nominal_camera_taken_as_it_is_is_uncertain_in_f_principal_point_and_distortion():
    """The certificate a block uses when no calibration is accepted holds the nominal camera with nothing
    estimated: its f, cx, cy and its unknown radial distortion carry their tolerances into the diagnosis."""
    from aerocal.certificates.review import NOMINAL_PARAMETERS, nominal_sigma
    from aerocal.diagnose.io_uncertainty import IOUncertainty

    camera = Camera(width=640, height=512, f=1125.0, cx=320.0, cy=256.0)
    held = {n: ParameterSignificance(0.0, False, "nominal value, not calibrated",
                                     prior_sigma=nominal_sigma(n, camera)) for n in NOMINAL_PARAMETERS}
    cert = Certificate(identity=CameraIdentity("DJI", "ZH20T", "1", "13.5 mm"), camera=camera, significance=held)
    io = IOUncertainty.from_certificate(Certificate.from_json(cert.to_json()))
    sd = dict(zip(io.names, np.sqrt(np.diag(io.covariance)), strict=True))
    corner2 = (320.0**2 + 256.0**2) / 1125.0**2
    assert sd["f"] == pytest.approx(11.25) and sd["cx"] == pytest.approx(6.4) and sd["cy"] == pytest.approx(5.12)
    # either term alone moves the corner by 2 % of its radius
    assert sd["k1"] * corner2 == pytest.approx(0.02) and sd["k2"] * corner2**2 == pytest.approx(0.02)


#: what a hand edit, a script or an attacker puts anywhere in a document
HOSTILE_VALUES = [None, [], {}, "", "x", 10**400, -(10**400), float("nan"), float("inf"), True, -1, 0, 1.5, [[1]],
                  {"a": 1}, [None], "2024-13-01", "a|b", "\n", 4294967297, [1, 2], {"kind": "linear"}, 1e308]
FUZZ_SEED = 20261126


def _paths(obj, path=()):
    yield path
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, (*path, i))


@pytest.mark.parametrize("variant", list(THERMAL_VARIANTS))
def test_hostile_values_anywhere_are_one_line_certificate_errors(variant):
    """300 seeded mutations per thermal variant (any node of the document replaced by a hostile value): each
    document is refused with a one-line CertificateError naming a field, or accepted and then round-trips;
    never another exception."""
    rng = np.random.default_rng(FUZZ_SEED)
    base = _variant(variant).to_dict()
    for k in range(300):
        doc = copy.deepcopy(base)
        paths = [p for p in _paths(doc) if p]
        path = paths[int(rng.integers(len(paths)))]
        node = doc
        for p in path[:-1]:
            node = node[p]
        node[path[-1]] = copy.deepcopy(HOSTILE_VALUES[int(rng.integers(len(HOSTILE_VALUES)))])
        case = f"seed {FUZZ_SEED}, {variant} case {k}: {path} = {node[path[-1]]!r:.40}"
        try:
            cert = Certificate.from_dict(doc)
        except CertificateError as exc:
            text = str(exc)
            assert "\n" not in text and ": " in text and "; " in text, f"{case}: {text}"
            continue
        except Exception as exc:  # the assertion: nothing else is raised
            pytest.fail(f"{case}: {type(exc).__name__}: {exc}")
        assert Certificate.from_json(cert.to_json()) == cert, case


def test_a_term_the_calibration_dropped_and_a_diagnosis_found_makes_a_valid_next_version():
    """k3 and b2 dropped by the self-calibration, then found by a flight's diagnosis: the extended certificate
    estimates them with the diagnosis's significance, and validates (it raised "k3 is marked dropped but is listed
    in estimated", stopping `aerocal process` on a simulated UltraCam block with refraction hidden)."""
    from aerocal.diagnose.extension import ModelTerm, extend_certificate

    cert = make_certificate()
    terms = (ModelTerm("radial_k3", (2.2e-4,), (3.5e-5,), "held-out gain +0.05 +- 0.01 %"),
             ModelTerm("affinity_skew", (0.0, 0.3), (0.05, 0.1), "held-out gain +1.0 +- 0.2 %"))
    new = extend_certificate(cert, terms, "survey")
    assert {"k3", "b2"} <= set(new.estimated)
    assert new.significance["k3"].dropped is None and new.significance["k3"].t == pytest.approx(2.2e-4 / 3.5e-5)
    assert new.significance["b2"].dropped is None and new.significance["b2"].significant
    assert Certificate.from_dict(new.to_dict()).camera.k3 == pytest.approx(2.2e-4)
