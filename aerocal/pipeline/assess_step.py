"""The assessment step: check-point residuals with achieved / predicted accuracy
(:func:`aerocal.assess.accuracy_ratio`), control residuals, reprojection statistics."""

from __future__ import annotations

from typing import Any

import numpy as np

from aerocal.assess import accuracy_ratio, reprojection_stats
from aerocal.pipeline.runner import JsonOutput, Runner, StepInputs, StepResult


def assessment(adj: dict, residuals: np.ndarray, observations, images) -> dict[str, Any]:
    """The ``assessment`` document of an adjustment summary (``adjust`` step) and its residuals (pixels):
    ``check_points`` (rho per axis and verdict; points without a prediction named in ``not_measured``),
    ``control_points`` (n, RMSE E N Up metres), ``reprojection`` (overall, per image, per strip, binned) and
    ``sigma0``."""
    out: dict[str, Any] = {}
    e = np.asarray(adj["check_errors_m"], dtype=float).reshape(-1, 3)
    s = np.asarray(adj["check_sigma_m"], dtype=float).reshape(-1, 3) if adj["check_sigma_m"] else None
    ids = list(adj.get("check_ids") or [])
    measured = (np.isfinite(e).all(axis=1) & (s > 0).all(axis=1)) if s is not None else np.zeros(len(e), bool)
    unmeasured = [ids[i] if i < len(ids) else str(i) for i in np.flatnonzero(~measured)]
    if measured.sum() >= 2:
        out["check_points"] = accuracy_ratio(e[measured], s[measured]).to_dict()
    else:
        out["check_points"] = {"n": int(measured.sum()),
                               "verdict": "fewer than 2 check points: accuracy not assessed"}
    if unmeasured:  # e.g. seen in one image only: no intersection, no prediction
        out["check_points"]["not_measured"] = unmeasured
    c = np.asarray(adj["control_errors_m"], dtype=float).reshape(-1, 3)
    out["control_points"] = {"n": len(c), "rmse_m": np.sqrt(np.mean(c**2, axis=0)).tolist() if len(c) else None}
    ok = np.isfinite(residuals).all(axis=1)
    out["reprojection"] = reprojection_stats(observations.filter(ok), residuals[ok], images).to_dict()
    out["sigma0"] = adj["sigma0"]
    return out


def assess_step(runner: Runner, ingest: StepResult, observations: str, adjusted: StepResult,
                name: str = "assess") -> StepResult:
    """Output ``assessment`` (:func:`assessment`) of the adjustment ``adjusted`` (on the data it used, where it
    says: ``block_images``, ``block_observations``)."""
    inputs = {"images": ingest["images"], "observations": observations, "adjustment": adjusted["adjustment"],
              "residuals": adjusted["residuals"]}
    if "block_images" in adjusted.outputs:
        inputs.update(images=adjusted["block_images"], observations=adjusted["block_observations"])

    def compute(inp: StepInputs) -> dict:
        doc = assessment(inp.json("adjustment"), inp.array("residuals"), inp.table("observations"),
                         inp.table("images"))
        return {"assessment": JsonOutput(doc, "assessment")}

    return runner.run(name, inputs, None, compute)
