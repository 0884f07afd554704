"""Parrot drone metadata (``XMP-drone-parrot``) of Anafi and Bebop images.

Fields (namespace ``http://www.parrot.com/drone-parrot/1.0/``): ``CameraRollDegree``, ``CameraPitchDegree``,
``CameraYawDegree``: the camera's attitude, as gimbal angles with DJI's meaning (pitch -90 looking straight
down, yaw the heading clockwise from north; public readers of Parrot files treat them as DJI's
``GimbalRollDegree``/``GimbalPitchDegree``/``GimbalYawDegree``), read in convention ``"dji_gimbal"``
(:func:`aerocal.geometry.dji_gimbal_to_R_cw`). The position is EXIF GPS (Parrot writes none in XMP); the height
above ground, where the camera records it, is Pix4D's ``Camera:AboveGroundAltitude``
(:data:`aerocal.ingest.metadata.PIX4D_CAMERA_NUMBERS`).

A name mapping over :func:`aerocal.ingest.xmp.parse_xmp`, as :mod:`aerocal.ingest.dji` and
:mod:`aerocal.ingest.sensefly` are.
"""

from __future__ import annotations

from aerocal.ingest.recorded_pose import RecordedPose

PREFIX = "drone-parrot:"


def has_parrot(xmp: dict[str, str]) -> bool:
    return any(k.startswith(PREFIX) for k in xmp)


def read_parrot(xmp: dict[str, str]) -> RecordedPose:
    """The camera attitude Parrot recorded; convention ``"dji_gimbal"``; the position comes from EXIF GPS."""
    pose = RecordedPose(source="xmp:drone-parrot")
    pose.roll, pose.pitch, pose.yaw = (pose.number(xmp, PREFIX + name)
                                       for name in ("CameraRollDegree", "CameraPitchDegree", "CameraYawDegree"))
    if any(v is not None for v in (pose.roll, pose.pitch, pose.yaw)):
        pose.convention = "dji_gimbal"
    return pose
