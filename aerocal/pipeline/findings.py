"""What a run found of the catalogue's effects, wherever it found them, and where each went.

A flight's systematic effects are caught at three places, each with its own test on data the fit did not use:

* the **self-calibration** keeps a thermal slope of the focal length or the principal point only with a gain on
  held-out strips (:mod:`aerocal.calibrate.heldout`); the slope is then the certificate's thermal model;
* the **recorded-EO check** of the block adjustment removes a GNSS time lag, and a horizontal GNSS offset against
  three or more control points, from the recorded positions before the adjustment (:mod:`aerocal.calibrate.eo_checks`);
* the **diagnosis** names what the block's model still leaves, with a held-out gain, and the block is extended by
  it (:mod:`aerocal.pipeline.extend_step`).

:func:`run_findings` lists them in one form (:class:`Finding`), so that a reader (and a test) asks one place what
the run found and what it did with it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass

from aerocal.effects import CATALOGUE, rotation_zero_point, rotation_zero_point_text

#: where a finding was made
FOUND_BY = ("self-calibration", "recorded-EO check", "diagnosis", "recorded-EO check and diagnosis")
#: effects both the recorded-EO check and the diagnosis find, whose two parts add up (small angles, a lag, a shift)
_ADDITIVE = ("gnss_time_offset", "gnss_bias", "boresight")


@dataclass(frozen=True)
class Finding:
    """One effect of the catalogue the run found: ``name``, ``values`` and ``sigmas`` in ``units``, ``found_by``
    (one of :data:`FOUND_BY`), where it was ``applied`` and its ``evidence`` on data the fit did not use, in
    words."""

    name: str
    values: tuple[float, ...]
    sigmas: tuple[float | None, ...]
    units: str
    found_by: str
    applied: str
    evidence: str

    def __post_init__(self) -> None:
        if self.name not in CATALOGUE:
            raise ValueError(f"finding {self.name!r} is not an effect of the catalogue")
        if self.found_by not in FOUND_BY:
            raise ValueError(f"finding {self.name}: found_by {self.found_by!r} unknown; valid: {', '.join(FOUND_BY)}")

    def text(self) -> str:
        """``"gnss_time_offset = 0.0431 +- 0.00083 s (recorded-EO check; removed from the recorded positions)"``."""
        values = ", ".join(f"{v:.4g}" for v in self.values)
        sigmas = ", ".join("?" if s is None else f"{s:.2g}" for s in self.sigmas)
        return f"{self.name} = {values} +- {sigmas} {self.units} ({self.found_by}: {self.applied})"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["values"], d["sigmas"] = list(self.values), list(self.sigmas)
        return d

    @classmethod
    def from_dict(cls, doc: dict) -> Finding:
        """A finding from :meth:`to_dict`'s form."""
        return cls(doc["name"], tuple(float(v) for v in doc["values"]),
                   tuple(None if s is None else float(s) for s in doc["sigmas"]), doc["units"], doc["found_by"],
                   doc["applied"], doc["evidence"])


#: the certificate's thermal slopes as catalogue effects
_SLOPES = {"thermal_focal": ("df_dt",), "thermal_principal_point": ("dcx_dt", "dcy_dt")}


def calibration_findings(certificate: dict) -> list[Finding]:
    """The thermal slopes a self-calibration kept (a certificate document made on this flight)."""
    thermal = certificate.get("thermal") or {}
    if thermal.get("kind") != "linear":
        return []
    sig = certificate.get("significance") or {}
    out = []
    for name, slopes in _SLOPES.items():
        values = [float(thermal.get(s) or 0.0) for s in slopes]
        if not any(values):
            continue
        sigmas = [(thermal.get("sigmas") or {}).get(s) for s in slopes]
        held = [sig.get(s) or {} for s in slopes]
        evidence = "; ".join(f"{s}: held-out gain {100 * h['held_out_gain']:+.2f} +- "
                             f"{100 * (h.get('held_out_sigma') or 0):.2f} %"
                             for s, h in zip(slopes, held, strict=True) if h.get("held_out_gain") is not None)
        out.append(Finding(name, tuple(values), tuple(sigmas), CATALOGUE[name].units, "self-calibration",
                           f"the certificate's thermal model (T0 {thermal.get('t0'):.4g} degC)",
                           evidence or "kept by the calibration's review"))
    return out


def recorded_eo_findings(adjustment: dict) -> list[Finding]:
    """The GNSS time lag and offset the block adjustment's recorded-EO check removed from the recorded positions."""
    c = adjustment.get("recorded_eo_corrections") or {}
    evidence = c.get("evidence") or {}
    out = []
    if c.get("time_offset_s") is not None:
        out.append(Finding("gnss_time_offset", (float(c["time_offset_s"]),), (c.get("time_sigma_s"),), "s",
                           "recorded-EO check", "removed from the recorded positions before the adjustment",
                           evidence.get("gnss_time_offset") or "beyond 3 sigma of its calibrated uncertainty"))
    if c.get("attitude_offset_deg") is not None:
        check = c.get("attitude_check") or {}
        out.append(Finding("boresight", tuple(float(v) for v in c["attitude_offset_deg"]),
                           tuple(check.get("sigma") or [None] * 3), "deg", "recorded-EO check",
                           "removed from the recorded attitudes before the adjustment",
                           f"leave-one-out gain {100 * check.get('held_out_gain', 0.0):+.1f} +- "
                           f"{100 * check.get('held_out_sigma', 0.0):.1f} % over {check.get('n_images')} images"))
    if c.get("offset_m") is not None:
        out.append(Finding("gnss_bias", tuple(float(v) for v in c["offset_m"]), tuple(c.get("sigma_m") or [None] * 3),
                           "m", "recorded-EO check", "its horizontal part removed from the recorded positions",
                           evidence.get("gnss_bias") or "against the control points, beyond 3 sigma"))
    return out


def extension_findings(extension: dict) -> list[Finding]:
    """The terms the diagnosis named and the block was extended by
    (:func:`aerocal.pipeline.extend_step.extension_record`)."""
    camera = set(extension.get("camera_terms") or [])
    certificate = (extension.get("after") or {}).get("certificate_id")
    out = []
    for t in extension.get("terms") or []:
        applied = "the block adjusted again with it"
        if t["name"] in camera:
            applied += f"; written into certificate {certificate}"
        out.append(Finding(t["name"], tuple(t["values"]), tuple(t["sigmas"]), t["units"], "diagnosis", applied,
                           t.get("evidence") or ""))
    return out


def run_findings(calibration_certificate: dict | None, adjustment: dict | None,
                 extension: dict | None) -> list[Finding]:
    """Every effect the run found (module docstring): the self-calibration's thermal slopes
    (``calibration_certificate``: the certificate this flight's calibration made, None where it used a stored one),
    the recorded-EO check's corrections (``adjustment``: the first block adjustment's summary) and the diagnosis's
    extension."""
    out = calibration_findings(calibration_certificate) if calibration_certificate else []
    out += recorded_eo_findings(adjustment or {})
    for f in extension_findings(extension) if extension else []:
        first = next((k for k, g in enumerate(out) if g.name == f.name and f.name in _ADDITIVE), None)
        if first is None:
            out.append(f)
        else:
            out[first] = _together(out[first], f)
    return _rotation_zero_point(out)


def _rotation_zero_point(found: list[Finding]) -> list[Finding]:
    """A thermal rotation found with a boresight about the optical axis alone is one finding
    (:func:`aerocal.effects.rotation_zero_point`): the boresight stays applied to the block and is reported in the
    rotation's finding (a simulated warming conte-calibration block with 0.05 px/degC hidden named a 0.020 deg
    boresight about z beside it)."""
    names = {f.name for f in found}
    rotation = next((k for k, f in enumerate(found) if f.name == "thermal_rotation"), None)
    turn = next((k for k, f in enumerate(found) if f.name == "boresight"
                 and rotation_zero_point(names, f.values, f.sigmas)), None)
    if rotation is None or turn is None:
        return found
    r, b = found[rotation], found[turn]
    merged = dataclasses.replace(r, applied=f"{r.applied}; {rotation_zero_point_text(b.values[2], b.sigmas[2])} "
                                            f"({b.found_by}: {b.applied})",
                                 evidence=f"{r.evidence}; the turn at the reference: {b.evidence}")
    return [merged if k == rotation else f for k, f in enumerate(found) if k != turn]


def _together(eo: Finding, diagnosed: Finding) -> Finding:
    """One effect removed from the records by the recorded-EO check and what the diagnosis found of it beyond that
    (a linearised test's shortfall on a large lag, a boresight component the check held back): their sum, with the
    diagnosis' sigmas (the remainder's, given the first part)."""
    values = tuple(a + b for a, b in zip(eo.values, diagnosed.values, strict=True))
    rest = ", ".join(f"{v:.4g}" for v in diagnosed.values)
    return Finding(eo.name, values, diagnosed.sigmas, eo.units, "recorded-EO check and diagnosis",
                   f"{eo.applied}; the rest ({rest} {eo.units}) named by the diagnosis and {diagnosed.applied}",
                   f"{eo.evidence}; the rest: {diagnosed.evidence}")
