"""The configuration of a flight's processing: one typed dataclass per step, and :class:`ProcessConfig`.

A run records the whole configuration (:meth:`ProcessConfig.to_json`) and the adjustment settings in effect
(:func:`effective_adjustments`: the flight's declared sigmas, the robust loss and tie thinning of matched
blocks, no GNSS/IMU priors for a block oriented by SfM).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from aerocal.adjust import AdjustConfig, ThinningConfig
from aerocal.adjust.control import ControlScreeningConfig
from aerocal.adjust.problem import ROBUST_LOSSES, RobustLoss
from aerocal.calibrate.self_calibration import CalibrationConfig
from aerocal.diagnose.engine import DiagnoseConfig
from aerocal.enhance import EnhanceConfig
from aerocal.matching import FeatureConfig, MatchConfig
from aerocal.matching.retrieval import RetrievalConfig
from aerocal.orient import IncrementalConfig
from aerocal.pipeline.dataset import IngestStepConfig
from aerocal.pipeline.runner import configuration_json
from aerocal.products.dense import DenseConfig
from aerocal.products.dsm import DsmConfig
from aerocal.products.mosaic import MosaicConfig
from aerocal.products.terrain import GroundFilterConfig


class CertificateMode(StrEnum):
    """Values of ``certificate`` that are not certificate ids (a certificate id pins that certificate)."""

    AUTO = "auto"  #: the stored certificate that applies, else self-calibrate and issue one
    NONE = "none"  #: always self-calibrate
    #: the flight's nominal camera as given in its camera.json (e.g. a metric camera's laboratory calibration):
    #: neither calibrated nor stored
    NOMINAL = "nominal"


CERTIFICATE_MODES = tuple(m.value for m in CertificateMode)
#: the ``certificate`` mode that adjusts the block with the nominal camera
NOMINAL = CertificateMode.NOMINAL

@dataclass(frozen=True)
class MatchStepConfig:
    """Enhance and match settings (defaults: :class:`aerocal.enhance.EnhanceConfig`,
    :class:`aerocal.matching.FeatureConfig`, :class:`aerocal.matching.MatchConfig`); ``min_overlap`` of
    candidate footprints (0.1); ``max_pairs_per_image`` (None: every candidate; N: each image keeps its N
    candidates of largest footprint overlap, a pair staying where either image keeps it). No cap by default: ranked
    by overlap, a frame's best pairs are its own strip's, and a cap cuts the pairs across strips first, which
    determine the focal length (``benchmarks/RESULTS.md``, "Candidate pairs: a cap by overlap").
    Flights without a recorded position and attitude for every image score all pairs by a coarse match of their
    strongest keypoints and match in full those it retrieves (``retrieval``, default
    :class:`aerocal.matching.retrieval.RetrievalConfig`), up to ``exhaustive_max_images`` (150, ~11,000 pairs
    scored). Flights of at most ``serial_max_megapixels`` (10) in all are matched in this process without a local
    cluster: a fresh cluster's start and worker imports cost more than the work for small flights
    (``benchmarks/history/engine_measurements.md``)."""

    enhance: EnhanceConfig | None = None
    features: FeatureConfig | None = None
    match: MatchConfig | None = None
    retrieval: RetrievalConfig | None = None
    min_overlap: float = 0.1
    max_pairs_per_image: int | None = None  #: None: every candidate pair
    exhaustive_max_images: int = 150
    serial_max_megapixels: float = 10.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_overlap < 1.0:
            raise ValueError(f"MatchStepConfig.min_overlap must be a fraction in [0, 1), got {self.min_overlap}")
        if self.max_pairs_per_image is not None and self.max_pairs_per_image < 1:
            raise ValueError(f"MatchStepConfig.max_pairs_per_image must be at least 1 (or None: every pair), got "
                             f"{self.max_pairs_per_image}")
        if self.exhaustive_max_images < 2:
            raise ValueError(f"MatchStepConfig.exhaustive_max_images must be 2 or more, got "
                             f"{self.exhaustive_max_images}")
        if self.serial_max_megapixels < 0:
            raise ValueError(f"MatchStepConfig.serial_max_megapixels must be 0 or more, got "
                             f"{self.serial_max_megapixels}")


@dataclass(frozen=True)
class OrientStepConfig:
    """Initial orientation. With a recorded position and attitude for every image the poses are those
    records (:func:`aerocal.orient.orient_from_priors`). Without them, and when the frames were matched,
    incremental SfM on our matches (:func:`aerocal.orient.orient_incremental`, options ``incremental``,
    default :class:`aerocal.orient.IncrementalConfig`) georeferenced on the control GCPs
    (:func:`aerocal.orient.georeference`); images it cannot register are left out of the block and named."""

    incremental: IncrementalConfig | None = None

    def __post_init__(self) -> None:
        if self.incremental is not None and not isinstance(self.incremental, IncrementalConfig):
            raise ValueError(f"OrientStepConfig.incremental must be None or an IncrementalConfig, got "
                             f"{self.incremental!r}")


@dataclass(frozen=True)
class ControlStepConfig:
    """``screening``: the data snooping's thresholds; ``enabled`` (True): False uses the ground control
    as ingested (the report then says it was not screened)."""

    screening: ControlScreeningConfig = field(default_factory=ControlScreeningConfig)
    enabled: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.screening, ControlScreeningConfig):
            raise ValueError(f"ControlStepConfig.screening must be a ControlScreeningConfig (enabled=False to skip "
                             f"the screening), got {self.screening!r}")
        if not isinstance(self.enabled, bool):
            raise ValueError(f"ControlStepConfig.enabled must be True or False, got {self.enabled!r}")


@dataclass(frozen=True)
class BlockStepConfig:
    """``adjust``: the full-block adjustment (IO is fixed whatever ``adjust.free`` says; default GNSS
    sigmas 0.10/0.10/0.15 m, GCPs weighted by their survey sigmas); ``thermal_correction`` (True): apply
    the certificate's linear thermal model to the measurements; ``recorded_eo_images`` (200): test the
    recorded positions for a GNSS time lag (and, with 3 control GCPs, a horizontal offset) on this many
    central images and remove what passes before adjusting (:func:`aerocal.calibrate.eo_checks.correct_gnss_offset`;
    0 = use the positions as recorded).

    City-scale blocks: from ``partition_min_images`` images (800; 0 = never) the adjustment runs in sub-blocks
    on the Dask cluster (:class:`aerocal.matching.cluster.ExecutionConfig`), at least one per worker and each
    of at most about ``partition_max_images`` (3200) images (:mod:`aerocal.adjust.partition`:
    the same solution as one adjustment, the observations' memory and the point eliminations spread over the
    workers). From 800 images the partitioned adjustment on 2 local workers was faster than the single one, with
    a smaller largest process (``benchmarks/partition_bench.py``, ``benchmarks/history/engine_measurements.md``)."""

    adjust: AdjustConfig = field(default_factory=AdjustConfig)
    thermal_correction: bool = True
    recorded_eo_images: int = 200
    partition_min_images: int = 800
    partition_max_images: int = 3200

    def __post_init__(self) -> None:
        if self.recorded_eo_images < 0 or self.partition_min_images < 0:
            raise ValueError("BlockStepConfig: recorded_eo_images and partition_min_images must be 0 or more, got "
                             f"{self.recorded_eo_images}, {self.partition_min_images}")
        if self.partition_max_images < 1:
            raise ValueError(f"BlockStepConfig.partition_max_images must be 1 or more, got {self.partition_max_images}")


@dataclass(frozen=True)
class MosaicStepConfig:
    """DSM and orthomosaic settings (:class:`aerocal.products.dsm.DsmConfig`,
    :class:`aerocal.products.mosaic.MosaicConfig`; ``None`` = their defaults). The dense surface's pairs and the
    orthomosaic's tiles run on the Dask scheduler given to the run (:class:`aerocal.matching.cluster.ExecutionConfig`).
    Without one, the dense surface runs on a local cluster only for flights of more than ``serial_max_megapixels``
    (100) of frames in all, smaller ones in this process: there OpenCV's semi-global matcher already uses every
    core and nothing is shipped between processes, so a local cluster of worker processes costs more than it gains
    on a block that size (``benchmarks/RESULTS.md``, "The mosaic step in the calling process"); and the
    orthomosaic's tiles always run in this process, on one thread per local worker
    (:func:`aerocal.products.mosaic.build_mosaic`)."""

    dsm: DsmConfig | None = None
    mosaic: MosaicConfig | None = None
    serial_max_megapixels: float = 100.0
    #: the dense surface matched in the frames (:mod:`aerocal.products.dense`), which the DSM and orthomosaic then
    #: stand on; ``None``: the tie points' surface only (the only one for a flight without frames)
    dense: DenseConfig | None = DenseConfig()
    #: how the dense cloud is gridded: about one cell per ground sample, as the cloud holds one point per sample
    dense_dsm: DsmConfig = DsmConfig(cell_gsd=1.0, reject_outliers=False, fill_pinholes=True)
    #: the ground filter that makes the DTM from the dense DSM (:mod:`aerocal.products.terrain`)
    ground_filter: GroundFilterConfig = GroundFilterConfig()

    def __post_init__(self) -> None:
        if self.serial_max_megapixels < 0:
            raise ValueError(f"MosaicStepConfig.serial_max_megapixels must be 0 or more, got "
                             f"{self.serial_max_megapixels}")


@dataclass(frozen=True)
class ReportStepConfig:
    """``title`` of the report (default "Flight report: <flight name>"); ``extra`` key figures added to
    the summary; DSM cells within ``measured_within_m`` (2 m) of a tie point count as measured in the
    DSM-minus-reference statistics; ``figures`` False writes the page and ``summary.json`` with every figure's
    caption and numbers but no picture (rendering them is most of the report's time: a batch that reads
    ``summary.json`` alone)."""

    title: str | None = None
    extra: dict = field(default_factory=dict)
    measured_within_m: float = 2.0
    figures: bool = True

    def __post_init__(self) -> None:
        if not self.measured_within_m > 0:
            raise ValueError(f"ReportStepConfig.measured_within_m must be positive metres, got "
                             f"{self.measured_within_m}")
        if not isinstance(self.figures, bool):
            raise ValueError(f"ReportStepConfig.figures must be True or False, got {self.figures!r}")


@dataclass(frozen=True)
class ProcessConfig:
    """Everything :func:`aerocal.pipeline.process` can be told (defaults documented per step class).

    * ``max_certificate_age_days``: a stored certificate older than this (days between its calibration
      and the flight) is not reused (default ``None``: no age limit).
    * ``use_flight_sigmas``: GNSS and IMU sigmas declared by the flight (``flight.json``:
      ``gnss_sigma_m`` [horizontal, vertical], ``imu_sigma_deg``) replace the adjustments' a-priori
      sigmas (default True); the run records the effective values.
    * ``matched_robust_loss``: :class:`~aerocal.adjust.problem.RobustLoss` (or its string value, held as the
      member) of the adjustments' screening pass when the observations come from image matching ("cauchy",
      default: a few wrong matches survive geometric verification and, unweighted, can make a tie point's
      normal matrix singular); observations given by the flight keep the adjustment configurations' own loss.
      Cauchy rather than Huber because a mismatch keeps a Huber influence that grows with its size, and with
      the IO free it bends the weakest parameters before the screening judges the residuals: on the real
      seneca flight the Huber pass left f, cx and cy undetermined and on the rendered conte-city flight a k3
      the true lens lacks, where the Cauchy pass recovered the lens (``benchmarks/history/engine_measurements.md``).
    * ``matched_tie_thinning``: :class:`aerocal.adjust.thinning.ThinningConfig` of the full-block
      adjustment when the observations come from image matching (default: its defaults, 4 tracks per cell
      of 8 x 6 per image; ``None``: every track adjusted). The tracks left out are intersected afterwards
      from the adjusted poses, so the DSM still gets every tie point (``AdjustConfig.tie_thinning``).
      The self-calibration and the diagnosis adjust every track: on the real seneca flight the thinned
      calibration sub-block lost the focal length's temperature slope, and a certificate serves many flights,
      so its precision is worth the extra time (``benchmarks/history/engine_measurements.md``).
    * ``diagnose``: :class:`aerocal.diagnose.engine.DiagnoseConfig` (``None``: its defaults, the reference
      temperature from the certificate's thermal model).
    * ``extend``: the effects the diagnosis names become the block's model (default True): the block is adjusted
      again with them and every product comes from the extended block; the camera terms (readout, affinity, k3,
      thermal slopes) go into a new version of the camera's certificate, made by calibrating the camera again on
      this flight where it was calibrated here (:mod:`aerocal.pipeline.extend_step`). False: named, not applied.
    """

    ingest: IngestStepConfig = field(default_factory=IngestStepConfig)
    match: MatchStepConfig = field(default_factory=MatchStepConfig)
    orient: OrientStepConfig = field(default_factory=OrientStepConfig)
    control: ControlStepConfig = field(default_factory=ControlStepConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    block: BlockStepConfig = field(default_factory=BlockStepConfig)
    mosaic: MosaicStepConfig = field(default_factory=MosaicStepConfig)
    diagnose: DiagnoseConfig | None = None
    report: ReportStepConfig = field(default_factory=ReportStepConfig)
    max_certificate_age_days: float | None = None
    use_flight_sigmas: bool = True
    matched_robust_loss: RobustLoss = RobustLoss.CAUCHY
    matched_tie_thinning: ThinningConfig | None = field(default_factory=ThinningConfig)
    extend: bool = True

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "matched_robust_loss", RobustLoss(self.matched_robust_loss))
        except ValueError:
            raise ValueError(f"ProcessConfig.matched_robust_loss {self.matched_robust_loss!r} unknown; valid: "
                             f"{', '.join(ROBUST_LOSSES)}") from None
        age = self.max_certificate_age_days
        if age is not None and not age > 0:
            raise ValueError(f"ProcessConfig.max_certificate_age_days must be positive days or None, got {age}")

    def to_json(self) -> dict:
        """The configuration as plain JSON (what a run records)."""
        return configuration_json(self)


@dataclass(frozen=True)
class Adjustments:
    """The adjustment settings in effect for a flight: the self-calibration's and the full block's."""

    calibration: AdjustConfig
    block: AdjustConfig

    def to_json(self) -> dict:
        return {"calibration_adjust": configuration_json(self.calibration),
                "block_adjust": configuration_json(self.block)}


def with_flight_sigmas(config: AdjustConfig, flight: dict) -> AdjustConfig:
    """``config`` with the GNSS (E, N, Up metres) and IMU (degrees) sigmas the flight declares."""
    changes: dict[str, Any] = {}
    gnss = flight.get("gnss_sigma_m")
    if gnss and config.gnss_sigma_m is not None:
        h, v = float(gnss[0]), float(gnss[-1])
        changes["gnss_sigma_m"] = (h, h, v)
    imu = flight.get("imu_sigma_deg")
    if imu:
        changes["attitude_sigma_deg"] = tuple(float(x) for x in imu)
    return dataclasses.replace(config, **changes) if changes else config


def effective_adjustments(config: ProcessConfig, flight: dict, matched: bool) -> Adjustments:
    """The adjustments' settings for this flight: its declared sigmas (``use_flight_sigmas``), and for
    ``matched`` observations (image mode) the robust loss and the block's tie thinning of ``config``."""
    cal, blk = config.calibration.adjust, config.block.adjust
    if config.use_flight_sigmas:
        cal, blk = with_flight_sigmas(cal, flight), with_flight_sigmas(blk, flight)
    if matched and config.matched_robust_loss != RobustLoss.NONE:
        cal = dataclasses.replace(cal, robust_loss=config.matched_robust_loss)
        blk = dataclasses.replace(blk, robust_loss=config.matched_robust_loss)
    if matched and config.matched_tie_thinning is not None:
        blk = dataclasses.replace(blk, tie_thinning=config.matched_tie_thinning)
    return Adjustments(cal, blk)


def without_recorded_eo(adjustments: Adjustments) -> Adjustments:
    """No GNSS/IMU priors: a block oriented by SfM starts from poses that are not measurements; the datum comes
    from the control GCPs."""
    return Adjustments(dataclasses.replace(adjustments.calibration, gnss_sigma_m=None, attitude_sigma_deg=None),
                       dataclasses.replace(adjustments.block, gnss_sigma_m=None, attitude_sigma_deg=None))
