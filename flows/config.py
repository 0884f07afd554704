"""The configuration of a flight's processing: one typed dataclass per step, recorded with each run."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from aerocal.adjust import AdjustConfig, ThinningConfig
from tasks.block import BlockStepConfig
from tasks.calibration import CalibrationStepConfig
from tasks.control import ControlStepConfig
from tasks.flight import IngestStepConfig, MatchStepConfig, OrientStepConfig
from tasks.products import MosaicStepConfig, ReportStepConfig
from tasks.resume import configuration_json

#: values of ``certificate`` that are not certificate ids
CERTIFICATE_MODES = ("auto", "none")


@dataclass
class ProcessConfig:
    """Everything :func:`flows.flight.process_flight` can be told (defaults documented per step class).

    * ``max_certificate_age_days``: a stored certificate older than this (days between its calibration
      and the flight) is not reused (default ``None``: no age limit).
    * ``use_flight_sigmas``: GNSS and IMU sigmas declared by the flight (``flight.json``:
      ``gnss_sigma_m`` [horizontal, vertical], ``imu_sigma_deg``) replace the adjustments' a-priori
      sigmas (default True); the run records the effective values.
    * ``matched_robust_loss``: robust loss of the adjustments when the observations come from image
      matching ("huber", default: a few wrong matches survive geometric verification and, unweighted,
      can make a tie point's normal matrix singular); observations given by the flight keep the
      adjustment configurations' own loss.
    * ``matched_tie_thinning``: :class:`aerocal.adjust.thinning.ThinningConfig` of the full-block
      adjustment when the observations come from image matching (default: its defaults, 4 tracks per cell
      of 8 x 6 per image; ``None``: every track adjusted). The tracks left out are intersected afterwards
      from the adjusted poses, so the DSM still gets every tie point (``AdjustConfig.tie_thinning``).
      The self-calibration and the diagnosis adjust every track: on the real seneca flight the thinned
      calibration sub-block lost the focal length's temperature slope (t 0.7 instead of 7.0) and its
      certificate moved 43 px in f; a certificate serves many flights, so its precision is worth the
      seconds (33 s against 10 s there, same machine, idle).
    * ``diagnose``: :class:`aerocal.diagnose.engine.DiagnoseConfig` (``None``: its defaults, the reference
      temperature from the certificate's thermal model).
    """

    ingest: IngestStepConfig = field(default_factory=IngestStepConfig)
    match: MatchStepConfig = field(default_factory=MatchStepConfig)
    orient: OrientStepConfig = field(default_factory=OrientStepConfig)
    control: ControlStepConfig = field(default_factory=ControlStepConfig)
    calibration: CalibrationStepConfig = field(default_factory=CalibrationStepConfig)
    block: BlockStepConfig = field(default_factory=BlockStepConfig)
    mosaic: MosaicStepConfig = field(default_factory=MosaicStepConfig)
    diagnose: Any = None
    report: ReportStepConfig = field(default_factory=ReportStepConfig)
    max_certificate_age_days: float | None = None
    use_flight_sigmas: bool = True
    matched_robust_loss: str = "huber"
    matched_tie_thinning: ThinningConfig | None = field(default_factory=ThinningConfig)

    def to_json(self) -> dict:
        """The configuration as plain JSON (what a run records)."""
        return configuration_json(self)


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
