"""Every configuration refuses a value that could not be meant where it is made, naming the class, the field and
the value, instead of failing (or silently misbehaving) steps later."""

import pytest

from aerocal.adjust.control import ControlScreeningConfig
from aerocal.calibrate.heldout import HeldOutConfig
from aerocal.calibrate.self_calibration import CalibrationConfig
from aerocal.calibrate.subset import SubsetConfig
from aerocal.certificates.review import DecisionConfig
from aerocal.certificates.selection import SelectionRules
from aerocal.diagnose.engine import DiagnoseConfig
from aerocal.matching.cluster import ExecutionConfig
from aerocal.orient import IncrementalConfig
from aerocal.pipeline.config import (
    BlockStepConfig,
    ControlStepConfig,
    MatchStepConfig,
    MosaicStepConfig,
    OrientStepConfig,
    ReportStepConfig,
)
from aerocal.pipeline.dataset import IngestStepConfig
from aerocal.simulate.flight_plan import FlightPlanConfig
from aerocal.simulate.sensors import SensorConfig
from flows.demo import DemoConfig

BAD = [
    (lambda: HeldOutConfig(folds=1), "HeldOutConfig.folds"),
    (lambda: CalibrationConfig(subset_images=(1, 2), subset_names=("a",)), "not both"),
    (lambda: CalibrationConfig(subset_names=()), "CalibrationConfig.subset_names is empty"),
    (lambda: SubsetConfig(images_per_strip=(1,)), "SubsetConfig.images_per_strip"),
    (lambda: DecisionConfig(certified_focal_sigma=0.0), "DecisionConfig.certified_focal_sigma"),
    (lambda: DiagnoseConfig(hypotheses=("rolling_shuter",)), "rolling_shuter"),
    (lambda: DiagnoseConfig(family_alpha=1.5), "DiagnoseConfig.family_alpha"),
    (lambda: ExecutionConfig(local_workers=-1), "ExecutionConfig.local_workers"),
    (lambda: IncrementalConfig(min_model_size=1), "IncrementalConfig.min_model_size"),
    (lambda: IncrementalConfig(camera_model="SIMPLE_RADIAL_FISHEYE"), "IncrementalConfig.camera_model"),
    (lambda: ControlScreeningConfig(neighbour_tracks=0), "ControlScreeningConfig.neighbour_tracks"),
    (lambda: ControlScreeningConfig(camera_tolerance=0.0), "ControlScreeningConfig.camera_tolerance"),
    (lambda: ControlScreeningConfig(min_points_for_scatter=1), "ControlScreeningConfig.min_points_for_scatter"),
    (lambda: MatchStepConfig(min_overlap=1.0), "MatchStepConfig.min_overlap"),
    (lambda: MatchStepConfig(max_pairs_per_image=0), "MatchStepConfig.max_pairs_per_image"),
    (lambda: BlockStepConfig(partition_max_images=0), "BlockStepConfig.partition_max_images"),
    (lambda: MosaicStepConfig(serial_max_megapixels=-1.0), "MosaicStepConfig.serial_max_megapixels"),
    (lambda: ReportStepConfig(measured_within_m=0.0), "ReportStepConfig.measured_within_m"),
    (lambda: ReportStepConfig(figures="no"), "ReportStepConfig.figures"),
    (lambda: FlightPlanConfig(direction="diagonal"), "FlightPlanConfig.direction"),
    (lambda: FlightPlanConfig(side_overlap=1.2), "side_overlap"),
    (lambda: SensorConfig(gnss_sigma_h_m=float("nan")), "SensorConfig"),
    (lambda: IngestStepConfig(gcp_file=""), "IngestStepConfig.gcp_file"),
    (lambda: IngestStepConfig(gcp_file=()), "IngestStepConfig.gcp_file"),
    (lambda: IngestStepConfig(gcp_file=("gcps.csv", " ")), "IngestStepConfig.gcp_file"),
    (lambda: IngestStepConfig(eo_file="  "), "IngestStepConfig.eo_file"),
    (lambda: IngestStepConfig(crs=""), "IngestStepConfig.crs"),
    (lambda: IngestStepConfig(flight_name=7), "IngestStepConfig.flight_name"),
    (lambda: OrientStepConfig(incremental={"min_model_size": 3}), "OrientStepConfig.incremental"),
    (lambda: ControlStepConfig(screening=None), "ControlStepConfig.screening"),
    (lambda: ControlStepConfig(enabled="no"), "ControlStepConfig.enabled"),
    (lambda: SelectionRules(temperature_tolerance_c=-1.0), "SelectionRules.temperature_tolerance_c"),
    (lambda: SelectionRules(thermal_tolerance_c=float("nan")), "SelectionRules.thermal_tolerance_c"),
    (lambda: SelectionRules(accept_unrecorded_temperature="no"), "SelectionRules.accept_unrecorded_temperature"),
    (lambda: DemoConfig(preset="conte-calibratoin"), "DemoConfig.preset"),
    (lambda: DemoConfig(seed=-1), "DemoConfig.seed"),
    (lambda: DemoConfig(max_images=1), "DemoConfig.max_images"),
    (lambda: DemoConfig(effects=(("rolling_shutter", (0.01, 0.02)),)), "DemoConfig.effects"),
    (lambda: DemoConfig(effects=(("rolling_shuter", (0.01,)),)), "DemoConfig.effects"),
    (lambda: DemoConfig(effects=(("rolling_shutter", (0.01,)), ("rolling_shutter", (0.02,)))), "DemoConfig.effects"),
    (lambda: DemoConfig(wind_m_s=(60.0, 0.0)), "DemoConfig.wind_m_s"),
    (lambda: DemoConfig(wind_m_s=(float("nan"), 0.0)), "DemoConfig.wind_m_s"),
    (lambda: DemoConfig(frames=-1), "DemoConfig.frames"),
]


@pytest.mark.parametrize("make, names", BAD, ids=[b[1] for b in BAD])
def test_a_value_that_cannot_be_meant_is_refused_by_name(make, names):
    with pytest.raises(ValueError, match=names):
        make()


def test_the_defaults_are_valid():
    for cls in (HeldOutConfig, CalibrationConfig, SubsetConfig, DecisionConfig, DiagnoseConfig, ExecutionConfig,
                IncrementalConfig, MatchStepConfig, BlockStepConfig, MosaicStepConfig, ReportStepConfig,
                FlightPlanConfig, SensorConfig, IngestStepConfig, OrientStepConfig, ControlStepConfig, SelectionRules,
                DemoConfig, ControlScreeningConfig):
        cls()
