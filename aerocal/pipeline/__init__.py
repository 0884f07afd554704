"""The flight pipeline of the engine: one step function per stage, and :func:`process` for a whole flight.

``aerocal.pipeline.process("flight/")`` runs ingest, enhance + match, orient, ground-control screening,
self-calibration (or a stored certificate), the fixed-IO block adjustment, DSM + orthomosaic, assessment,
diagnosis and the report, in this process, without Prefect or a database. The platform (``flows.process``)
runs the same function with its own runner (steps stored and reused, each a Prefect task) and certificate
store (the database).

Modules: :mod:`~aerocal.pipeline.dataset` (where a flight's inputs come from), :mod:`~aerocal.pipeline.config`
(typed settings per step), :mod:`~aerocal.pipeline.runner` (outputs, results, the in-memory runner),
:mod:`~aerocal.pipeline.certificates` (the certificate store interface and the choice), one module per step
(``*_step``), :mod:`~aerocal.pipeline.figures` (each step's small figures, typed), :mod:`~aerocal.pipeline.process`
and what a run hands on, :mod:`~aerocal.pipeline.summary` (:class:`RunSummary`, read by the CLI, written as
``run.json``).

Tests: tests/test_pipeline.py, tests/test_run_summary.py, tests/test_run_failures.py, tests/test_config_validation.py,
tests/test_model_loop.py.
"""

from aerocal.matching.cluster import ExecutionConfig
from aerocal.pipeline.certificates import CertificateStore, MemoryCertificates
from aerocal.pipeline.config import CertificateMode, ProcessConfig
from aerocal.pipeline.dataset import FlightDataset, FlightInputError, FlightMode, FolderDataset, MemoryDataset
from aerocal.pipeline.process import EXPORTS, FlightRun, process
from aerocal.pipeline.runner import LocalRunner, Runner, StepResult
from aerocal.pipeline.summary import RunSummary, StepRecord, StepStatus

__all__ = [
    "EXPORTS",
    "ExecutionConfig",
    "CertificateMode",
    "CertificateStore",
    "FlightDataset",
    "FlightInputError",
    "FlightMode",
    "FlightRun",
    "FolderDataset",
    "LocalRunner",
    "MemoryCertificates",
    "MemoryDataset",
    "ProcessConfig",
    "RunSummary",
    "Runner",
    "StepRecord",
    "StepResult",
    "StepStatus",
    "process",
]
