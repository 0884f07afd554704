"""senseFly autopilot metadata (``XMP-sensefly``) of eBee / Swinglet CAM images.

Fields (namespace ``http://ns.sensefly.com/sensefly/1.0/``, one element each, as written on ``seneca``):
``Latitude``, ``Longitude`` (WGS84 degrees), ``AltitudeWGS84`` (ellipsoidal height, m),
``AltitudeAMSL`` (above mean sea level, m), ``Height`` (above the take-off point, m), ``RollAngle``,
``PitchAngle``, ``Heading`` (aircraft attitude, degrees; aerospace Z-Y-X, see
:func:`aerocal.geometry.body_rpy_to_R_cw`), ``GroundSpeed``, ``AirSpeed`` (m/s), ``Course`` (0 on
``seneca``: not recorded), ``UTCTime`` (GNSS time, UTC), ``CamID``, ``AutopilotSN``, ``FrameSN``.

A name mapping over :func:`aerocal.ingest.xmp.parse_xmp`, not a parser: Pillow's ``getxmp`` gives these
values by local name only (without the ``sensefly`` namespace) inside a list of two descriptions on
``seneca``, so it is not used (see :mod:`aerocal.ingest.xmp`).
"""

from __future__ import annotations

from aerocal.ingest.recorded_pose import RecordedPose

PREFIX = "sensefly:"
_EXTRA_NUMBERS = {
    "AltitudeAMSL": "sensefly_altitude_amsl_m",
    "Height": "sensefly_height_above_takeoff_m",
    "GroundSpeed": "sensefly_ground_speed_mps",
    "AirSpeed": "sensefly_air_speed_mps",
    "Course": "sensefly_course_deg",
}
_EXTRA_TEXT = {
    "CamID": "sensefly_cam_id",
    "AutopilotSN": "sensefly_autopilot_serial",
    "FrameSN": "sensefly_frame_serial",
}


def has_sensefly(xmp: dict[str, str]) -> bool:
    return any(k.startswith(PREFIX) for k in xmp)


def read_sensefly(xmp: dict[str, str]) -> RecordedPose:
    """The pose senseFly recorded; attitude convention ``"body_rpy"``; height ellipsoidal (AltitudeWGS84)."""
    pose = RecordedPose(
        source="xmp:sensefly", convention="body_rpy", alt_reference="ellipsoidal (AltitudeWGS84)"
    )

    def number(name: str) -> float | None:
        return pose.number(xmp, PREFIX + name)

    pose.lat, pose.lon = number("Latitude"), number("Longitude")
    pose.alt = number("AltitudeWGS84")
    if pose.alt is None and PREFIX + "AltitudeWGS84" not in xmp:
        pose.alt = number("AltitudeAMSL")
        pose.alt_reference = "mean sea level (AltitudeAMSL)"
    pose.roll, pose.pitch, pose.yaw = number("RollAngle"), number("PitchAngle"), number("Heading")
    for name, key in _EXTRA_NUMBERS.items():
        value = number(name)
        if value is not None:
            pose.extra[key] = value
    for name, key in _EXTRA_TEXT.items():
        if xmp.get(PREFIX + name):
            pose.extra[key] = xmp[PREFIX + name][:200]
    if xmp.get(PREFIX + "UTCTime"):
        pose.utc_time = xmp[PREFIX + "UTCTime"][:64]
        pose.extra["sensefly_utc_time"] = pose.utc_time
    return pose
