"""Certificate store: versions, supersession, immutability, concurrency and selection, on both engines."""

from __future__ import annotations

import multiprocessing
import os
import time

import pytest
import sqlalchemy as sa

from aerocal.certificates.document import Certificate as EngineCertificate
from aerocal.certificates.selection import NoCertificateError as NoApplicableCertificateError
from aerocal.certificates.selection import choose_certificate
from storage.cameras import CameraIdentity
from storage.certificates import (
    SelectionRules,
    get_certificate,
    issue_certificate,
    list_certificates,
    select_certificate,
    supersession_chain,
)
from storage.errors import CertificateDocumentError, ImmutableCertificateError, NoStoredCertificateError
from storage.flights import register_flight
from storage.models import Certificate
from storage.provenance import provenance
from storage.runs import finish_run, record_timing, start_run

pytest_plugins = ["conftest_storage"]  # fixtures: storage_url, storage_db, unique, ...


def test_versions_are_consecutive_and_each_supersedes_the_previous(make_certificate, storage_db, unique):
    serial = f"v-{unique}"
    with storage_db.session() as session:
        stored = [issue_certificate(session, make_certificate(serial)) for _ in range(3)]
    assert [c.version for c in stored] == [1, 2, 3]
    assert [c.supersedes for c in stored] == [None, stored[0].id, stored[1].id]
    with storage_db.session() as session:
        latest = get_certificate(session, stored[2].id)
        doc = latest.document
        assert (doc["version"], doc["supersedes"]) == (3, stored[1].id)  # the store fills these in
        assert doc["model"]["params"]["f"] == 1668.0
        assert [c.version for c in supersession_chain(session, latest)] == [3, 2, 1]
        assert [c.id for c in list_certificates(session, f"nec {serial}")] == [c.id for c in stored]
        assert get_certificate(session, stored[0].id[:10]).id == stored[0].id  # unique prefix


def test_stored_certificates_cannot_be_modified(make_certificate, storage_db, unique):
    with storage_db.session() as session:
        cert = issue_certificate(session, make_certificate(f"imm-{unique}"))
        cert_id = cert.id
        with pytest.raises(ImmutableCertificateError, match="immutable"):
            cert.sigma0 = 0.5
    with storage_db.session() as session:
        cert = session.get(Certificate, cert_id)
        doc = cert.document
        doc["model"]["params"]["f"] = 1.0  # editing the copy...
        assert cert.document["model"]["params"]["f"] == 1668.0  # ...never touches the record
        session.delete(cert)
        with pytest.raises(ImmutableCertificateError, match="cannot be deleted"):
            session.flush()
        session.rollback()
    # the database refuses raw SQL too
    for statement in (
        "UPDATE certificates SET sigma0 = 2.0 WHERE id = :id",
        "DELETE FROM certificates WHERE id = :id",
    ):
        with storage_db.engine.connect() as conn:
            with pytest.raises(sa.exc.DBAPIError, match="immutable"):
                conn.execute(sa.text(statement), {"id": cert_id})
            conn.rollback()
    with storage_db.session() as session:
        assert session.get(Certificate, cert_id).sigma0 == pytest.approx(0.93)


def test_reissuing_a_stored_document_is_refused(make_certificate, storage_db, unique):
    doc = make_certificate(f"dup-{unique}")
    with storage_db.session() as session:
        first = issue_certificate(session, doc)
        with pytest.raises(CertificateDocumentError, match="already stored"):
            issue_certificate(session, doc)
        assert [
            c.id for c in list_certificates(session, CameraIdentity("NEC", "TS9260", f"dup-{unique}"))
        ] == [first.id]


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda d: d["camera"].pop("serial"), "camera.serial: missing; add it"),
        (lambda d: d["camera"].update(serial="unknown"),
         "camera: camera identity 'NEC|TS9260|unknown|unknown' lacks serial: give make, model and serial number"),
        (lambda d: d.update(schema="aerocal.certificate/2"),
         'schema: expected "aerocal.certificate/1", got "aerocal.certificate/2"; this aerocal reads certificate '
         "schema 1 only; re-export the certificate or upgrade aerocal"),
        (lambda d: d["conditions"].update(date="14/03/2016"),
         'conditions.date: expected a date "YYYY-MM-DD" or null, got "14/03/2016"; write e.g. "2024-05-17"'),
        (lambda d: d["sigmas"].update(k3=float("nan")),
         "sigmas.k3: expected a non-negative number, got NaN; write the standard deviation (>= 0)"),
        (lambda d: d["conditions"].update(temperature_range=[30, 10]),
         "conditions.temperature_range: expected [lo, hi] with lo <= hi, got [30.0, 10.0]; swap the two values"),
        (lambda d: d["model"]["params"].update(f="1668"),
         'model.params.f: expected a positive number, got "1668"; write f as a JSON number (pixels)'),
    ],
)
def test_malformed_documents_name_the_field(make_certificate, storage_db, unique, edit, expected):
    doc = make_certificate(f"bad-{unique}")
    edit(doc)
    with storage_db.session() as session, pytest.raises(CertificateDocumentError) as err:
        issue_certificate(session, doc)
    assert str(err.value).startswith(f"certificate {doc['id']}: {expected}"), str(err.value)


# ------------------------------------------------------------------------------------ concurrency
def _issue_many(url: str, serial: str, n: int, barrier, results) -> None:
    """Worker (spawned process): issue ``n`` certificates for one camera as fast as possible."""
    from conftest_storage import certificate_document

    from storage.database import connect

    db = connect(url)
    barrier.wait(timeout=60)
    out = []
    with db.session() as session:
        for _ in range(n):
            cert = issue_certificate(session, certificate_document(serial))
            out.append((cert.id, cert.version, cert.supersedes))
            time.sleep(0.005)  # give the other process a chance to take the lock in between
    db.dispose()
    results.put((os.getpid(), out))


def test_two_processes_issuing_for_one_camera_get_distinct_consecutive_versions(storage_url, unique):
    n_proc, n_each = 2, 10
    serial = f"race-{unique}"
    ctx = multiprocessing.get_context("spawn")
    barrier, results = ctx.Barrier(n_proc), ctx.Queue()
    procs = [
        ctx.Process(target=_issue_many, args=(storage_url, serial, n_each, barrier, results))
        for _ in range(n_proc)
    ]
    for p in procs:
        p.start()
    outputs = dict(results.get(timeout=120) for _ in procs)
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0, f"issuing process exited with {p.exitcode}"
    issued = [item for out in outputs.values() for item in out]
    versions = sorted(v for _, v, _ in issued)
    assert versions == list(range(1, n_proc * n_each + 1)), f"versions {versions}"
    for out in outputs.values():  # each process saw its own versions increase
        assert [v for _, v, _ in out] == sorted(v for _, v, _ in out)
    by_version = {v: (cid, sup) for cid, v, sup in issued}
    for v in range(2, n_proc * n_each + 1):
        assert by_version[v][1] == by_version[v - 1][0], f"v{v} does not supersede v{v - 1}"
    from storage.database import connect

    db = connect(storage_url)
    try:
        with db.session() as session:
            stored = list_certificates(session, CameraIdentity("NEC", "TS9260", serial))
    finally:
        db.dispose()
    assert sorted(c.id for c in stored) == sorted(cid for cid, _, _ in issued)  # nothing lost or duplicated
    assert [c.version for c in stored] == list(range(1, n_proc * n_each + 1))


# -------------------------------------------------------------------------------------- selection
def test_certificate_of_flight_a_2016_is_used_for_flight_b_2017_and_recorded(
    make_certificate, storage_db, unique
):
    camera = CameraIdentity("NEC", "TS9260", f"123-{unique}")
    other = CameraIdentity("NEC", "TS9260", f"456-{unique}")
    with storage_db.session() as session:
        cert_a = issue_certificate(session, make_certificate(camera.serial, "2016-03-14", (20.0, 22.0)))
        # a newer certificate of another camera of the same model must never be chosen
        issue_certificate(session, make_certificate(other.serial, "2017-01-10", (15.0, 25.0)))
        register_flight(
            session,
            f"A-{unique}",
            "2016-03-14",
            camera,
            crs="EPSG:32632",
            n_images=44,
            temperature_range=(20.0, 22.0),
        )
        flight_b = register_flight(
            session,
            f"B-{unique}",
            "2017-05-02",
            camera,
            crs="EPSG:32632",
            n_images=812,
            bbox=(500000, 5000000, 503000, 5002000),
            temperature_range=(19.0, 23.5),
        )
        run_id = f"flow-run-B-{unique}"
        start_run(
            session, run_id, "process_flight", configuration={"subset": {"n_images": 44}}, flight=flight_b
        )
        chosen, reason = select_certificate(
            session, camera, flight_b.date, flight_b.temperature_range, run_id=run_id
        )
        record_timing(session, run_id, "adjust", 12.5)
        finish_run(session, run_id)
        session.commit()
    assert chosen.id == cert_a.id
    assert "v1" in reason and "2016-03-14" in reason and "17-25 degC" in reason
    with storage_db.session() as session:
        prov = provenance(session, run_id)
    assert prov.certificate is not None and prov.certificate.id == cert_a.id
    assert prov.certificate.reason == reason
    assert prov.flight == f"B-{unique}"
    assert prov.configuration == {"subset": {"n_images": 44}}
    assert prov.timings == {"adjust": 12.5}
    assert prov.status == "completed"


def test_no_certificate_message_says_what_is_missing(make_certificate, storage_db, unique):
    serial = f"123-{unique}"
    with storage_db.session() as session:
        issue_certificate(session, make_certificate(serial, "2016-03-14", (21.0, 21.0)))
        with pytest.raises(NoStoredCertificateError) as err:
            select_certificate(session, CameraIdentity("NEC", "TS9260", serial), "2017-05-02", (12.0, 19.0))
        assert (
            f"camera NEC TS9260 s/n {serial}: newest certificate 2016-03-14 covers 18-24 degC; "
            "flight spans 12-19 degC" in str(err.value)
        )
        with pytest.raises(
            NoStoredCertificateError, match="is 414 days older than the flight of 2017-05-02; the limit is 365"
        ):
            select_certificate(session, f"NEC|TS9260|{serial}", "2017-05-02", (20.0, 22.0), max_age_days=365)
        with pytest.raises(NoStoredCertificateError, match="was calibrated after the flight of 2015-06-01"):
            select_certificate(session, f"NEC|TS9260|{serial}", "2015-06-01", (20.0, 22.0))
        with pytest.raises(NoStoredCertificateError, match=f"s/n nothing-{unique}: no certificate is stored"):
            select_certificate(session, f"NEC|TS9260|nothing-{unique}", "2017-05-02", None)


def test_thermal_model_covers_its_valid_range_and_the_newest_applicable_wins(
    make_certificate, storage_db, unique
):
    serial = f"th-{unique}"
    with storage_db.session() as session:
        constant = issue_certificate(session, make_certificate(serial, "2016-03-14", (30.0, 31.0)))
        thermal = issue_certificate(
            session, make_certificate(serial, "2016-01-10", (8.0, 30.0), thermal_range=(5.0, 35.0))
        )
        camera = CameraIdentity("NEC", "TS9260", serial)
        # a constant-IO certificate made at 30 degC does not cover a flight at 10 degC; the thermal one does
        chosen, reason = select_certificate(session, camera, "2017-05-02", (10.0, 12.0))
        assert chosen.id == thermal.id, reason
        assert "linear thermal model valid 5-35 degC" in reason
        # both cover 29-32 degC: the newer calibration (2016-03-14) wins although it has the lower version
        chosen, reason = select_certificate(session, camera, "2017-05-02", (29.0, 32.0))
        assert chosen.id == constant.id and chosen.version == 1, reason
        # the thermal model is not extrapolated (tolerance 0) unless the rules say so
        with pytest.raises(NoStoredCertificateError) as err:
            select_certificate(session, camera, "2017-05-02", (2.0, 12.0))
        assert "newest certificate 2016-03-14 covers 27-34 degC; flight spans 2-12 degC" in str(err.value)
        assert "widest temperature coverage of any certificate: 5-35 degC" in str(err.value)
        chosen, _ = select_certificate(
            session, camera, "2017-05-02", (2.0, 12.0), rules=SelectionRules(thermal_tolerance_c=5.0)
        )
        assert chosen.id == thermal.id


def test_pinned_certificate_is_used_and_must_belong_to_the_camera(make_certificate, storage_db, unique):
    mine, theirs = f"pin-{unique}", f"pin-other-{unique}"
    with storage_db.session() as session:
        cert = issue_certificate(session, make_certificate(mine, "2016-03-14", (21.0, 21.0)))
        foreign = issue_certificate(session, make_certificate(theirs, "2016-03-14", (21.0, 21.0)))
        chosen, reason = select_certificate(
            session, f"NEC|TS9260|{mine}", "2017-05-02", (5.0, 9.0), pin=cert.id
        )
        assert chosen.id == cert.id
        assert reason.startswith("pinned by id") and "covers 18-24 degC; flight spans 5-9 degC" in reason
        with pytest.raises(NoStoredCertificateError, match=f"belongs to camera NEC TS9260 s/n {theirs}"):
            select_certificate(session, f"NEC|TS9260|{mine}", "2017-05-02", None, pin=foreign.id)


def test_a_rejected_certificate_is_on_record_but_never_selected(make_certificate, storage_db, unique):
    """A calibration that failed its review is stored with its reasons; auto-selection passes over it to
    the older accepted one, and pinning it is refused with the reason."""
    serial = f"rej-{unique}"
    why = "f 1560.0 px is +103.9 % off the nominal 765.0 px (the band is +-15 %)"
    with storage_db.session() as session:
        good = issue_certificate(session, make_certificate(serial, "2016-03-14", (20.0, 22.0)))
        doc = make_certificate(serial, "2016-06-01", (20.0, 22.0))
        doc["review"] = {"status": "rejected", "problems": [why], "checks": [], "notes": []}
        bad = issue_certificate(session, doc)
        assert (bad.status, bad.version, good.status) == ("rejected", 2, "accepted")
        camera = CameraIdentity("NEC", "TS9260", serial)
        chosen, reason = select_certificate(session, camera, "2017-05-02", (20.0, 21.0))
        assert chosen.id == good.id, reason
        with pytest.raises(NoStoredCertificateError, match="was rejected by its review") as err:
            select_certificate(session, camera, "2017-05-02", None, pin=bad.id)
        assert why in str(err.value)
        doc = make_certificate(serial, "2016-07-01", (20.0, 22.0))
        doc["review"] = {"status": "maybe", "problems": [], "checks": [], "notes": []}
        with pytest.raises(CertificateDocumentError, match="review.status"):
            issue_certificate(session, doc)


def test_the_store_fills_in_a_missing_id_and_issue_time(make_certificate, storage_db, unique):
    doc = make_certificate(f"fill-{unique}")
    del doc["id"], doc["issued"]
    with storage_db.session() as session:
        stored = issue_certificate(session, doc)
        assert len(stored.id) == 32 and stored.document["id"] == stored.id
        assert stored.document["issued"].endswith("Z") and stored.calibration_date.isoformat() == "2016-03-14"


def test_stored_documents_load_into_the_engine_which_chooses_as_the_store_does(make_certificate, storage_db, unique):
    """The rules are the engine's: an in-memory list of engine certificates gives the same choice and reason."""
    serial = f"mem-{unique}"
    why = "f 1560.0 px is +103.9 % off the nominal 765.0 px"
    docs = [make_certificate(serial, "2016-03-14", (30.0, 31.0)),
            make_certificate(serial, "2016-01-10", (8.0, 30.0), thermal_range=(5.0, 35.0)),
            make_certificate(serial, "2016-06-01", (5.0, 35.0))]
    docs[2]["review"] = {"status": "rejected", "problems": [why], "checks": [], "notes": []}
    camera = CameraIdentity("NEC", "TS9260", serial)
    with storage_db.session() as session:
        rows = [issue_certificate(session, doc) for doc in docs]
        in_memory = [EngineCertificate.from_dict(row.document) for row in rows]
        assert [(c.version, c.status) for c in in_memory] == [(1, "accepted"), (2, "accepted"), (3, "rejected")]
        assert [c.calibration_date for c in in_memory] == [r.calibration_date for r in rows]
        for flight in ((10.0, 12.0), (29.0, 32.0), None):
            stored, stored_reason = select_certificate(session, camera, "2017-05-02", flight)
            chosen, reason = choose_certificate(in_memory, camera, "2017-05-02", flight)
            assert (chosen.id, reason) == (stored.id, stored_reason)
        with pytest.raises(NoStoredCertificateError) as stored_err:
            select_certificate(session, camera, "2017-05-02", (2.0, 12.0))
        with pytest.raises(NoApplicableCertificateError) as err:
            choose_certificate(in_memory, camera, "2017-05-02", (2.0, 12.0))
        assert str(err.value) == str(stored_err.value)
        assert isinstance(stored_err.value, NoApplicableCertificateError)  # one except clause catches both
