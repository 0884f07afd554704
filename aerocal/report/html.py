"""A report page: one self-contained HTML file (figures embedded as PNG data URIs) rendered from a Jinja2
template of ``aerocal/report/templates``, and summary.json with its numbers.

:func:`write_report` takes plain data: a summary dict (JSON-ready, e.g. the ``to_dict()`` of the
:mod:`aerocal.assess` results), :class:`aerocal.report.figures.Figure` objects and a certificate
table, so a flow, a study or a notebook can call it alike. :func:`render` renders any template of the
package (the flight report's is :mod:`aerocal.report.flight_report`).
"""

from __future__ import annotations

import base64
import dataclasses
import datetime as dt
import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import jinja2

from aerocal.camera import PARAM_UNITS
from aerocal.certificates.document import Conditions
from aerocal.io import write_json_atomic, write_text_atomic
from aerocal.report import wording
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
        sigmas = sigmas or {}
        units = {**PARAM_UNITS, **(units or {})}
        rows = [(k, float(v), None if sigmas.get(k) is None else float(sigmas[k]), units.get(k, ""))
                for k, v in values.items()]
        return cls(title=title, rows=rows, info=dict(info or {}))

    def to_dict(self) -> dict:
        return {"title": self.title, "info": self.info, "parameters": [
            {"name": n, "value": v, "sigma": s, "unit": u} for n, v, s, u in self.rows]}


#: the report templates: Jinja2, shipped inside the package (pyproject package-data)
TEMPLATES = "templates"


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


@functools.cache
def environment() -> jinja2.Environment:
    """The Jinja2 environment of the report templates: loaded from the installed package
    (``aerocal/report/templates``), HTML autoescaped, undefined names an error, ``datauri`` filter (PNG
    bytes to a ``data:`` URI)."""
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("aerocal.report", TEMPLATES),
        autoescape=jinja2.select_autoescape(["html", "j2"]),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["datauri"] = _data_uri
    return env


def render(template: str, context: Mapping) -> str:
    """The page of ``template`` (a file of :data:`TEMPLATES`) with ``context``."""
    return environment().get_template(template).render(**context)


def machine_summary(title: str, summary: Mapping, figures: Sequence[Figure] = (), notes: Sequence[str] = (),
                    certificate: CertificateTable | None = None) -> dict:
    """The ``summary.json`` document: title, creation time (UTC), ``summary``, every figure's numbers under
    ``figures.<name>``, the ``notes`` (one sentence per figure not drawn) and the certificate table.
    Raises ``ValueError`` when figure names repeat."""
    names = [f.name for f in figures]
    if len(set(names)) != len(names):
        raise ValueError(f"write_report: figure names must be unique, got {names}")
    doc = {
        "title": title, "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "summary": dict(summary), "figures": {f.name: {"title": f.title, **f.numbers} for f in figures},
        "notes": [str(n) for n in notes],
        "certificate": certificate.to_dict() if certificate else None,
    }
    return doc


def write_report(
    run_dir: str | Path,
    summary: Mapping,
    figures: Sequence[Figure] = (),
    certificate: CertificateTable | None = None,
    title: str = "Flight report",
    notes: Sequence[str] = (),
) -> Path:
    """Write ``run_dir/report.html`` (self-contained, from ``templates/report.html.j2``) and ``run_dir/summary.json``.

    The page shows the summary's key figures under readable labels (:func:`aerocal.report.wording.key_figures`),
    the figures with their captions, the ``notes`` (one sentence per figure the data could not support) and the
    certificate's parameters. Both files are written atomically. A processed flight's report is
    :func:`aerocal.report.flight_report.write_flight_report`.

    Args:
        run_dir: the folder written (created with its parents when missing).
        summary: the key figures, JSON-ready (e.g. the ``to_dict()`` of :mod:`aerocal.assess` results); the first
            value that is a mapping with a text ``verdict`` gives the page's verdict.
        figures: the figures (:class:`aerocal.report.figures.Figure`), in page order, names unique.
        certificate: the certificate table, or ``None``.
        title: the page's title (default "Flight report").
        notes: one sentence per figure not drawn.

    Returns:
        The path of ``report.html``; ``summary.json`` is :func:`machine_summary`'s document.

    Raises:
        ValueError: figure names repeat.
    """
    run_dir = Path(run_dir)
    machine = machine_summary(title, summary, figures, notes, certificate)
    context = {
        "title": title, "created_utc": machine["created_utc"], "summary_name": SUMMARY_NAME,
        "verdict": _find_verdict(summary) or "", "key_figures": wording.key_figures(summary),
        "figures": [{"name": f.name, "title": f.title, "caption": f.caption, "png": f.png} for f in figures],
        "notes": [str(n) for n in notes],
        "certificate": None if certificate is None else {
            "title": certificate.title,
            "info": [(wording.humanise(str(k))[0], _info_text(v)) for k, v in certificate.info.items()],
            "rows": [{"name": wording.PARAM_LABELS.get(n, n), "value": wording.number(v, 6),
                      "sigma": "" if s is None else wording.number(s, 2), "unit": "" if u == "1" else u}
                     for n, v, s, u in certificate.rows],
        },
    }
    write_json_atomic(run_dir / SUMMARY_NAME, machine)
    return write_text_atomic(run_dir / REPORT_NAME, render("report.html.j2", context))


def _info_text(value) -> str:
    """A certificate-table ``info`` value for a reader; conditions (a mapping) as labelled pairs."""
    if isinstance(value, Mapping) and set(value) <= {f.name for f in dataclasses.fields(Conditions)}:
        return "; ".join(f"{a}: {b}" for a, b in wording.conditions_rows(Conditions(**value)))
    return wording.say(value)


def _find_verdict(summary: Mapping) -> str | None:
    for value in summary.values():
        if isinstance(value, Mapping) and isinstance(value.get("verdict"), str):
            return value["verdict"]
    return None
