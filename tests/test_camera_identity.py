"""The one camera identity: its stored forms (certificate key, images.camera_id, database row), the serial-less
identity, and the same class in ingest, certificates, formats and storage."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

import aerocal.certificates.document
import aerocal.ingest.folder
import storage.cameras
from aerocal.camera import Camera
from aerocal.certificates.document import CertificateError
from aerocal.certificates.identity import UNKNOWN, CameraIdentity
from aerocal.ingest.camera_json import UNKNOWN_CAMERA_ID
from aerocal.ingest.inferred import certificate_identity
from storage.cameras import stored_identity


def test_every_layer_uses_the_same_class():
    assert aerocal.certificates.document.CameraIdentity is CameraIdentity
    assert aerocal.ingest.folder.CameraIdentity is CameraIdentity
    assert storage.cameras.CameraIdentity is CameraIdentity


def test_missing_parts_are_unknown_and_whitespace_is_stripped():
    assert CameraIdentity("DJI", " XT2 ", "", None) == CameraIdentity("DJI", "XT2")  # type: ignore[arg-type]
    assert CameraIdentity("DJI", "XT2").parts == ("DJI", "XT2", UNKNOWN, UNKNOWN)
    assert CameraIdentity.from_parts("DJI", "XT2", None, "  ") == CameraIdentity("DJI", "XT2")
    assert CameraIdentity.unknown().key == "unknown|unknown|unknown|unknown"
    assert not CameraIdentity.unknown().is_known and CameraIdentity(model="XT2").is_known


def test_certificate_key_and_images_camera_id_are_two_forms_of_one_identity():
    ident = CameraIdentity("DJI", "ZH20T", "1ZNBJ7", "DL 4.5mm")
    assert ident.key == ident.camera_id == "DJI|ZH20T|1ZNBJ7|DL 4.5mm"
    assert CameraIdentity.from_key(ident.key) == ident
    # a part not recorded: "unknown" in the key (certificates, database), empty in images.camera_id
    canon = CameraIdentity.from_parts("Canon", "Canon PowerShot ELPH 300 HS", None, None)
    assert canon.key == "Canon|Canon PowerShot ELPH 300 HS|unknown|unknown"
    assert canon.camera_id == "Canon|Canon PowerShot ELPH 300 HS||"  # as earlier flights' tables hold it
    assert CameraIdentity.from_camera_id(canon.camera_id) == canon == CameraIdentity.from_key(canon.key)
    # '|' inside a part is written as '/' in images.camera_id (the key of a certificate refuses it)
    assert CameraIdentity.from_parts("A|B", "m", "s", None).camera_id == "A/B|m|s|"
    assert CameraIdentity.from_camera_id(UNKNOWN_CAMERA_ID) == CameraIdentity.unknown()
    assert CameraIdentity.from_key("NEC|TS9260|123") == CameraIdentity("NEC", "TS9260", "123")  # lens left out
    with pytest.raises(CertificateError, match="expected 4 parts"):
        CameraIdentity.from_key("DJI|ZH20T")


def test_mapping_and_database_row_forms():
    ident = CameraIdentity("NEC", "TS9260", "123", "39.2mm Ge")
    assert CameraIdentity.from_mapping(ident.as_dict()) == ident
    assert CameraIdentity.from_mapping({"make": "NEC", "model": "TS9260", "serial": 123}).serial == "123"
    row = SimpleNamespace(make="NEC", model="TS9260", serial="123", lens="39.2mm Ge", id=7)
    assert CameraIdentity.coerce(row) == ident == CameraIdentity.coerce(ident.key)
    with pytest.raises(CertificateError, match=r"camera.serial: expected text, got list"):
        CameraIdentity.from_mapping({"make": "NEC", "model": "TS9260", "serial": [1]})
    with pytest.raises(TypeError, match="cannot read a camera identity from float"):
        CameraIdentity.coerce(1.5)


def test_labels_and_the_database_refusal_of_an_incomplete_identity():
    assert CameraIdentity("NEC", "TS9260", "123").label == "NEC TS9260 s/n 123"
    assert str(CameraIdentity("NEC", "TS9260", "123", "39.2mm Ge")) == "NEC TS9260 s/n 123 lens 39.2mm Ge"
    shared = CameraIdentity("DJI", "XT2", "no-serial 640x512", "13.0 mm")
    assert shared.shared_body and shared.label == (
        "DJI XT2 (no-serial 640x512: any body of this model, no serial recorded) lens 13.0 mm")
    assert stored_identity("NEC|TS9260|123") == CameraIdentity("NEC", "TS9260", "123")
    with pytest.raises(ValueError, match=r"camera identity 'NEC\|TS9260\|unknown\|unknown' lacks serial"):
        stored_identity("NEC|TS9260|")
    with pytest.raises(ValueError, match="lacks make, model, serial"):
        stored_identity(CameraIdentity.unknown())


def test_a_camera_recording_no_serial_gets_the_serial_less_identity():
    camera = Camera(width=640, height=512, f=764.7, cx=320.0, cy=256.0, pixel_size_mm=0.017)
    for serial in (None, "", "unknown"):  # camera.json written by hand says "unknown"
        given = CameraIdentity.from_parts("DJI", "XT2", serial, None)
        assert certificate_identity([], given, camera) == CameraIdentity("DJI", "XT2", "no-serial 640x512", "13.0 mm")
    kept = certificate_identity([], CameraIdentity("DJI", "XT2", "SN1", "13 mm"), camera)
    assert kept == CameraIdentity("DJI", "XT2", "SN1", "13 mm")
    assert certificate_identity([], CameraIdentity.unknown(), camera) is None
