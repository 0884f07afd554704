"""The demo: a small simulated thermal flight with one hidden effect, processed end to end.

:func:`demo` simulates ``conte-calibration`` (the NEC TS9260 thermal camera over a synthetic city) in
observations mode with a hidden effect (a 10 ms rolling-shutter readout, :class:`DemoConfig`), renders a handful
of frames near the block centre so that the orthomosaic has pixels, and runs :func:`flows.process.process_flight`
with every step: ingest, orient, self-calibration with the certificate stored, full-block adjustment with fixed
IO and thermal correction, assessment, diagnosis, the block extended by what the diagnosis names, DSM and
orthomosaic, and the HTML report.

Everything goes under the output folder: the flight, the run folder, the SQLite database and the artifact
store (unless ``AEROCAL_DATABASE_URL`` / ``AEROCAL_ARTIFACT_ROOT`` are set), and Prefect's home (set by
the ``aerocal demo`` command before Prefect is imported; see
:func:`flows.environment.demo_environment`).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from prefect import flow

from aerocal.effects import CATALOGUE, EffectError, effect_values
from aerocal.pipeline import ProcessConfig, RunSummary
from aerocal.simulate import PRESETS, get_preset, simulate_flight, write_flight
from aerocal.simulate.rendered_frames import render_flight_images
from aerocal.simulate.simulator import spec_summary
from flows.environment import demo_environment
from flows.process import FlowInputError, process_flight


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    """The demo flight: ``preset`` (conte-calibration, the 44-image thermal calibration block), ``seed``
    (7), ``max_images`` (None: all frames), ``effects`` (hidden: the microbolometer reads its rows out
    over 10 ms while the aircraft flies 60 m/s through the air, ``rolling_shutter``: a 1.2 px stretch of the
    image's along-track axis, which a Brown model self-calibrating f, cx, cy, k1, k2, p1, p2 does not hold),
    ``wind_m_s`` (east, north; (9, 4): the aircraft is faster over the ground one way than the other and crabs on
    the transversal strip, as real flights do, which tells a readout from an affinity of the pixel grid), ``frames``
    rendered for the orthomosaic (8, the ones nearest the block centre). A flight that could not be simulated (an
    unknown preset or effect, a magnitude of the wrong size, a wind as fast as the preset's airspeed) is refused
    here, before anything is written."""

    preset: str = "conte-calibration"
    seed: int = 7
    max_images: int | None = None
    effects: tuple[tuple[str, tuple[float, ...]], ...] = (("rolling_shutter", (0.010,)),)
    wind_m_s: tuple[float, float] = (9.0, 4.0)
    frames: int = 8

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"DemoConfig.preset {self.preset!r} unknown; valid: {', '.join(PRESETS)}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"DemoConfig.seed must be an integer of 0 or more, got {self.seed!r}")
        if self.max_images is not None and self.max_images < 2:
            raise ValueError(f"DemoConfig.max_images must be None (every frame) or 2 or more, got {self.max_images}")
        names = [name for name, _ in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"DemoConfig.effects names an effect more than once: {names}")
        for name, values in self.effects:
            try:
                effect_values(name, values)
            except EffectError as e:
                raise ValueError(f"DemoConfig.effects: {e}") from None
        airspeed = PRESETS[self.preset].plan.speed_m_s
        wind = tuple(self.wind_m_s)
        if len(wind) != 2 or not all(math.isfinite(w) for w in wind) or not math.hypot(*wind) < airspeed:
            raise ValueError(f"DemoConfig.wind_m_s must be (east, north) m/s slower than the preset's airspeed of "
                             f"{airspeed:g} m/s (the aircraft must make headway on every strip), got {self.wind_m_s}")
        if self.frames < 0:
            raise ValueError(f"DemoConfig.frames must be 0 (no orthomosaic pixels) or more, got {self.frames}")

    @property
    def hidden(self) -> str:
        """The hidden effects in words, e.g. ``rolling_shutter = 0.01 s``."""
        return ", ".join(f"{name} = {', '.join(f'{v:g}' for v in values)} {CATALOGUE[name].units}"
                         for name, values in self.effects) or "none"


def simulate_demo_flight(folder: Path, config: DemoConfig) -> dict[str, Any]:
    """Write the demo flight (observations mode plus ``config.frames`` rendered frames) to ``folder``."""
    if folder.exists():
        if not (folder / "flight.json").exists():
            raise FlowInputError(
                f"{folder} exists and is not a demo flight; remove it or choose another output"
            )
        shutil.rmtree(folder)  # the demo's own previous flight
    spec = get_preset(config.preset).flown(config.wind_m_s)
    sim = simulate_flight(spec, seed=config.seed, effects=dict(config.effects), max_images=config.max_images)
    write_flight(sim, folder, mode="observations")
    if config.frames:
        xy = np.column_stack([sim.images.column("gnss_x").to_numpy(), sim.images.column("gnss_y").to_numpy()])
        near = np.argsort(np.linalg.norm(xy - np.median(xy, axis=0), axis=1))[: config.frames]
        idx = sorted(int(i) for i in near)
        subset = dataclasses.replace(
            sim, images=sim.images.take(idx), exposures=[sim.exposures[i] for i in idx]
        )
        render_flight_images(subset, folder / "images")
    return spec_summary(sim)


@dataclasses.dataclass(frozen=True)
class DemoSummary:
    """What the demo hands on: the processing ``run``'s summary, the ``simulated`` flight's figures
    (:func:`aerocal.simulate.simulator.spec_summary`: preset, images, GSD, CRS, effects), the ``hidden`` effects in
    words and the ``flight_dir`` it wrote."""

    run: RunSummary
    simulated: dict[str, Any]
    hidden: str
    flight_dir: str


@flow(name="demo", validate_parameters=False)
def demo(
    out: str | Path = "demo-output",
    config: DemoConfig | None = None,
    database_url: str | None = None,
    artifact_root: str | None = None,
) -> DemoSummary:
    """Simulate the demo flight under ``out/flight`` and process it into ``out/run``; returns the run's summary
    with the simulated flight's figures."""
    config = config or DemoConfig()
    out = Path(out).resolve()
    env = demo_environment(out)
    flight = out / "flight"
    simulated = simulate_demo_flight(flight, config)
    run = process_flight(
        flight,
        out / "run",
        "auto",
        ProcessConfig(),
        database_url or env["database_url"],
        artifact_root or env["artifact_root"],
    )
    return DemoSummary(run, simulated, config.hidden, str(flight))
