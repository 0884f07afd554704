"""The platform's runner of the flight pipeline: every step a Prefect task, stored and reused through storage.

:class:`StoreRunner` is the :class:`aerocal.pipeline.runner.Runner` that ``flows.process`` hands to
:func:`aerocal.pipeline.process`: a step runs as a Prefect task named after it (retries of transient failures,
:mod:`tasks.retries`; logging, the UI), and inside it :func:`storage.steps.run_step` reuses the completed step
for the same inputs, configuration and code, or computes it and stores its outputs with their lineage.
References are the artifacts' SHA-256.

Prefect's own result cache is off (``NO_CACHE``): the step record in aerocal's database is the cache (see
:mod:`storage.steps` for why).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from prefect import task
from prefect.cache_policies import NO_CACHE

from aerocal.pipeline.runner import Compute, Output, StepResult
from storage.steps import StepContext, StoredInputs, export_artifact, put_value, record_skip, run_step
from tasks.retries import TASK_RETRIES, TASK_RETRY_DELAYS_S, retry_condition


def _run_step(ctx: StepContext, step: str, inputs: Mapping[str, str], config: Any, compute: Compute) -> StepResult:
    return run_step(ctx, step, inputs, config, compute)


class StoreRunner:
    """Runs each step as a Prefect task (``prefect_tasks=False``: in this process, e.g. outside a flow) over the
    artifact store and database of ``ctx``."""

    def __init__(self, ctx: StepContext, prefect_tasks: bool = True) -> None:
        self.ctx, self.prefect_tasks = ctx, prefect_tasks
        self.run_id = ctx.run_id

    def run(self, step: str, inputs: Mapping[str, str], config: Any, compute: Compute) -> StepResult:
        if not self.prefect_tasks:
            return run_step(self.ctx, step, inputs, config, compute)
        as_task = task(_run_step, name=step, retries=TASK_RETRIES, retry_delay_seconds=TASK_RETRY_DELAYS_S,
                       retry_condition_fn=retry_condition, cache_policy=NO_CACHE)
        return as_task(self.ctx, step, inputs, config, compute)

    def skip(self, step: str, reason: str) -> StepResult:
        return record_skip(self.ctx, step, reason)

    def put(self, output: Output) -> str:
        return put_value(self.ctx, output)

    def inputs(self, refs: Mapping[str, str]) -> StoredInputs:
        return StoredInputs(self.ctx, refs)

    def export(self, ref: str, target: Path) -> Path:
        return export_artifact(self.ctx, ref, Path(target))
