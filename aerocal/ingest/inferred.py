"""What a flight's own images say about its camera, flying height and GNSS, when sidecar files are absent.

A folder straight off the drone has no ``camera.json`` and no ``flight.json``. Each function here infers
one of their facts from the image metadata and says where it came from, so that ingest can report it
and processing can use it; each returns ``None`` (with the reason) where the images do not tell.

* :func:`infer_camera`: the nominal camera from :mod:`aerocal.ingest.camera_catalogue`.
* :func:`certificate_identity`: the identity a certificate is stored under. A camera that records no
  serial number is identified by make, model, lens and frame size: its serial part is
  ``"no-serial WxH"`` (:data:`aerocal.certificates.identity.NO_SERIAL`), and such a certificate may be
  shared by several bodies of that model (the certificate store says so).
* :func:`infer_height_agl`: the flying height above ground from DJI's XMP ``RelativeAltitude`` or senseFly's
  ``Height`` (height above the take-off point: above ground where the take-off point is at the ground level
  of the area).
* :func:`infer_gnss_sigma`: the GNSS standard deviations from DJI's RTK fields, or consumer grade for a
  DJI position without RTK.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from aerocal.camera import Camera
from aerocal.certificates.identity import CameraIdentity
from aerocal.ingest.camera_catalogue import nominal_camera
from aerocal.ingest.metadata import ImageMetadata

#: GNSS standard deviations (horizontal, vertical; metres) of a drone position without RTK: the makers
#: state ~1.5 m horizontal hovering accuracy; the altitude mixes GNSS and barometer (several metres)
CONSUMER_GNSS_SIGMA_M = (2.0, 5.0)
#: smallest RTK sigma taken from the images (RtkStd* of 0.01 m would claim more than the block holds)
MIN_RTK_SIGMA_M = 0.02
#: lowest RelativeAltitude median taken as a flying height (below, the images were taken on the ground)
MIN_HEIGHT_AGL_M = 5.0


@dataclass(frozen=True)
class Inferred:
    """A value inferred from the images (``None`` where they do not tell) and one sentence on its source."""

    value: object
    source: str


def _dominant(metas: list[ImageMetadata]) -> tuple[str | None, str | None, int, int]:
    key = Counter((m.make, m.model, m.width, m.height) for m in metas).most_common(1)[0][0]
    return key


def infer_camera(metas: list[ImageMetadata]) -> tuple[Camera | None, str]:
    """The nominal camera of the flight's most common make, model and frame size; (camera, reason)."""
    if not metas:
        return None, "no image was ingested"
    make, model, w, h = _dominant(metas)
    same = [m for m in metas if (m.make, m.model, m.width, m.height) == (make, model, w, h)]

    def median(key: str) -> float | None:
        values = [float(m.extra[key]) for m in same if key in m.extra]
        return float(np.median(values)) if values else None

    result = nominal_camera(make, model, w, h, exif_focal_mm=median("exif_focal_length_mm"),
                            field_of_view_deg=median("flir_field_of_view_deg"),
                            pixel_pitch_mm=median("exif_pixel_pitch_mm"), focal_35mm=median("exif_focal_length_35mm"))
    return result.camera, result.reason


def certificate_identity(
    metas: list[ImageMetadata], given: CameraIdentity | None, camera: Camera | None
) -> CameraIdentity | None:
    """The identity the flight's certificate is stored under: ``camera.json``'s where it names make and
    model, else the images' (most common make and model); the serial is the one the images or
    ``camera.json`` record, else ``"no-serial WxH"``; the lens is the recorded one, else the focal length
    in millimetres where the pixel pitch is known."""
    ident = given if given is not None and given.is_known else None
    if ident is None and metas:
        make, model, w, h = _dominant(metas)
        if not (make or model):
            return given
        same = [m for m in metas if (m.make, m.model) == (make, model)]
        serials = {m.serial for m in same if m.serial}
        lenses = {m.lens for m in same if m.lens}
        ident = CameraIdentity.from_parts(make, model, serials.pop() if len(serials) == 1 else None,
                                          lenses.pop() if len(lenses) == 1 else None)
    if ident is None:
        return None
    if not ident.has_serial:
        w, h = (camera.width, camera.height) if camera is not None else _dominant(metas)[2:]
        ident = ident.serial_less(w, h)
    if not ident.has_lens and camera is not None and camera.pixel_size_mm:
        ident = CameraIdentity(ident.make, ident.model, ident.serial, f"{camera.f * camera.pixel_size_mm:.1f} mm")
    return ident


#: per-image heights above the take-off point an autopilot records: (extra key, what it is)
HEIGHT_ABOVE_TAKEOFF = (
    ("dji_relative_altitude_m", "DJI XMP RelativeAltitude"),
    ("sensefly_height_above_takeoff_m", "senseFly XMP Height"),
    ("xmp_above_ground_altitude_m", "Pix4D XMP Camera:AboveGroundAltitude"),
)


def infer_height_agl(metas: list[ImageMetadata]) -> Inferred:
    """Median height above the take-off point (m) the images' autopilot records, where it is a flying height
    (:data:`HEIGHT_ABOVE_TAKEOFF`: DJI RelativeAltitude, senseFly Height)."""
    for key, name in HEIGHT_ABOVE_TAKEOFF:
        values = [float(m.extra[key]) for m in metas if key in m.extra and np.isfinite(float(m.extra[key]))]
        if not values:
            continue
        med = float(np.median(values))
        if med < MIN_HEIGHT_AGL_M:
            return Inferred(None, f"{name} median {med:.1f} m: the images were not taken in flight")
        return Inferred(
            med,
            f"median {name} of {len(values)} images ({med:.1f} m above the take-off point; a flying height above "
            "ground where the take-off point is at the area's ground level)",
        )
    return Inferred(None, "no image records a height above ground (DJI XMP RelativeAltitude, senseFly XMP Height)")


def infer_gnss_sigma(metas: list[ImageMetadata]) -> Inferred:
    """(horizontal, vertical) GNSS sigmas in metres from the images' DJI records; consumer grade for positions
    an image records without an accuracy (DJI without RTK, senseFly XMP, EXIF GPS); ``None`` for positions that
    come from an EO file or nowhere (the file's author declares them in flight.json)."""
    dji = [m for m in metas if m.pose.source == "xmp:drone-dji" and m.pose.lat is not None]
    xy = [float(m.extra["xmp_gps_xy_accuracy_m"]) for m in metas if "xmp_gps_xy_accuracy_m" in m.extra]
    z = [float(m.extra["xmp_gps_z_accuracy_m"]) for m in metas if "xmp_gps_z_accuracy_m" in m.extra]
    if not dji and xy and z and len(z) >= len(metas) // 2:
        h, v = max(float(np.median(xy)), MIN_RTK_SIGMA_M), max(float(np.median(z)), MIN_RTK_SIGMA_M)
        return Inferred((h, v), f"median XMP Camera:GPSXYAccuracy/GPSZAccuracy of {len(z)} images")
    if not dji:
        recorded = sorted({str(m.pose.source) for m in metas if m.pose.lat is not None
                           and str(m.pose.source) in ("xmp:sensefly", "xmp:drone-parrot", "exif:gps")})
        if not recorded:
            return Inferred(None, "the images carry no position record of their own")
        return Inferred(
            CONSUMER_GNSS_SIGMA_M,
            f"positions from {', '.join(recorded)} without an accuracy record: consumer-grade GNSS assumed "
            f"({CONSUMER_GNSS_SIGMA_M[0]:g} m horizontal, {CONSUMER_GNSS_SIGMA_M[1]:g} m vertical); declare "
            "gnss_sigma_m in flight.json if better",
        )
    lon = [float(m.extra["dji_rtk_std_lon_m"]) for m in dji if "dji_rtk_std_lon_m" in m.extra]
    lat = [float(m.extra["dji_rtk_std_lat_m"]) for m in dji if "dji_rtk_std_lat_m" in m.extra]
    hgt = [float(m.extra["dji_rtk_std_hgt_m"]) for m in dji if "dji_rtk_std_hgt_m" in m.extra]
    if lon and lat and hgt and len(hgt) >= len(dji) // 2:
        h = max(float(np.median(lon)), float(np.median(lat)), MIN_RTK_SIGMA_M)
        v = max(float(np.median(hgt)), MIN_RTK_SIGMA_M)
        return Inferred((h, v), f"median DJI RtkStdLon/Lat/Hgt of {len(hgt)} images")
    return Inferred(
        CONSUMER_GNSS_SIGMA_M,
        f"DJI positions without RTK records: consumer-grade GNSS assumed ({CONSUMER_GNSS_SIGMA_M[0]:g} m "
        f"horizontal, {CONSUMER_GNSS_SIGMA_M[1]:g} m vertical); declare gnss_sigma_m in flight.json if better",
    )
