"""What the seed-paper studies share: where their outputs go and how a study's result is written."""

from __future__ import annotations

import argparse
import csv
import json
from collections.abc import Callable
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import pyarrow as pa

from aerocal.adjust import AdjustConfig
from aerocal.io import atomic_path, write_text_atomic
from aerocal.pipeline.config import ProcessConfig, ReportStepConfig

ROOT = Path(__file__).resolve().parents[1]
#: the papers' measured numbers as CSV (beside the repository)
REFERENCE = ROOT.parent / "shared" / "reference"
OUT = ROOT / "studies" / "output"
#: the product's configuration in the studies' runs: its defaults, with each run's report written without pictures
#: (a study reads the run's certificate, diagnosis and summary, never the report's figures; drawing them was about
#: a third of the quick Daakir study's time: benchmarks/RESULTS.md, "The test suite's time: reports nobody looks at")
PRODUCT = ProcessConfig(report=ReportStepConfig(figures=False))


def reference(name: str) -> list[dict]:
    """The rows of a paper's reference CSV (``../shared/reference/<name>``), none when it is absent."""
    path = REFERENCE / name
    if not path.is_file():
        return []
    with path.open() as fh:
        return list(csv.DictReader(fh))


def stats(v: np.ndarray) -> dict:
    """Mean, standard deviation, min, max and RMS of residuals (their units)."""
    return {"mean": float(np.mean(v)), "std": float(np.std(v)), "min": float(np.min(v)),
            "max": float(np.max(v)), "rmse": float(np.sqrt(np.mean(v**2)))}


def as_checks(gcps: pa.Table) -> pa.Table:
    """The GCP table with every point a check point (kept out of the adjustment, triangulated afterwards)."""
    i = gcps.schema.get_field_index("role")
    return gcps.set_column(i, "role", pa.array(["check"] * gcps.num_rows))


def certificate_row(run) -> dict:
    """The certificate a product run (:func:`aerocal.pipeline.process`) used or issued: its id and why, its focal
    length (px), what it estimated, its review's verdict and words."""
    cert = run.json("certificate")
    review = cert.get("review") or {}
    return {"certificate": run.summary.certificate_id, "reason": run.summary.certificate_reason,
            "f": float(cert["model"]["params"]["f"]), "estimated": list(cert.get("estimated") or []),
            "status": review.get("status", "nominal"), "notes": list(review.get("notes") or []),
            "problems": list(review.get("problems") or [])}


def gnss_priors(sim, **kw) -> AdjustConfig:
    """A simulated flight's GNSS sigmas (E, N, Up metres) as an adjustment configuration, ``kw`` added."""
    s = sim.spec.sensors
    return AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m), **kw)


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display)."""
    matplotlib.use("Agg")
    return plt


def save_png(fig, path: Path) -> None:
    """Write a matplotlib figure as PNG atomically (100 dpi) and close it."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def write_study(stem: str, result: dict, markdown: Callable[[dict], str], figure: Callable[[dict, Path], None],
                out: Path, quick: bool) -> Path:
    """Write a study's result to ``out``: ``<stem>[_quick].json`` (its numbers), ``.md`` (its section) and
    ``.png`` (its figure); the Markdown file's path."""
    stem = f"{stem}_quick" if quick else stem
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / f"{stem}.json", json.dumps(result, indent=1, default=str))
    md = write_text_atomic(out / f"{stem}.md", markdown(result))
    figure(result, out / f"{stem}.png")
    return md


def study_parser(doc: str, quick_help: str) -> argparse.ArgumentParser:
    """The command line every paper study has: ``--quick`` (its reduced set-up, ``quick_help`` says what) and
    ``--out`` (default :data:`OUT`); the study adds its own."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--out", type=Path, default=OUT, help=f"output folder (default {OUT})")
    return ap
