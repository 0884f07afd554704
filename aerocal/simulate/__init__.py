"""Flight simulator: scenes, flight plans, sensors, hidden effects, observations and rendered images.

Entry points: :func:`simulate_flight` (in memory) and :func:`write_flight` (a flight folder).
"""

from aerocal.simulate.presets import PRESETS, FlightSpec, PresetError, get_preset
from aerocal.simulate.simulator import (
    MODES,
    SimulatedFlight,
    SimulationError,
    as_dataset,
    simulate_flight,
    write_flight,
)

__all__ = [
    "MODES", "PRESETS", "FlightSpec", "PresetError", "SimulatedFlight", "SimulationError", "as_dataset", "get_preset",
    "simulate_flight", "write_flight",
]
