"""Conte 2018's calibration strategies and Daakir 2019's thermally corrected full-block adjustment.

* ``"fixed"`` (STR1): the whole block with IO fixed at a given camera (a laboratory calibration or a
  certificate), measurements corrected for temperature when a thermal model is given.
* ``"self"`` (STR2): self-calibration of the whole block.
* ``"certificate"``: self-calibration on a calibration sub-block (image ids given, e.g. from
  :func:`aerocal.calibrate.subset.propose_subset`), then the whole block with that IO fixed (and its thermal
  model applied to the measurements, when one was estimated).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from aerocal.adjust.bundle import AdjustmentResult, adjust
from aerocal.adjust.problem import AdjustConfig, AdjustmentError
from aerocal.adjust.solver import BundleProblem, Solution, State
from aerocal.camera import Camera, LinearThermalModel

STRATEGIES = ("fixed", "self", "certificate")


@dataclass
class StrategyResult:
    """The full-block adjustment of a strategy and, for "certificate", the calibration it used."""

    strategy: str
    block: AdjustmentResult
    calibration: AdjustmentResult | None = None


def select_images(table: pa.Table, image_ids) -> pa.Table:
    """Rows of ``table`` (any table with an ``image_id`` column) whose image is in ``image_ids``."""
    ids = pa.array(np.asarray(list(image_ids), dtype=np.int32))
    return table.filter(pc.is_in(table.column("image_id"), value_set=ids))


def long_tracks(table: pa.Table, min_rays: int) -> pa.Table:
    """Rows of ``table`` (an observations table) whose track is measured in ``min_rays`` images or more (rows
    counted in ``table`` itself)."""
    track = table.column("track_id").to_numpy()
    if not len(track):
        return table
    _, inverse, counts = np.unique(track, return_inverse=True, return_counts=True)
    return table.filter(pa.array(counts[inverse] >= min_rays))


def central_images(images: pa.Table, n: int) -> np.ndarray:
    """Image ids of the ``n`` images whose recorded positions lie nearest the block's median position
    (the first ``n`` ids when positions are missing).

    A square of a block flown in parallel strips holds a stretch of every strip, so the sub-block spans
    the flight's whole time and sensor-temperature range (what thermal and time hypotheses need) and
    keeps the strips' overlaps; a corridor keeps its middle stretch.
    """
    ids = images.column("image_id").to_numpy()
    if len(ids) <= n:
        return ids
    x = images.column("gnss_x").to_numpy(zero_copy_only=False).astype(float)
    y = images.column("gnss_y").to_numpy(zero_copy_only=False).astype(float)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < n:
        return np.sort(ids)[:n]
    d = np.hypot(x - np.median(x[ok]), y - np.median(y[ok]))
    d[~ok] = np.inf
    return np.sort(ids[np.argsort(d, kind="stable")[:n]])


def adjust_fixed_io(
    images: pa.Table,
    observations: pa.Table,
    camera: Camera,
    config: AdjustConfig | None = None,
    gcps: pa.Table | None = None,
    gcp_observations: pa.Table | None = None,
    thermal: LinearThermalModel | None = None,
    solver: Callable[[BundleProblem, State], Solution] | None = None,
) -> AdjustmentResult:
    """Full-block adjustment with IO fixed at ``camera`` (IO at ``thermal.t0`` when a model is given).
    ``solver``: see :func:`aerocal.adjust.bundle.adjust`.

    With ``thermal`` the tie-point and GCP measurements are corrected to T0 before adjusting (Daakir 2019).
    """
    config = dataclasses.replace(config or AdjustConfig(), free=(), thermal=(), adaptive=False)
    result = adjust(images, observations, camera, config, gcps, gcp_observations, thermal_correction=thermal,
                    solver=solver)
    if result.converged:
        return result
    # a weakly determined direction can leave Levenberg-Marquardt in a slow tail (real h20t_forest, two opposite
    # strips, consumer GNSS, no attitude records, no GCPs: 156 iterations to converge before the solver moved the
    # points of a failed step to its cameras, 6 since); adjust again with a longer budget rather than report a
    # solution as unfinished
    longer = dataclasses.replace(config, max_iterations=SLOW_TAIL_FACTOR * config.max_iterations)
    again = adjust(images, observations, camera, longer, gcps, gcp_observations, thermal_correction=thermal,
                   solver=solver)
    again.selection = again.selection + [
        f"the adjustment stopped after {result.iterations} iterations without converging; adjusted again with up "
        f"to {longer.max_iterations}: {'converged' if again.converged else 'did not converge either'} in "
        f"{again.iterations}"]
    return again


#: the longer budget (times AdjustConfig.max_iterations) of a fixed-IO adjustment that did not converge
SLOW_TAIL_FACTOR = 4


def run_strategy(
    strategy: str,
    images: pa.Table,
    observations: pa.Table,
    camera: Camera,
    config: AdjustConfig | None = None,
    gcps: pa.Table | None = None,
    gcp_observations: pa.Table | None = None,
    thermal: LinearThermalModel | None = None,
    subset_image_ids=None,
    subset_config: AdjustConfig | None = None,
) -> StrategyResult:
    """Run one of :data:`STRATEGIES` on a block (see the module docstring).

    Raises:
        AdjustmentError: ``strategy`` is not one of :data:`STRATEGIES` (the message lists them), or it is
            ``'certificate'`` without ``subset_image_ids``.
    """
    config = config or AdjustConfig()
    if strategy == "fixed":
        return StrategyResult(
            "fixed", adjust_fixed_io(images, observations, camera, config, gcps, gcp_observations, thermal)
        )
    if strategy == "self":
        return StrategyResult("self", adjust(images, observations, camera, config, gcps, gcp_observations))
    if strategy == "certificate":
        if subset_image_ids is None:
            raise AdjustmentError("strategy 'certificate' needs subset_image_ids (the calibration sub-block)")
        gobs = select_images(gcp_observations, subset_image_ids) if gcp_observations is not None else None
        cal = adjust(
            select_images(images, subset_image_ids),
            select_images(observations, subset_image_ids),
            camera,
            subset_config or config,
            gcps,
            gobs,
        )
        block = adjust_fixed_io(images, observations, cal.camera, config, gcps, gcp_observations, cal.thermal)
        return StrategyResult("certificate", block, cal)
    raise AdjustmentError(f"strategy {strategy!r} unknown; valid: {', '.join(STRATEGIES)}")
