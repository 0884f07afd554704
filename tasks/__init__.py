"""Prefect tasks: thin wrappers around the engine's functions, with retries, cache keys and artifacts.

Modules: :mod:`tasks.resume` (content-addressed steps that resume after a crash), :mod:`tasks.retries`
(which failures are retried), :mod:`tasks.flight` (manifest, ingest, enhance + match, orient),
:mod:`tasks.calibration` (sub-block, self-calibration, certificate issue and selection),
:mod:`tasks.block` (full-block adjustment with fixed IO), :mod:`tasks.products` (DSM + orthomosaic,
assessment, diagnosis, report).
"""
