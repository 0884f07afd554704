"""Export certificates to, and import them from, other tools' calibration files.

=============  =====================================  ==============================================
``fmt``        file                                   module
=============  =====================================  ==============================================
certificate    aerocal certificate JSON (lossless)    :mod:`aerocal.certificates.schema`
opencv         OpenCV ``cv2.FileStorage`` YAML        :mod:`aerocal.formats.opencv` (XML read too)
colmap         COLMAP ``cameras.txt`` (FULL_OPENCV)   :mod:`aerocal.formats.colmap`
opensfm        OpenSfM / ODM ``cameras.json``         :mod:`aerocal.formats.opensfm`
metashape      Agisoft Metashape calibration XML      :mod:`aerocal.formats.metashape`
=============  =====================================  ==============================================

Foreign formats hold only part of a certificate (each exporter's docstring says what is lost); an
imported certificate holds what the file held, with the camera identity passed in (or ``unknown``).
Every write is atomic; every read is size-capped and safe (``defusedxml``, YAML safe loader) and fails
with a one-line :class:`FormatError` naming the file, the field and the fix.

Tests: tests/test_formats.py.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aerocal.certificates.document import Certificate, CertificateError
from aerocal.certificates.identity import CameraIdentity
from aerocal.certificates.schema import SCHEMA
from aerocal.formats import colmap, metashape, opencv, opensfm
from aerocal.formats.safe_parsing import FormatError, decode_text, format_error, parse_xml, read_bytes
from aerocal.io import write_text_atomic

#: Format names accepted by :func:`export_certificate` and :func:`import_certificate`.
FORMATS: tuple[str, ...] = ("certificate", "opencv", "colmap", "opensfm", "metashape")

#: Keyword options each format accepts on export / import (beyond ``identity`` on import).
EXPORT_OPTIONS: dict[str, tuple[str, ...]] = {
    "certificate": (), "opencv": ("drop_skew",), "colmap": ("camera_id", "drop_skew"),
    "opensfm": ("key", "drop_skew"), "metashape": ("form",),
}
IMPORT_OPTIONS: dict[str, tuple[str, ...]] = {
    "certificate": (), "opencv": (), "colmap": ("camera_id",), "opensfm": ("key",), "metashape": ("sensor",),
}

_SUFFIXES = {".yaml": "opencv", ".yml": "opencv", ".txt": "colmap"}


def _check_format(fmt: str) -> str:
    if fmt not in FORMATS:
        raise FormatError(f"format {fmt!r} unknown; use one of {', '.join(FORMATS)}")
    return fmt


def _check_options(
    fmt: str, options: Mapping[str, Any], allowed: dict[str, tuple[str, ...]], what: str
) -> None:
    extra = sorted(set(options) - set(allowed[fmt]))
    if extra:
        valid = ", ".join(allowed[fmt]) or "none"
        raise TypeError(f"{what} to {fmt}: option(s) {', '.join(extra)} not accepted; valid: {valid}")


def export_certificate(doc_or_cert: Certificate | Mapping[str, Any], fmt: str, path: str | Path,
                       **options: Any) -> Path:
    """Write a certificate (object or JSON document, validated) in format ``fmt`` to ``path``, atomically.

    ``options`` by format: opencv ``drop_skew``; colmap ``camera_id``, ``drop_skew``; opensfm ``key``,
    ``drop_skew``; metashape ``form`` (:func:`aerocal.formats.metashape.write_metashape_xml`).
    Formats without skew refuse a non-zero ``b2`` unless ``drop_skew=True``.
    Returns the path written.

    Raises:
        FormatError: ``fmt`` is not one of :data:`FORMATS`; ``doc_or_cert`` is not a valid certificate document; the
            format has no skew and ``b2`` is non-zero without ``drop_skew=True``.
        TypeError: an option in ``options`` that ``fmt`` does not accept (the message lists the valid ones).
    """
    _check_format(fmt)
    _check_options(fmt, options, EXPORT_OPTIONS, "export")
    path = Path(path)
    if isinstance(doc_or_cert, Certificate):
        cert = doc_or_cert
    else:
        try:
            cert = Certificate.from_dict(doc_or_cert)
        except CertificateError as e:
            raise FormatError(f"certificate to export to {path}: {e}") from None
    if fmt == "certificate":
        return write_text_atomic(path, cert.to_json() + "\n")
    if fmt == "opencv":
        return opencv.write_opencv_yaml(cert, path, **options)
    if fmt == "colmap":
        return colmap.write_colmap_cameras(cert, path, **options)
    if fmt == "opensfm":
        return opensfm.write_opensfm_cameras(cert, path, **options)
    return metashape.write_metashape_xml(cert, path, **options)


def import_certificate(path: str | Path, fmt: str | None = None, *, identity: CameraIdentity | None = None,
                       **options: Any) -> Certificate:
    """Read a calibration file into a :class:`~aerocal.certificates.document.Certificate`.

    ``fmt`` is guessed from the file (:func:`guess_format`) when ``None``. ``identity`` names the camera
    for foreign formats (``unknown`` otherwise; a certificate JSON records its own and refuses one).
    ``options`` by format: colmap ``camera_id``, opensfm ``key``, metashape ``sensor`` (id or label),
    each choosing one camera in a file that holds several.

    Raises:
        TypeError: ``identity`` given for a certificate JSON, or an option in ``options`` that the format does not
            accept.
        FormatError: ``fmt`` is not one of :data:`FORMATS` or cannot be guessed, or the file does not read as that
            format; the message names the file, the line and the field.
    """
    path = Path(path)
    fmt = _check_format(fmt) if fmt is not None else guess_format(path)
    _check_options(fmt, options, IMPORT_OPTIONS, "import")
    if fmt == "certificate":
        if identity is not None:
            raise TypeError("a certificate JSON records its own camera identity; do not pass identity=")
        return read_certificate_json(path)
    if fmt == "opencv":
        return opencv.read_opencv(path, identity=identity)
    if fmt == "colmap":
        return colmap.read_colmap_cameras(path, identity=identity, **options)
    if fmt == "opensfm":
        return opensfm.read_opensfm_cameras(path, identity=identity, **options)
    return metashape.read_metashape_xml(path, identity=identity, **options)


def read_certificate_json(path: str | Path) -> Certificate:
    """Read and strictly validate a certificate JSON file; errors name the file and the field path.

    Raises:
        FormatError: the file is missing, not a regular file, too large or not UTF-8, or its content is not a valid
            certificate (the message names the field path).
    """
    path = Path(path)
    text = decode_text(path, read_bytes(path))
    try:
        return Certificate.from_json(text)
    except CertificateError as e:
        raise FormatError(f"{path}: {e}") from None


def guess_format(path: str | Path) -> str:
    """The format of a calibration file, from its extension and, where that is ambiguous, its content.

    ``.yaml``/``.yml`` opencv; ``.txt`` colmap; ``.json`` certificate when it carries the aerocal
    schema, else opensfm; ``.xml`` opencv for ``<opencv_storage>``, else metashape. Without a known
    extension the content decides (``%YAML``, ``<``, ``{``/``[``).

    Raises:
        FormatError: neither the extension nor the content tells the format (pass ``fmt=``); the file is missing, not a
            regular file, too large or not UTF-8; XML content that :func:`parse_xml` refuses.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in _SUFFIXES:
        return _SUFFIXES[suffix]
    data = read_bytes(path)
    head = decode_text(path, data).lstrip()
    if suffix == ".json" or head.startswith(("{", "[")):
        try:
            doc = json.loads(head)
        except ValueError:
            if suffix == ".json":
                return "opensfm"  # the importer reports the syntax error with its line
            raise format_error(path, None, "cannot tell the format (not valid JSON)",
                               f"pass fmt= (one of {', '.join(FORMATS)})") from None
        is_cert = isinstance(doc, Mapping) and str(doc.get("schema", "")).startswith(SCHEMA.split("/")[0])
        return "certificate" if is_cert else "opensfm"
    if suffix == ".xml" or head.startswith("<"):
        return "opencv" if parse_xml(path, data).tag == "opencv_storage" else "metashape"
    if head.startswith("%YAML"):
        return "opencv"
    raise format_error(path, None, "cannot tell the format from the file name or content",
                       f"pass fmt= (one of {', '.join(FORMATS)})")


__all__ = [
    "EXPORT_OPTIONS",
    "FORMATS",
    "IMPORT_OPTIONS",
    "FormatError",
    "export_certificate",
    "guess_format",
    "import_certificate",
    "read_certificate_json",
]
