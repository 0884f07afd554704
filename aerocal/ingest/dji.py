"""DJI metadata: ``XMP-drone-dji`` fields and the radiometric JPEG (R-JPEG) of thermal cameras.

XMP (namespace ``http://www.dji.com/drone-dji/1.0/``, attributes of ``rdf:Description``):
``GpsLatitude``, ``GpsLongitude`` (older firmware: ``GpsLongtitude``) in WGS84 degrees,
``AbsoluteAltitude`` (m; DJI does not document its vertical reference, which differs between models
and RTK/non-RTK modes), ``RelativeAltitude`` (m above the take-off point), ``GimbalRoll/Pitch/YawDegree``
(the camera's attitude: yaw clockwise from north, pitch -90 = nadir; see
:func:`aerocal.geometry.dji_gimbal_to_R_cw`), ``FlightRoll/Pitch/YawDegree`` (the aircraft's),
``FlightX/Y/ZSpeed`` (m/s), ``LRFTargetDistance`` and friends (laser range finder), RTK fields.

R-JPEG (H20T, H20N, M2EA, M30T, M3T, H30T, XT S): the visible part is an 8-bit false-colour preview; the
raw sensor frame is stored little-endian uint16, row-major, split over consecutive APP3 segments
(APP4 on the XT S; concatenate their payloads; 640 x 512 x 2 = 655360 bytes on the H20T). The Zenmuse XT
and XT2 are FLIR cores and write FLIR's own format instead (:mod:`aerocal.ingest.flir`). On the H20T the
APP4 segment holds a DJI parameter block; float32 values at byte offsets 132, 136 and 156 drift smoothly
over a flight (27.4 -> 26.7, 28.7 -> 28.1, 25.3 -> 24.9 on ``h20t_forest``) and read as internal camera
temperatures in degC. This reading is **not documented by DJI**: they are reported as
``dji_app4_f132_undocumented`` etc. and are used as the sensor temperature only when the user opts in
(``IngestConfig.dji_app4_temperature``). On the M2EA, M30T and H30T the same bytes hold zeros or values
like 1e28, so they are read on the H20T only.

Kept as our own reader: no installed library reads R-JPEG data (Pillow returns the APP3/APP4 payloads as
opaque bytes in ``applist``; tifffile reads no JPEG; DJI's Thermal SDK is a closed binary library, not a
package), and the XMP fields are a name mapping over :func:`aerocal.ingest.xmp.parse_xmp` (Pillow's
``getxmp`` loses the ``drone-dji`` namespace, see :mod:`aerocal.ingest.xmp`).
"""

from __future__ import annotations

import struct

import numpy as np

from aerocal.ingest.jpeg import JpegStructure
from aerocal.ingest.recorded_pose import RecordedPose

PREFIX = "drone-dji:"
APP3, APP4 = 0xE3, 0xE4
#: raw frame sizes of DJI thermal cameras, tried when the APP3 length does not match the JPEG frame size
KNOWN_RAW_SIZES = ((640, 512), (1280, 1024), (320, 256), (640, 480), (336, 256), (160, 120))
APP4_FLOAT_OFFSETS = (132, 136, 156)

_EXTRA_NUMBERS = {
    "RelativeAltitude": "dji_relative_altitude_m",
    "FlightRollDegree": "dji_flight_roll_deg",
    "FlightPitchDegree": "dji_flight_pitch_deg",
    "FlightYawDegree": "dji_flight_yaw_deg",
    "FlightXSpeed": "dji_flight_x_speed_mps",
    "FlightYSpeed": "dji_flight_y_speed_mps",
    "FlightZSpeed": "dji_flight_z_speed_mps",
    "LRFTargetDistance": "dji_lrf_target_distance_m",
    "LRFTargetLat": "dji_lrf_target_lat_deg",
    "LRFTargetLon": "dji_lrf_target_lon_deg",
    "LRFTargetAlt": "dji_lrf_target_alt_m",
    "LRFTargetAbsAlt": "dji_lrf_target_abs_alt_m",
    "RtkStdLon": "dji_rtk_std_lon_m",
    "RtkStdLat": "dji_rtk_std_lat_m",
    "RtkStdHgt": "dji_rtk_std_hgt_m",
}
_EXTRA_TEXT = {
    "ImageSource": "dji_image_source",
    "AltitudeType": "dji_altitude_type",
    "GpsStatus": "dji_gps_status",
    "LRFStatus": "dji_lrf_status",
    "RtkFlag": "dji_rtk_flag",
}


def app4_field_name(offset: int) -> str:
    """Column name of an undocumented APP4 float in ``extra``."""
    return f"dji_app4_f{offset}_undocumented"


def has_dji(xmp: dict[str, str]) -> bool:
    return any(k.startswith(PREFIX) for k in xmp)


def read_dji_xmp(xmp: dict[str, str]) -> RecordedPose:
    """The pose in DJI XMP; attitude = gimbal angles, convention ``"dji_gimbal"``."""
    pose = RecordedPose(source="xmp:drone-dji", alt_reference="DJI AbsoluteAltitude (reference undocumented)")

    def number(name: str) -> float | None:
        return pose.number(xmp, PREFIX + name)

    pose.lat = number("GpsLatitude")
    lon_name = "GpsLongitude" if PREFIX + "GpsLongitude" in xmp else "GpsLongtitude"
    pose.lon = number(lon_name)
    pose.alt = number("AbsoluteAltitude")
    pose.roll, pose.pitch, pose.yaw = (
        number("GimbalRollDegree"),
        number("GimbalPitchDegree"),
        number("GimbalYawDegree"),
    )
    if any(v is not None for v in (pose.roll, pose.pitch, pose.yaw)):
        pose.convention = "dji_gimbal"
    for name, key in _EXTRA_NUMBERS.items():
        value = number(name)
        if value is not None:
            pose.extra[key] = value
    for name, key in _EXTRA_TEXT.items():
        if xmp.get(PREFIX + name):
            pose.extra[key] = xmp[PREFIX + name][:200]
    return pose


def raw_thermal_segments(jpeg: JpegStructure) -> tuple[int, int, int] | None:
    """(APPn marker, width, height) of the raw uint16 frame of a DJI R-JPEG, or ``None`` if there is none.

    The raw frame is in the APP3 segments (H20T, H20N, M2EA, M30T, M3T, H30T) or, on the Zenmuse XT S, in
    the APP4 segments (its APP3 then holds a 32 KiB block that is not the frame). A segment group holds the
    frame when its payload length equals 2 x width x height: of the JPEG frame size first (H30T
    1280 x 1024), else of one of :data:`KNOWN_RAW_SIZES` (the M30T's 1280 x 1024 preview of a 640 x 512
    frame).
    """
    for marker in (APP3, APP4):
        total = sum(len(p) for p in jpeg.app(marker))
        if total == 0:
            continue
        if total == 2 * jpeg.width * jpeg.height:
            return marker, jpeg.width, jpeg.height
        for w, h in KNOWN_RAW_SIZES:
            if total == 2 * w * h:
                return marker, w, h
    return None


def raw_thermal_layout(jpeg: JpegStructure) -> tuple[int, int] | None:
    """(width, height) of the raw uint16 frame of a DJI R-JPEG (:func:`raw_thermal_segments`), or ``None``."""
    found = raw_thermal_segments(jpeg)
    return None if found is None else found[1:]


def raw_thermal_frame(jpeg: JpegStructure) -> np.ndarray | None:
    """The raw thermal frame (uint16 counts, shape (height, width)) of a DJI R-JPEG, or ``None``.

    DJI stores counts only; their conversion to temperature is in DJI's Thermal SDK and is not documented,
    so no temperature is derived from them here.
    """
    found = raw_thermal_segments(jpeg)
    if found is None:
        return None
    marker, w, h = found
    raw = b"".join(jpeg.app(marker))
    return np.frombuffer(raw, dtype="<u2").reshape(h, w).astype(np.uint16)


def app4_floats(jpeg: JpegStructure) -> dict[int, float]:
    """The float32 (little-endian) values at :data:`APP4_FLOAT_OFFSETS` of the first APP4 segment.

    Values are returned as read (possibly NaN or absurd); the caller checks them.
    """
    segments = jpeg.app(APP4)
    found = raw_thermal_segments(jpeg)
    if not segments or (found is not None and found[0] == APP4):
        return {}
    block = segments[0]
    out: dict[int, float] = {}
    for off in APP4_FLOAT_OFFSETS:
        if off + 4 <= len(block):
            out[off] = float(struct.unpack_from("<f", block, off)[0])
    return out
