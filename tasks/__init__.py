"""The platform's parts of the flight pipeline (:mod:`aerocal.pipeline`): thin wrappers with retries, storage
and records.

Modules: :mod:`tasks.runner` (every step a Prefect task, stored and reused through :mod:`storage.steps`),
:mod:`tasks.certificates` (the database as the certificate store), :mod:`tasks.run_records` (what a run
records as it goes), :mod:`tasks.retries` (which failures are retried).
"""
