"""Bundle adjustment with self-calibration, thermal IO model, GNSS/IMU priors and weighted ground control.

Entry points: :func:`adjust` (tables in, :class:`AdjustmentResult` out) and :func:`run_strategy`
(Conte 2018's strategies: fixed IO, self-calibration of the whole block, certificate from a subset).
"""

from aerocal.adjust.bundle import AdjustmentResult, adjust
from aerocal.adjust.problem import AdjustConfig, AdjustmentError
from aerocal.adjust.strategy import STRATEGIES, StrategyResult, adjust_fixed_io, run_strategy, select_images

__all__ = [
    "STRATEGIES",
    "AdjustConfig",
    "AdjustmentError",
    "AdjustmentResult",
    "StrategyResult",
    "adjust",
    "adjust_fixed_io",
    "run_strategy",
    "select_images",
]
