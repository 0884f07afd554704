"""Prefect flows and the platform commands.

Modules: :mod:`flows.flight` (``process_flight``, ``calibrate_camera``), :mod:`flows.campaign`
(``run_campaign``, campaign deployments and schedules), :mod:`flows.demo` (the ``aerocal demo`` flow),
:mod:`flows.config` (the processing configuration), :mod:`flows.environment` (database, artifacts,
Prefect settings), :mod:`flows.commands` and :mod:`flows.commands_storage` (CLI commands).
"""
