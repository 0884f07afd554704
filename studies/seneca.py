"""What a constant-IO model and the simulation get wrong on a real block whose camera cooled from 37 to 23 degC.

Data: ``../shared/data/seneca/images``, the nadir JPEGs of a senseFly Swinglet CAM (Canon PowerShot ELPH 300
HS, 1800x1350, rolling shutter) ~70 m above farm fields; GNSS and autopilot attitude in the senseFly XMP,
the camera's temperature in the Canon maker notes. The flight folder is the one of
:func:`benchmarks.seneca_bench.build_flight` (image links only: ingest reads the nominal camera, the flying height
and consumer-grade GNSS sigmas from the images themselves).

The study is a thin caller of the product: it runs :func:`aerocal.pipeline.process` (the code of
``aerocal process FLIGHT --certificate none``, here without Prefect or a database) and writes what the run
itself decided, from its own outputs, so that the study and ``aerocal process`` give the same answer on the
same images:

1. the self-calibration under the decision rule (:mod:`aerocal.calibrate.self_calibration`): per parameter the formal t,
   the t calibrated by the block's overdispersion (pure-noise per-image focal hypotheses), the held-out gain
   of a thermal slope (k-fold over strips, :mod:`aerocal.calibrate.heldout`), kept / held at nominal / dropped and why;
2. the recorded-EO checks (height datum, GNSS time lag, lever arm, boresight) with their sigmas;
3. the diagnosis of the fixed-IO block: what is named, what is not testable here and why;
4. the flight's twin (:mod:`aerocal.diagnose.twin`): the real block's statistics beside those of the same block made
   again with the simulation's noise model, what differs and its likely cause, and how much of the gap the
   extended simulation (per-image focal jitter) closes.

Run: ``python studies/seneca.py`` (``--quick``: strips 0, 2 and 4, ~30 images; ``--work DIR`` keeps the run
and reports it again without processing). Writes ``studies/output/seneca.md`` (``seneca_quick.md``) and the
twin figure beside it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the project's packages
    sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402

from aerocal import pipeline  # noqa: E402
from aerocal.certificates.document import Certificate  # noqa: E402
from aerocal.io import atomic_path, write_json_atomic, write_text_atomic  # noqa: E402
from aerocal.matching import FeatureConfig  # noqa: E402
from aerocal.pipeline.config import MatchStepConfig, ProcessConfig  # noqa: E402
from benchmarks.seneca_bench import MAX_FEATURES, build_flight  # noqa: E402

OUT = ROOT / "studies" / "output"


def process(work: Path, quick: bool) -> Path:
    """Build the seneca flight folder under ``work`` and process it as ``aerocal process`` does; the run
    folder."""
    run_dir = work / "run"
    if (run_dir / "diagnosis.json").is_file():
        return run_dir
    folder, _ = build_flight(work, quick)
    config = ProcessConfig(match=MatchStepConfig(features=FeatureConfig(max_features=MAX_FEATURES)))
    run = pipeline.process(folder, config, certificate="none", out_dir=run_dir)
    write_json_atomic(run_dir / "run.json", run.summary.to_json())
    return run_dir


def read_run(run_dir: Path) -> dict:
    """What the run decided: its calibration certificate (with its review), the calibration's record, the
    certificate the block used, the diagnosis (recorded-EO checks and twin within)."""
    run_dir = Path(run_dir)

    def doc(name: str) -> dict:
        return json.loads((run_dir / name).read_text())

    return {
        "calibration_certificate": Certificate.from_json((run_dir / "calibration_certificate.json").read_text()),
        "certificate": Certificate.from_json((run_dir / "certificate.json").read_text()),
        "calibration": doc("calibration.json"),
        "diagnosis": doc("diagnosis.json"),
        "adjustment": doc("adjustment.json"),
        "run": doc("run.json"),
    }


def _pm(v: float | None, s: float | None, digits: int = 4) -> str:
    if v is None or not np.isfinite(v):
        return "-"
    return f"{v:.{digits}g} +- {s:.2g}" if s is not None and np.isfinite(s) else f"{v:.{digits}g}"


def calibration_rows(r: dict) -> list[list[str]]:
    """One row per parameter the self-calibration considered: value +- sigma, formal t, calibrated t,
    held-out gain, decision."""
    cert: Certificate = r["calibration_certificate"]
    rows = []
    names = list(dict.fromkeys(list(cert.significance) + list(cert.estimated)))
    for name in names:
        sig = cert.significance.get(name)
        value = getattr(cert.camera, name, None)
        if value is None and cert.thermal is not None:
            value = getattr(cert.thermal.model, name, None)
        sigma = cert.sigmas.get(name) if name in cert.sigmas else (
            cert.thermal.sigmas.get(name) if cert.thermal is not None else None)
        kept = name in cert.estimated or (cert.thermal is not None and name in cert.thermal.sigmas)
        gain = "-"
        if sig is not None and sig.held_out_gain is not None:
            gain = f"{100 * sig.held_out_gain:+.1f} +- {100 * (sig.held_out_sigma or float('nan')):.1f} %"
        decision = "kept" if kept else (sig.dropped if sig is not None and sig.dropped else "not estimated")
        rows.append([name, _pm(value, sigma if kept else None, 6),
                     f"{sig.t:.1f}" if sig is not None and np.isfinite(sig.t) else "-",
                     f"{sig.calibrated_t:.1f}" if sig is not None and sig.calibrated_t is not None else "-",
                     gain, decision.replace("|", "/")])
    return rows


def recorded_eo_rows(r: dict) -> list[list[str]]:
    rows = []
    for name, c in (r["diagnosis"].get("recorded_eo") or {}).items():
        est = ", ".join(f"{v:.3g}" for v in c.get("estimate", []))
        sig = ", ".join(f"{v:.2g}" for v in c.get("sigma", []))
        rows.append([name, c.get("units", ""), est or "-", sig or "-", str(c.get("status", "-")),
                     str(c.get("reason") or "").replace("|", "/")])
    return rows


def twin_rows(r: dict) -> list[list[str]]:
    """Real statistic | twin mean +- sd | z | cause if it differs | per extension tried: its twins' mean
    (gap closed)."""
    twin = r["diagnosis"].get("twin") or {}
    if not twin:
        return []
    rows = []
    for k, real in twin["real"].items():
        if real is None or not np.isfinite(real):
            continue
        row = [k, f"{real:.4g}", f"{twin['twin_mean'][k]:.4g} +- {twin['twin_sd'][k]:.2g}", f"{twin['z'][k]:.1f}",
               twin.get("differs", {}).get(k, ""), twin.get("cause", {}).get(k, "-" if k in twin.get("differs", {})
                                                                              else "")]
        for ext in [*twin.get("extended", {}).values(), *([twin["combined"]] if twin.get("combined") else [])]:
            cell = f"{ext['twin_mean'].get(k, float('nan')):.4g}"
            if k in ext.get("gap_closed", {}):
                cell += f" ({100 * ext['gap_closed'][k]:.0f} %)"
            row.append(cell)
        rows.append(row)
    return rows


def _extension_header(name: str, ext: dict) -> str:
    """A twin extension's column title: its name, the size it needed and whether that is physically possible."""
    verdict = "" if ext.get("plausible", True) else ", beyond what is physically possible: not the cause"
    # a run kept from before the twin sized several causes holds its one extension's size as "jitter"
    size = ext.get("physical", ext.get("jitter", float("nan")))
    return f"twin + {name} ({size:.2g} {ext.get('unit', 'of f per frame')}{verdict}): mean (gap closed)"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + [
        "| " + " | ".join(row) + " |" for row in rows]


def markdown(r: dict, title: str) -> str:
    cert, cal, d = r["calibration_certificate"], r["calibration"], r["diagnosis"]
    review = cert.review.to_dict() if cert.review is not None else {}
    twin = d.get("twin") or {}
    lines = [
        f"# {title}",
        "",
        "Written by `studies/seneca.py` from the outputs of `aerocal process` (`aerocal.pipeline.process`, "
        "certificate `none`) on the same images: the study reports what the product decided.",
        "",
        f"- run {r['run']['run_id']}; block adjustment: reprojection RMS "
        f"{r['adjustment'].get('reprojection_rms_px', float('nan')):.3f} px, sigma0 "
        f"{r['adjustment'].get('sigma0', float('nan')):.3f}",
        f"- calibration: {cert.conditions.n_images} images, overdispersion of the formal statistics "
        f"{cal.get('overdispersion', 1.0):.1f} (t calibrated by its square root); review **{review.get('status')}**"
        + (f": {'; '.join(review.get('problems', []))}" if review.get("problems") else ""),
        f"- certificate used by the block: {r['run'].get('certificate_reason')}",
        "",
        "## Self-calibration under the decision rule",
        "",
        *_table(["parameter", "value +- sigma", "formal t", "calibrated t", "held-out gain", "decision"],
                calibration_rows(r)),
        "",
        "## Recorded exterior orientation",
        "",
        *_table(["check", "units", "estimate", "sigma", "status", "reason"], recorded_eo_rows(r)),
        "",
        "## Diagnosis of the fixed-IO block",
        "",
        f"- named: {d.get('summary')}",
        *[f"- {n}" for n in d.get("notes", [])],
        "",
        "## The flight's twin: what the simulation gets wrong",
        "",
    ]
    if twin:
        lines += [
            f"{twin['n_twins']} twins: the block as adjusted (poses, tie-point layout, camera, temperatures, "
            "priors and their sigmas) made again with the simulation's noise model and adjusted the same way.",
            "",
            *_table(["statistic", "real", "twin", "z", "what differing says", "likely cause (named)",
                     *[_extension_header(n, e) for n, e in twin.get("extended", {}).items()],
                     *(["the extended simulation, every named cause at once: mean (gap closed)"]
                       if twin.get("combined") else [])],
                    twin_rows(r)),
            "",
            f"- {twin.get('summary')}",
        ]
    else:
        lines.append("- no twin in this run's diagnosis (DiagnoseConfig.twins < 2)")
    return "\n".join(lines) + "\n"


def twin_figure(r: dict, path: Path) -> Path | None:
    """Each statistic of the real block over the twins' mean, with the twins' spread and the extended twin."""
    twin = r["diagnosis"].get("twin") or {}
    rows = [k for k, v in twin.get("real", {}).items()
            if v is not None and np.isfinite(v) and twin["twin_mean"].get(k) not in (None, 0)]
    if not rows:
        return None

    matplotlib.use("Agg")

    mean = np.array([twin["twin_mean"][k] for k in rows])
    real = np.array([twin["real"][k] for k in rows]) / mean
    sd = np.array([twin["twin_sd"][k] for k in rows]) / np.abs(mean)
    fig, ax = plt.subplots(figsize=(7.5, 0.5 * len(rows) + 1.5))
    y = np.arange(len(rows))
    ax.errorbar(np.ones(len(rows)), y, xerr=2 * sd, fmt="o", color="0.5", label="twin (mean +- 2 sd)")
    ax.plot(real, y, "s", color="C3", label="real block")
    for n, (name, ext) in enumerate(twin.get("extended", {}).items()):
        e = np.array([ext["twin_mean"].get(k, np.nan) for k in rows]) / mean
        ax.plot(e, y + 0.1 * (n + 1), "^v<>"[n % 4], color=f"C{n}", ms=4, label=f"twin + {name}")
    if twin.get("combined"):
        e = np.array([twin["combined"]["twin_mean"].get(k, np.nan) for k in rows]) / mean
        ax.plot(e, y, "D", color="k", mfc="none", label="the extended simulation (every named cause)")
    ax.set_yticks(y, rows)
    ax.set_xscale("log")
    ax.set_xlabel("statistic / twin mean")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("seneca: real block against its simulated twins")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path


def write_study(run_dir: Path, out: Path, stem: str = "seneca") -> Path:
    """``out/<stem>.md`` and ``out/<stem>_twin.png`` from the processed run in ``run_dir``."""
    out.mkdir(parents=True, exist_ok=True)
    r = read_run(run_dir)
    twin_figure(r, out / f"{stem}_twin.png")
    md = out / f"{stem}.md"
    title = "seneca (real): the product's answer" + (" (quick: strips 0, 2, 4)" if stem.endswith("quick") else "")
    write_text_atomic(md, markdown(r, title))
    return md


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="strips 0, 2 and 4 only (~30 images)")
    ap.add_argument("--out", type=Path, default=OUT, help="output folder (default studies/output)")
    ap.add_argument("--work", type=Path, default=None,
                    help="keep the flight folder, store and run here (default: a temporary folder); given again, "
                    "the run found there is reported without processing")
    args = ap.parse_args(argv)
    work = args.work.resolve() if args.work else Path(tempfile.mkdtemp(prefix="aerocal-seneca-study-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        run_dir = process(work, args.quick)
        md = write_study(run_dir, args.out, "seneca_quick" if args.quick else "seneca")
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print(md)
    return md


if __name__ == "__main__":
    main()
