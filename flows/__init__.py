"""Prefect flows and the platform commands.

Modules: :mod:`flows.process` (``process_flight``, ``calibrate_camera``: :func:`aerocal.pipeline.process` with
the platform's runner, certificate store and records), :mod:`flows.campaign` (``run_campaign``, campaign
deployments and schedules), :mod:`flows.demo` (the ``aerocal demo`` flow), :mod:`flows.environment`
(database, artifacts, Prefect settings), :mod:`flows.cli` (the ``aerocal`` command tree).
"""
