"""Flight simulator: scenes, flight plans, sensors, hidden effects, observations and rendered images.

The tool the science tests with, never a part of processing (no processing module imports it): a preset
(:mod:`presets`) names a camera, a scene (:mod:`scene`), a flight plan (:mod:`flight_plan`), the GNSS/IMU and
sensor temperature (:mod:`sensors`) and the catalogue effects hidden in the data; :mod:`observations` writes
image measurements directly, :mod:`raycast` and :mod:`rendered_frames` render the frames a camera would record,
:mod:`faults` spoils a folder the way field data is spoiled, and :mod:`measured` reads a preset's flight
plan, attitudes, times and temperatures from real images. The truth is written beside the data
(``truth.json``) for tests and studies to judge with.

Entry points: :func:`simulate_flight` (in memory) and :func:`write_flight` (a flight folder).

Tests: tests/test_simulate.py, tests/test_scene.py, tests/test_raycast.py, tests/test_rendered_flight.py.
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
