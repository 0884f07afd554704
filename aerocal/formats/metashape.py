"""Agisoft Metashape (PhotoScan) calibration XML.

Metashape's frame model is aerocal's Brown model (``aerocal/camera.py`` is written as Metashape writes
it): same p1/p2, same b1 (affinity) and b2 (skew), same pixel convention (centre of the first pixel at
(0.5, 0.5)). The only conversion is the principal point, which Metashape stores as an offset from the
image centre: ``cx_metashape = cx - width / 2``, ``cy_metashape = cy - height / 2`` (pixels).

The exporter writes a standalone calibration file (``Tools > Camera Calibration > Load``)::

    <calibration class="adjusted" type="frame">
      <projection>frame</projection> <width/> <height/> <f/> <cx/> <cy/> <b1/> <b2/>
      <k1/> <k2/> <k3/> <p1/> <p2/> <date/>
    </calibration>

A certificate whose camera terms hold a rolling-shutter readout is written instead as a cameras XML
(``File > Import > Import Cameras``) with one ``<sensor>``: the only Metashape file with a rolling-shutter
flag (``<property name="rolling_shutter" value="true"/>``), which turns on Metashape's rolling-shutter
compensation for the sensor. Metashape estimates that compensation per image; it has no field for a readout
time, so the certificate's readout is written in a comment. ``form`` chooses either file explicitly.

The importer reads both files, and the ``<sensor>`` elements of a Metashape cameras XML (``File >
Export > Export Cameras``): the adjusted calibration, the ``pixel_width`` property (mm) and the
``<covariance>`` block (parameter names and their covariance), from which it fills sigmas and the
correlation matrix. k4 and p3/p4 must be zero (the Brown model has none).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from aerocal.camera import PARAM_NAMES, Camera
from aerocal.certificates.document import Certificate, sigmas_and_correlation
from aerocal.certificates.identity import CameraIdentity
from aerocal.certificates.schema import MAX_IMAGE_SIDE_PX
from aerocal.formats.imported import imported_certificate
from aerocal.formats.safe_parsing import FormatError, format_error, parse_xml, read_bytes
from aerocal.io import write_text_atomic

#: Metashape parameters aerocal's model cannot hold; they must be zero (or absent).
UNSUPPORTED_PARAMS = ("k4", "p3", "p4")


#: the two files :func:`write_metashape_xml` writes: a standalone calibration, or a cameras XML with one sensor
FORMS = ("calibration", "sensor")


def write_metashape_xml(cert: Certificate, path: str | Path, form: str | None = None) -> Path:
    """Write ``cert``'s camera as a Metashape XML, atomically: ``form`` "calibration" (the standalone calibration
    file) or "sensor" (a cameras XML with one ``<sensor>``, its pixel size and rolling-shutter flag); ``None``
    chooses "sensor" when the certificate holds a rolling-shutter readout among its camera terms, else
    "calibration".

    Neither file can hold: sigmas, correlations, significance, the thermal model, conditions, provenance, and
    the values of camera terms the block applies to its measurements (a readout, a thermal rotation); those are
    named in a comment. Both hold every Brown parameter including b1 and b2, and the issue time as ``<date>``.
    Raises ``ValueError`` for an unknown ``form``.
    """
    readout = cert.terms.get("rolling_shutter")
    form = form or ("sensor" if readout is not None else "calibration")
    if form not in FORMS:
        raise ValueError(f"Metashape form {form!r}: valid {', '.join(FORMS)}")
    calib = _calibration_element(cert)
    comment = f"aerocal certificate {cert.id} for camera {_comment_safe(cert.identity.key)}"
    held = [f"{name} {', '.join(f'{v:.6g}' for v in t.values)} {t.units} (+- "
            f"{', '.join(f'{v:.2g}' for v in t.sigmas)}, applied to the {t.applied})"
            for name, t in cert.terms.items() if t.applied == "measurements"]
    if held:
        comment += "; camera terms Metashape has no field for: " + "; ".join(_comment_safe(h) for h in held)
    if form == "calibration":
        root = calib
    else:
        cam = cert.camera
        root = ET.Element("document", {"version": "1.5.0"})
        sensors = ET.SubElement(ET.SubElement(root, "chunk", {"label": "aerocal"}), "sensors", {"next_id": "1"})
        sensor = ET.SubElement(sensors, "sensor", {"id": "0", "label": cert.identity.key, "type": "frame"})
        ET.SubElement(sensor, "resolution", {"width": str(cam.width), "height": str(cam.height)})
        if cam.pixel_size_mm:
            for name in ("pixel_width", "pixel_height"):
                ET.SubElement(sensor, "property", {"name": name, "value": repr(float(cam.pixel_size_mm))})
        ET.SubElement(sensor, "property", {"name": "rolling_shutter",
                                           "value": "true" if readout is not None else "false"})
        ET.SubElement(calib, "resolution", {"width": str(cam.width), "height": str(cam.height)})
        sensor.append(calib)
    ET.indent(root)
    text = ('<?xml version="1.0" encoding="UTF-8"?>\n' f"<!-- {comment} -->\n"
            + ET.tostring(root, encoding="unicode") + "\n")
    return write_text_atomic(path, text)


def _calibration_element(cert: Certificate) -> ET.Element:
    """The ``<calibration>`` element of ``cert``'s camera (Metashape's principal point: from the image centre)."""
    cam = cert.camera
    root = ET.Element("calibration", {"class": "adjusted", "type": "frame"})
    values = {
        "projection": "frame",
        "width": str(cam.width),
        "height": str(cam.height),
        "f": repr(float(cam.f)),
        "cx": repr(float(cam.cx - cam.width / 2.0)),
        "cy": repr(float(cam.cy - cam.height / 2.0)),
        "b1": repr(float(cam.b1)),
        "b2": repr(float(cam.b2)),
        "k1": repr(float(cam.k1)),
        "k2": repr(float(cam.k2)),
        "k3": repr(float(cam.k3)),
        "p1": repr(float(cam.p1)),
        "p2": repr(float(cam.p2)),
        "date": cert.issued.strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    for tag, text in values.items():
        ET.SubElement(root, tag).text = text
    return root


def _comment_safe(text: str) -> str:
    return text.replace("--", "- -")


def read_metashape_xml(
    path: str | Path, identity: CameraIdentity | None = None, sensor: str | None = None
) -> Certificate:
    """Read a Metashape calibration XML or cameras XML; ``sensor`` (id or label) chooses among sensors.

    XML is parsed with ``defusedxml``; a document type declaration, entity or external reference is
    refused. Errors name the file, the element and the fix.
    """
    path = Path(path)
    data = read_bytes(path)
    root = parse_xml(path, data)
    if root.tag == "calibration":
        calib, sensor_el = root, None
    else:
        calib, sensor_el = _choose_sensor(path, root, sensor)
    camera, date = _camera(path, calib, sensor_el)
    sigmas, correlation, estimated = {}, None, ()
    if sensor_el is not None and sensor_el.find("covariance") is not None:
        sigmas, correlation, estimated = _covariance(path, sensor_el.find("covariance"))
    return imported_certificate(camera, source=path, data=data, fmt="metashape", identity=identity,
                                sigmas=sigmas, correlation=correlation, estimated=estimated, date=date)


def _choose_sensor(path: Path, root: ET.Element, wanted: str | None) -> tuple[ET.Element, ET.Element]:
    sensors = [s for s in root.iter("sensor") if s.find("calibration") is not None]
    if not sensors:
        raise format_error(path, f"<{root.tag}>", "no <calibration> and no <sensor> with a calibration",
                           "give a Metashape calibration XML or a cameras XML with calibrated sensors")
    names = [f"{s.get('id')} ({s.get('label')})" for s in sensors]
    if wanted is None:
        if len(sensors) > 1:
            raise format_error(path, "<sensor>", f"{len(sensors)} sensors: {', '.join(names)}",
                               "pass sensor= (id or label) to choose one")
        chosen = sensors[0]
    else:
        matches = [s for s in sensors if wanted in (s.get("id"), s.get("label"))]
        if not matches:
            raise format_error(path, "<sensor>", f"no sensor {wanted!r}; the file has {', '.join(names)}",
                               "pass one of those ids or labels as sensor=")
        chosen = matches[0]
    calibs = chosen.findall("calibration")
    adjusted = [c for c in calibs if c.get("class") == "adjusted"]
    return (adjusted or calibs)[0], chosen


def _number(path: Path, el: ET.Element, tag: str, default: float | None = None) -> float:
    child = el.find(tag)
    if child is None:
        if default is None:
            raise format_error(path, f"<{tag}>", "missing", f"add <{tag}> to the <calibration> element")
        return default
    text = (child.text or "").strip()
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise format_error(path, f"<{tag}>", f"expected a number, got {text!r}", "write a decimal number")
    return value


def _size(path: Path, calib: ET.Element, sensor_el: ET.Element | None) -> tuple[int, int]:
    for el in (calib, sensor_el):
        if el is None:
            continue
        res = el.find("resolution")
        if res is not None:
            attrs = (res.get("width"), res.get("height"))
            where = "<resolution>"
        elif el.find("width") is not None:
            attrs = ((el.find("width").text or "").strip(), (el.find("height").text or "").strip()
                     if el.find("height") is not None else None)
            where = "<width>/<height>"
        else:
            continue
        try:
            w, h = (int(a) for a in attrs)
        except (TypeError, ValueError):
            w = h = 0
        if not (0 < w <= MAX_IMAGE_SIDE_PX and 0 < h <= MAX_IMAGE_SIDE_PX):
            shown = tuple(a if a is None or len(a) <= 20 else a[:17] + "..." for a in attrs)
            raise format_error(path, where, f"image size must be two positive integers of at most "
                               f"{MAX_IMAGE_SIDE_PX}, got {shown}",
                               "write the width and height in pixels")
        return w, h
    raise format_error(path, "<width>", "missing image size", "add <width> and <height> (pixels)")


def _camera(path: Path, calib: ET.Element, sensor_el: ET.Element | None) -> tuple[Camera, str | None]:
    kind = calib.get("type") or (calib.findtext("projection") or "frame").strip()
    if kind != "frame":
        raise format_error(path, "<projection>", f"camera type {kind!r} is not a frame camera",
                           "export a frame-camera calibration (fisheye and spherical are not supported)")
    w, h = _size(path, calib, sensor_el)
    f = _number(path, calib, "f")
    if f <= 0:
        raise format_error(path, "<f>", f"focal length must be positive, got {f}", "write f in pixels")
    for tag in UNSUPPORTED_PARAMS:
        v = _number(path, calib, tag, default=0.0)
        if v != 0.0:
            raise format_error(path, f"<{tag}>", f"{tag} = {v:g} cannot be held by the Brown model",
                               f"recalibrate with {tag} fixed at zero")
    tags = ("cx", "cy", "b1", "b2", "k1", "k2", "k3", "p1", "p2")
    vals = {t: _number(path, calib, t, default=0.0) for t in tags}
    pixel_mm = None
    if sensor_el is not None:
        for prop in sensor_el.iter("property"):
            if prop.get("name") == "pixel_width":
                try:
                    pixel_mm = float(prop.get("value", ""))
                except ValueError:
                    pixel_mm = None
                if pixel_mm is not None and not (math.isfinite(pixel_mm) and pixel_mm > 0):
                    pixel_mm = None
    camera = Camera(
        width=w, height=h, f=f, cx=w / 2.0 + vals.pop("cx"), cy=h / 2.0 + vals.pop("cy"),
        pixel_size_mm=pixel_mm, **vals,
    )
    date = (calib.findtext("date") or "").strip()[:10] or None
    if date is not None and not (len(date) == 10 and date[4] == "-" and date[7] == "-"):
        date = None
    return camera, date


def _covariance(path: Path, cov_el: ET.Element) -> tuple[dict[str, float], object, tuple[str, ...]]:
    names = (cov_el.findtext("params") or "").split()
    try:
        coeffs = np.array([float(t) for t in (cov_el.findtext("coeffs") or "").split()])
    except ValueError:
        raise format_error(path, "<covariance><coeffs>", "covariance coefficients must be numbers",
                           "write n x n numbers") from None
    n = len(names)
    if n == 0 or coeffs.size != n * n or not np.all(np.isfinite(coeffs)):
        raise format_error(path, "<covariance>", f"{n} parameters but {coeffs.size} coefficients",
                           "write n x n finite numbers for the n parameters in <params>")
    unknown = [p for p in names if p not in PARAM_NAMES and p not in UNSUPPORTED_PARAMS]
    if unknown:
        raise format_error(path, "<covariance><params>", f"unknown parameters {unknown}",
                           f"use Metashape's names ({', '.join(PARAM_NAMES)})")
    cov = coeffs.reshape(n, n)
    keep = [i for i, p in enumerate(names) if p in PARAM_NAMES]
    kept = tuple(names[i] for i in keep)
    # Marginal covariance of the parameters aerocal holds (k4, p3, p4 are zero: checked by the caller).
    try:
        sigmas, correlation = sigmas_and_correlation(kept, cov[np.ix_(keep, keep)])
    except ValueError as e:
        raise FormatError(f"{path}: <covariance>: {e}") from None
    return sigmas, correlation, kept
