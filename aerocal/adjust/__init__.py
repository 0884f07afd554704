"""Bundle adjustment with self-calibration, thermal IO model, GNSS/IMU priors and weighted ground control.

Entry points: :func:`adjust` (tables in, :class:`AdjustmentResult` out) and :func:`run_strategy`
(Conte 2018's strategies: fixed IO, self-calibration of the whole block, certificate from a subset);
:func:`fit_thermal_model` fits a linear thermal IO model to calibrations at several temperatures.

Tests: tests/test_adjust_core.py, tests/test_adjust_robust.py, tests/test_adjust_partition.py,
tests/test_adjust_selection.py, tests/test_adjust_thinning.py, tests/test_adjust_papers.py,
tests/test_adjust_laser.py, tests/test_conte_strategies.py, tests/test_thermal_model.py.
"""

from aerocal.adjust.bundle import AdjustmentResult, adjust, corrected_to_t0, scale_tie_sigma, screened_rows
from aerocal.adjust.problem import AdjustConfig, AdjustmentError, RobustLoss
from aerocal.adjust.strategy import (
    STRATEGIES,
    StrategyResult,
    adjust_fixed_io,
    long_tracks,
    run_strategy,
    select_images,
)
from aerocal.adjust.thermal import ThermalFit, fit_thermal_model, thermal_certificate
from aerocal.adjust.thinning import ThinningConfig, thin_tracks

__all__ = [
    "STRATEGIES",
    "AdjustConfig",
    "AdjustmentError",
    "AdjustmentResult",
    "RobustLoss",
    "StrategyResult",
    "ThermalFit",
    "ThinningConfig",
    "adjust",
    "adjust_fixed_io",
    "corrected_to_t0",
    "fit_thermal_model",
    "run_strategy",
    "scale_tie_sigma",
    "screened_rows",
    "select_images",
    "long_tracks",
    "thermal_certificate",
    "thin_tracks",
]
