"""Certificate selection rules on engine certificates alone (no database): what an in-memory store uses."""

from __future__ import annotations

import dataclasses
import datetime as dt

import pytest

from aerocal.camera import Camera, LinearThermalModel
from aerocal.certificates.document import CameraIdentity, Certificate, Conditions, ThermalCalibration
from aerocal.certificates.review import Review
from aerocal.certificates.selection import (
    Candidate,
    NoCertificateError,
    SelectionRules,
    choose_certificate,
    coverage,
)

CAMERA = CameraIdentity("NEC", "TS9260", "123")
OTHER = CameraIdentity("NEC", "TS9260", "456")


def certificate(day: str, temperatures: tuple[float, float] | None, identity: CameraIdentity = CAMERA,
                thermal: tuple[float, float] | None = None, review: Review | None = None,
                version: int | None = None) -> Certificate:
    th = None
    if thermal is not None:
        th = ThermalCalibration(LinearThermalModel(t0=20.0, df_dt=0.21, valid_range=thermal), {"df_dt": 0.02})
    cert = Certificate(identity=identity, camera=Camera(width=640, height=480, f=1668.0, cx=320.4, cy=240.7),
                       conditions=Conditions(date=day, temperature_range=temperatures), thermal=th, review=review)
    return cert if version is None else cert.with_version(version, None)


def test_the_newest_applicable_certificate_of_the_camera_wins_and_the_reason_says_why():
    old = certificate("2016-03-14", (20.0, 22.0), version=1)
    newer_other_camera = certificate("2017-01-10", (15.0, 25.0), identity=OTHER, version=1)
    newer = certificate("2016-09-01", (19.0, 24.0), version=2)
    chosen, reason = choose_certificate([old, newer_other_camera, newer], CAMERA, "2017-05-02", (19.0, 23.5))
    assert chosen is newer
    assert reason == (f"newest applicable certificate (2 of 2 for camera NEC TS9260 s/n 123): v2 {newer.id} "
                      "calibrated 2016-09-01, 243 days before the flight; covers 16-27 degC (constant IO calibrated "
                      "at 19-24 degC +/- 3) >= flight 19-23.5 degC")
    chosen, _ = choose_certificate([old, newer], CAMERA.key, dt.date(2016, 5, 1), None)  # before `newer`
    assert chosen is old


def test_temperature_coverage_and_thermal_models():
    constant = certificate("2016-03-14", (30.0, 31.0))
    thermal = certificate("2016-01-10", (8.0, 30.0), thermal=(5.0, 35.0))
    assert coverage(constant) == (27.0, 34.0) and coverage(thermal) == (5.0, 35.0)
    chosen, reason = choose_certificate([constant, thermal], CAMERA, "2017-05-02", (10.0, 12.0))
    assert chosen is thermal and "linear thermal model valid 5-35 degC" in reason
    with pytest.raises(NoCertificateError) as err:
        choose_certificate([constant, thermal], CAMERA, "2017-05-02", (2.0, 12.0))
    assert str(err.value) == (
        "camera NEC TS9260 s/n 123: newest certificate 2016-03-14 covers 27-34 degC; flight spans 2-12 degC "
        "(2 certificates checked; widest temperature coverage of any certificate: 5-35 degC); calibrate the "
        "camera on this flight, import a certificate, or pin one")
    chosen, _ = choose_certificate([constant, thermal], CAMERA, "2017-05-02", (2.0, 12.0),
                                   rules=SelectionRules(thermal_tolerance_c=5.0))
    assert chosen is thermal
    unrecorded = certificate("2016-03-14", None)
    chosen, reason = choose_certificate([unrecorded], CAMERA, "2017-05-02", (2.0, 12.0))
    assert chosen is unrecorded and "certificate records no temperatures, flight 2-12 degC not checked" in reason
    with pytest.raises(NoCertificateError, match="records no temperatures; flight spans 2-12 degC"):
        choose_certificate([unrecorded], CAMERA, "2017-05-02", (2.0, 12.0),
                           rules=SelectionRules(accept_unrecorded_temperature=False))


def test_age_date_and_no_certificate_messages():
    cert = certificate("2016-03-14", (21.0, 21.0))
    with pytest.raises(NoCertificateError, match="is 414 days older than the flight of 2017-05-02; the limit is 365"):
        choose_certificate([cert], CAMERA, "2017-05-02", (20.0, 22.0), max_age_days=365)
    with pytest.raises(NoCertificateError, match="oldest certificate 2016-03-14 was calibrated after the flight"):
        choose_certificate([cert], CAMERA, "2015-06-01", None)
    with pytest.raises(NoCertificateError, match="s/n 456: no certificate is stored for this camera"):
        choose_certificate([cert], OTHER, "2017-05-02", None)
    with pytest.raises(ValueError, match="flight date 'May 2nd' is not a date"):
        choose_certificate([cert], CAMERA, "May 2nd", None)


def test_a_rejected_certificate_is_never_chosen_not_even_pinned():
    why = "f 1560.0 px is +103.9 % off the nominal 765.0 px (the band is +-15 %)"
    good = certificate("2016-03-14", (20.0, 22.0))
    bad = certificate("2016-06-01", (20.0, 22.0), review=Review("rejected", (why,)))
    chosen, _ = choose_certificate([good, bad], CAMERA, "2017-05-02", (20.0, 21.0))
    assert chosen is good
    with pytest.raises(NoCertificateError, match="was rejected by its review") as err:
        choose_certificate([good, bad], CAMERA, "2017-05-02", None, pin=bad.id)
    assert why in str(err.value)
    # a store that keeps the status apart from the document
    with pytest.raises(NoCertificateError, match=r"newest certificate 2016-06-01 was rejected .*\(2 certificates"):
        choose_certificate([Candidate.of(good, status="rejected"), bad], CAMERA, "2017-05-02", (20.0, 21.0))


def test_pins_choose_by_id_or_prefix_and_must_be_of_the_camera():
    mine = certificate("2016-03-14", (21.0, 21.0), version=1)
    theirs = certificate("2016-03-14", (21.0, 21.0), identity=OTHER, version=1)
    chosen, reason = choose_certificate([mine, theirs], CAMERA, "2017-05-02", (5.0, 9.0), pin=mine.id[:8])
    assert chosen is mine
    assert reason == (f"pinned by id: v1 {mine.id} calibrated 2016-03-14; note: it covers 18-24 degC; "
                      "flight spans 5-9 degC")
    with pytest.raises(NoCertificateError, match=f"pinned certificate {theirs.id} belongs to camera NEC TS9260 s/n "
                                                 "456; pin a certificate of this camera"):
        choose_certificate([mine, theirs], CAMERA, "2017-05-02", None, pin=theirs.id)
    with pytest.raises(NoCertificateError, match="pinned certificate 'abc' not found among the 2 certificates"):
        choose_certificate([mine, theirs], CAMERA, "2017-05-02", None, pin="abc")
    twin = dataclasses.replace(mine, id=mine.id[:8] + "0" * 24)
    other_twin = dataclasses.replace(mine, id=mine.id[:8] + "1" * 24)
    with pytest.raises(NoCertificateError, match="is ambiguous"):
        choose_certificate([twin, other_twin], CAMERA, "2017-05-02", None, pin=mine.id[:8])


def test_candidates_carry_any_item_a_store_returns():
    cert = certificate("2016-03-14", (21.0, 21.0), version=4)
    row = object()
    candidate = dataclasses.replace(Candidate.of(cert), item=row)
    assert choose_certificate([candidate], CAMERA, "2017-05-02", None)[0] is row
    bare = Candidate(id="c" * 32, camera=CAMERA, calibration_date=dt.date(2016, 3, 14), temperature_range=None)
    assert choose_certificate([bare], CAMERA, "2017-05-02", None)[0] is bare
