"""Configuration of ingest: every threshold and default, with its unit and why it has that value."""

from __future__ import annotations

from dataclasses import dataclass, field

from aerocal.geometry import CONVENTIONS
from aerocal.ingest.strips import StripConfig

#: DJI APP4 float offsets that read as internal temperatures (undocumented by DJI)
DJI_APP4_OFFSETS = (132, 136, 156)


@dataclass(frozen=True)
class IngestConfig:
    """Settings of :func:`aerocal.ingest.ingest_folder`.

    Ground control:

    * ``gcp_sigma_xy_m`` (0.02 m), ``gcp_sigma_z_m`` (0.03 m): survey standard deviations of GCP coordinates
      when the file gives none (a GNSS RTK survey of targets).
    * ``gcp_pixel_sigma_px`` (1.0 px): standard deviation of a hand-marked GCP image measurement.
    * ``gcp_default_role`` ("control"): role of a GCP whose file gives none ("control" or "check").
    * ``odm_pixel_offset_px`` (0.5 px): added to the pixel coordinates of an OpenDroneMap ``gcp_list.txt``.
      OpenSfM, which reads these files for ODM, puts the centre of the first pixel at (0, 0)
      (``normalized_image_coordinates`` adds 0.5); aerocal puts it at (0.5, 0.5).
    * ``gcp_label_conflict_px`` (2.0 px): two labels measured closer than this in one image are one
      target carrying two names (``copr`` IMG_0031: gcp00 and gcp04 0.6 px apart).
    * ``gcp_label_conflict`` ("drop"): what to do with both measurements of such a conflict: "drop" them
      (reported as errors) or "keep" them (reported as warnings) for the adjustment to sort out.
    * ``unknown_height_sigma_z_m`` (None): when every GCP height of a file is 0.0 (unknown, not sea level),
      the points are kept with their configured sigma_z; set this (e.g. 1000.0) to make them
      planimetric-only control instead.
    * ``gcp_coordinate_tolerance_m`` (0.05 m): largest disagreement tolerated between the coordinates a
      GCP gets in ``gcps.csv`` and in ``gcp_list.txt`` before it is reported.
    * ``gcp_conflict_stop_m`` (1.0 m): beyond this the two files contradict each other (a blunder in one,
      e.g. a point 1000 m off that was once used as control): an error that stops processing.

    Metadata:

    * ``dji_app4_temperature`` (None): opt in to use one of the undocumented DJI APP4 floats (bytes 132,
      136 or 156) as the sensor temperature; by default they are only reported in ``extra``.
    * ``eo_default_attitude`` ("body_rpy"): attitude convention of an EO CSV without an ``# attitude:`` line.
    * ``temperature_range_c`` ((-60, 120) degC): plausible camera temperatures; outside -> reported, nulled.
    * ``altitude_range_m`` ((-500, 12000) m): plausible flying heights; outside -> reported, nulled.
    * ``time_zone_from_gnss`` (True): when DateTimeOriginal has no offset tag but the image carries a GNSS
      UTC time (EXIF GPS time, senseFly UTCTime), take the time zone as their difference rounded to 15 min.

    Files:

    * ``image_extensions`` (.jpg .jpeg .tif .tiff): files read as images (by content, not by extension).
    * ``max_file_bytes`` (2 GiB): larger files are skipped with an error instead of being read.
    * ``strips``: the strip rule's thresholds (:class:`~aerocal.ingest.strips.StripConfig`).
    """

    gcp_sigma_xy_m: float = 0.02
    gcp_sigma_z_m: float = 0.03
    gcp_pixel_sigma_px: float = 1.0
    gcp_default_role: str = "control"
    odm_pixel_offset_px: float = 0.5
    gcp_label_conflict_px: float = 2.0
    gcp_label_conflict: str = "drop"
    unknown_height_sigma_z_m: float | None = None
    gcp_coordinate_tolerance_m: float = 0.05
    gcp_conflict_stop_m: float = 1.0
    dji_app4_temperature: int | None = None
    eo_default_attitude: str = "body_rpy"
    temperature_range_c: tuple[float, float] = (-60.0, 120.0)
    altitude_range_m: tuple[float, float] = (-500.0, 12000.0)
    time_zone_from_gnss: bool = True
    image_extensions: tuple[str, ...] = (".jpg", ".jpeg", ".tif", ".tiff")
    max_file_bytes: int = 2 * 1024**3
    strips: StripConfig = field(default_factory=StripConfig)

    def __post_init__(self) -> None:
        for name in ("gcp_sigma_xy_m", "gcp_sigma_z_m", "gcp_pixel_sigma_px", "gcp_label_conflict_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"IngestConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.gcp_default_role not in ("control", "check"):
            raise ValueError(
                f"IngestConfig.gcp_default_role must be 'control' or 'check', got {self.gcp_default_role!r}"
            )
        if self.gcp_label_conflict not in ("drop", "keep"):
            raise ValueError(
                f"IngestConfig.gcp_label_conflict must be 'drop' or 'keep', got {self.gcp_label_conflict!r}"
            )
        if self.unknown_height_sigma_z_m is not None and not self.unknown_height_sigma_z_m > 0:
            raise ValueError(
                "IngestConfig.unknown_height_sigma_z_m must be > 0 or None, "
                f"got {self.unknown_height_sigma_z_m}"
            )
        if self.dji_app4_temperature is not None and self.dji_app4_temperature not in DJI_APP4_OFFSETS:
            raise ValueError(
                f"IngestConfig.dji_app4_temperature must be one of {DJI_APP4_OFFSETS} or None, "
                f"got {self.dji_app4_temperature!r}"
            )
        if self.eo_default_attitude not in CONVENTIONS:
            raise ValueError(
                f"IngestConfig.eo_default_attitude {self.eo_default_attitude!r} unknown; "
                f"valid: {', '.join(CONVENTIONS)}"
            )
        for name in ("temperature_range_c", "altitude_range_m"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ValueError(f"IngestConfig.{name} must be (low, high) with low < high, got {(lo, hi)}")
        if self.max_file_bytes <= 0:
            raise ValueError(f"IngestConfig.max_file_bytes must be > 0, got {self.max_file_bytes}")
