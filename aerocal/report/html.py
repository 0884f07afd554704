"""The flight report: one self-contained HTML file (figures embedded as PNG data URIs) and summary.json.

:func:`write_report` takes plain data: a summary dict (JSON-ready, e.g. the ``to_dict()`` of the
:mod:`aerocal.assess` results), :class:`aerocal.report.figures.Figure` objects and a certificate
table, so a flow, a study or a notebook can call it alike.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from aerocal.report.figures import Figure

REPORT_NAME = "report.html"
SUMMARY_NAME = "summary.json"


@dataclass
class CertificateTable:
    """The calibration certificate a flight used: parameters with their standard deviations.

    ``rows``: (name, value, sigma or None, unit). ``info``: identity, version, conditions (shown as text).
    """

    title: str
    rows: list[tuple[str, float, float | None, str]]
    info: dict = field(default_factory=dict)

    @classmethod
    def from_values(cls, title: str, values: Mapping[str, float], sigmas: Mapping[str, float] | None = None,
                    units: Mapping[str, str] | None = None, info: Mapping | None = None) -> CertificateTable:
        from aerocal.camera import PARAM_UNITS

        sigmas = sigmas or {}
        units = {**PARAM_UNITS, **(units or {})}
        rows = [(k, float(v), None if sigmas.get(k) is None else float(sigmas[k]), units.get(k, ""))
                for k, v in values.items()]
        return cls(title=title, rows=rows, info=dict(info or {}))

    def to_dict(self) -> dict:
        return {"title": self.title, "info": self.info, "parameters": [
            {"name": n, "value": v, "sigma": s, "unit": u} for n, v, s, u in self.rows]}


_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.6em; } h2 { font-size: 1.25em; border-bottom: 1px solid #ccc; padding-bottom: .2em; }
table { border-collapse: collapse; margin: .5em 0 1.5em; } td, th { padding: .25em .8em; text-align: right; }
th { background: #f0f0f0; } td:first-child, th:first-child { text-align: left; }
tr:nth-child(even) td { background: #fafafa; } figure { margin: 1em 0 2em; }
figure img { max-width: 100%; border: 1px solid #ddd; } figcaption { color: #555; font-size: .9em; }
.verdict { font-weight: bold; }
"""


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def _summary_table(summary: Mapping) -> str:
    """Scalars of the summary (one level of nesting) as a two-column table."""
    rows = []
    for key, value in summary.items():
        if isinstance(value, Mapping):
            for k2, v2 in value.items():
                if isinstance(v2, (int, float, str, type(None))):
                    rows.append((f"{key}.{k2}", v2))
                elif isinstance(v2, Mapping) and all(isinstance(x, (int, float, type(None))) for x in v2.values()):
                    rows.append((f"{key}.{k2}", ", ".join(f"{a} {_fmt(b)}" for a, b in v2.items())))
        elif isinstance(value, (int, float, str, type(None))):
            rows.append((key, value))
    body = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{_fmt(v)}</td></tr>" for k, v in rows)
    return f"<table><tr><th>figure</th><th>value</th></tr>{body}</table>" if rows else ""


def _certificate_html(cert: CertificateTable) -> str:
    info = "".join(f"<li>{html.escape(str(k))}: {_fmt(v)}</li>" for k, v in cert.info.items())
    rows = "".join(
        f"<tr><td>{html.escape(n)}</td><td>{v:.6g}</td><td>{'-' if s is None else f'{s:.3g}'}</td>"
        f"<td>{html.escape(u)}</td></tr>" for n, v, s, u in cert.rows)
    return (f"<h2>Calibration certificate: {html.escape(cert.title)}</h2><ul>{info}</ul>"
            f"<table><tr><th>parameter</th><th>value</th><th>&sigma;</th><th>unit</th></tr>{rows}</table>")


def write_report(
    run_dir: str | Path,
    summary: Mapping,
    figures: Sequence[Figure] = (),
    certificate: CertificateTable | None = None,
    title: str = "Flight report",
    notes: Sequence[str] = (),
) -> Path:
    """Write ``run_dir/report.html`` (self-contained) and ``run_dir/summary.json``; return the HTML path.

    ``summary.json`` holds ``summary``, every figure's numbers under ``figures.<name>``, the ``notes``
    (one sentence per figure the data could not support, shown after the figures) and the certificate.
    Both files are written atomically.
    """
    from aerocal.io import write_json_atomic, write_text_atomic

    run_dir = Path(run_dir)
    names = [f.name for f in figures]
    if len(set(names)) != len(names):
        raise ValueError(f"write_report: figure names must be unique, got {names}")
    machine = {
        "title": title, "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "summary": dict(summary), "figures": {f.name: {"title": f.title, **f.numbers} for f in figures},
        "notes": [str(n) for n in notes],
        "certificate": certificate.to_dict() if certificate else None,
    }
    json.dumps(machine, default=str)  # fail before writing anything if it is not serialisable
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"
             f"<p>Created {machine['created_utc']}. The numbers behind every figure are in {SUMMARY_NAME}.</p>"]
    verdict = _find_verdict(summary)
    if verdict:
        parts.append(f"<p class='verdict'>Achieved vs predicted accuracy: {html.escape(verdict)}</p>")
    parts.append("<h2>Key figures</h2>" + _summary_table(summary))
    for f in figures:
        data = base64.b64encode(f.png).decode("ascii")
        parts.append(f"<h2>{html.escape(f.title)}</h2><figure id='{html.escape(f.name)}'>"
                     f"<img alt='{html.escape(f.title)}' src='data:image/png;base64,{data}'>"
                     f"<figcaption>{html.escape(f.caption)}</figcaption></figure>")
    if notes:
        items = "".join(f"<li>{html.escape(str(n))}</li>" for n in notes)
        parts.append(f"<h2>Figures not drawn</h2><ul class='notes'>{items}</ul>")
    if certificate is not None:
        parts.append(_certificate_html(certificate))
    parts.append("</body></html>\n")
    write_json_atomic(run_dir / SUMMARY_NAME, machine)
    return write_text_atomic(run_dir / REPORT_NAME, "".join(parts))


def _find_verdict(summary: Mapping) -> str | None:
    for value in summary.values():
        if isinstance(value, Mapping) and isinstance(value.get("verdict"), str):
            return value["verdict"]
    return None
