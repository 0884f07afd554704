"""The report's words: labels with units for the machine keys, numbers formatted for a reader, and the
sentences that say what a step found.

The summary JSON keeps its keys (``check_rmse_m``, ``dsm_minus_reference_m``, ...) for machines; the HTML
shows :data:`SUMMARY_LABELS` instead, values through :func:`say`. Nothing here returns ``None``, ``nan``,
a Python repr or a lone dash: a value that is missing is said to be missing (:data:`MISSING`).
Units: metres, pixels, degrees Celsius, seconds, as the labels say.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence

from aerocal.camera import PARAM_NAMES, PARAM_UNITS
from aerocal.certificates.document import Certificate, Conditions
from aerocal.effects import CATALOGUE
from aerocal.ingest.problems import name_list

#: what the report says where a value was not recorded
MISSING = "not recorded"

#: summary key -> (label, unit shown after the value, "" for none)
SUMMARY_LABELS: dict[str, tuple[str, str]] = {
    "flight": ("Flight", ""),
    "mode": ("Input", ""),
    "images": ("Images", ""),
    "images_skipped_at_ingest": ("Images skipped at ingest", ""),
    "crs": ("Coordinate reference system", ""),
    "date": ("Date", ""),
    "temperature_c": ("Sensor temperature", "degC"),
    "flight_facts": ("Facts read from the images", ""),
    "temperature_raster": ("Temperature raster", ""),
    "certificate": ("Calibration certificate", ""),
    "certificate_review": ("Certificate review", ""),
    "thermal_model": ("Thermal model of the interior orientation", ""),
    "adjustment": ("Bundle adjustment", ""),
    "sigma0": ("Sigma naught (a-posteriori standard deviation of unit weight)", ""),
    "reprojection_rms_px": ("Reprojection error (RMS)", "px"),
    "check_rmse_m": ("Check-point error (RMSE)", "m"),
    "rho": ("Achieved over predicted check-point accuracy", ""),
    "verdict": ("Accuracy verdict", ""),
    "diagnosis": ("Diagnosis", ""),
    "recorded_eo_checks": ("Recorded GNSS/IMU checks", ""),
    "recorded_eo_corrections": ("Recorded GNSS corrections", ""),
    "twin": ("Simulated twin of the block", ""),
    "gsd_m": ("Ground sampling distance", "m"),
    "mosaic_frames": ("Frames in the orthomosaic", ""),
    "ground_control": ("Ground control", ""),
    "dsm_minus_reference_m": ("DSM minus reference", "m"),
}

#: the interior-orientation parameters by name, for a reader
PARAM_LABELS: dict[str, str] = {
    "f": "Focal length f", "cx": "Principal point cx", "cy": "Principal point cy",
    "k1": "Radial distortion k1", "k2": "Radial distortion k2", "k3": "Radial distortion k3",
    "p1": "Decentring distortion p1", "p2": "Decentring distortion p2",
    "b1": "Affinity b1", "b2": "Skew b2",
}

#: statistics keys of :meth:`aerocal.assess.DemDifference.to_dict` and friends, for a reader
STAT_LABELS: dict[str, str] = {
    "n": "cells", "mean_m": "mean", "median_m": "median", "std_m": "standard deviation", "nmad_m": "NMAD",
    "rmse_m": "RMSE", "max_m": "largest",
}

#: effects the diagnosis tests beyond the catalogue (:data:`aerocal.diagnose.hypotheses.HYPOTHESES`)
EXTRA_EFFECTS: dict[str, str] = {"per_strip_io": "an interior orientation of its own per strip"}

#: the statistics of a block and its simulated twins (:func:`aerocal.diagnose.twin.block_statistics`), for a reader
TWIN_LABELS: dict[str, str] = {
    "variance_tie": "Variance factor of the tie points",
    "variance_gnss": "Variance factor of the GNSS positions",
    "variance_attitude": "Variance factor of the IMU attitudes",
    "variance_gcp": "Variance factor of the ground control",
    "image_field_px": "Systematic field over the image (px)",
    "per_image_scale": "Per-image scale scatter",
    "per_image_row_field": "Per-image field along the rows",
    "per_image_column_field": "Per-image field along the columns",
    "gnss_lag1": "GNSS residual correlation from one image to the next",
    "tail_fraction": "Fraction of residuals beyond the blunder screening",
}

#: step names of a flight run, for a reader
STEP_LABELS: dict[str, str] = {
    "manifest": "Manifest", "ingest": "Ingest", "enhance": "Enhance", "match": "Enhance and match",
    "orient": "Orient", "control": "Screen ground control", "select": "Select certificate",
    "calibrate": "Calibrate", "issue": "Issue certificate", "adjust": "Bundle adjustment",
    "mosaic": "DSM and orthomosaic", "temperature": "Temperature raster", "assess": "Assess",
    "diagnose": "Diagnose", "report": "Report",
}

_UNIT_SUFFIXES = (("_px_per_degc", "px/degC"), ("_deg", "deg"), ("_px", "px"), ("_m", "m"), ("_c", "degC"),
                  ("_s", "s"), ("_pct", "%"))
_WORDS = {"gnss": "GNSS", "imu": "IMU", "eo": "EO", "io": "IO", "dsm": "DSM", "gsd": "GSD", "rms": "RMS",
          "rmse": "RMSE", "crs": "CRS", "nmad": "NMAD", "gcp": "GCP", "gcps": "GCPs", "utc": "UTC"}


def humanise(key: str) -> tuple[str, str]:
    """A machine key as (label, unit): ``"gnss_position_m"`` -> ``("GNSS position", "m")``."""
    k, unit = str(key), ""
    for suffix, u in _UNIT_SUFFIXES:
        if k.lower().endswith(suffix) and len(k) > len(suffix):
            k, unit = k[: -len(suffix)], u
            break
    words = [w for w in re.split(r"[_\s.]+", k) if w]
    words = [_WORDS.get(w.lower(), w) for w in words]
    text = " ".join(words)
    return (text[:1].upper() + text[1:]) if text else str(key), unit


def label(key: str) -> tuple[str, str]:
    """(label, unit) of a summary key: :data:`SUMMARY_LABELS`, else :func:`humanise`."""
    return SUMMARY_LABELS.get(key) or humanise(key)


def number(v: float | int | None, digits: int = 4) -> str:
    """A number for a reader: integers as they are, floats to ``digits`` significant digits (fixed
    notation between 1e-4 and 1e6), :data:`MISSING` for ``None``, "not available" for a non-finite value."""
    if v is None or isinstance(v, bool):
        return MISSING if v is None else ("yes" if v else "no")
    if isinstance(v, int):
        return str(v)
    x = float(v)
    if not math.isfinite(x):
        return "not available"
    if x == 0:
        return "0"
    if 1e-4 <= abs(x) < 1e6:
        decimals = max(digits - 1 - int(math.floor(math.log10(abs(x)))), 0)
        return f"{x:.{decimals}f}"
    return f"{x:.{digits - 1}e}"


def fixed(v: float | None, decimals: int = 3) -> str:
    """``v`` with ``decimals`` decimals (metres to the millimetre by default), :data:`MISSING` for none."""
    if v is None or not math.isfinite(float(v)):
        return MISSING
    return f"{float(v):.{decimals}f}"


def plus_minus(value: float | None, sigma: float | None, digits: int = 4) -> str:
    """``"1668.2 ± 0.41"``; the value alone when there is no sigma."""
    if sigma is None or not math.isfinite(float(sigma)):
        return number(value, digits)
    return f"{number(value, digits)} ± {number(sigma, 2)}"


def with_unit(text: str, unit: str) -> str:
    return f"{text} {unit}" if unit and text not in (MISSING, "not available") else text


def say(value, unit: str = "") -> str:
    """Any summary value as text for a reader: numbers with ``unit``, E/N/Up triples, ranges, mappings as
    ``label value`` pairs, ``None`` as :data:`MISSING`."""
    if value is None:
        return MISSING
    if isinstance(value, str):
        return value.strip() or MISSING
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        return with_unit(number(value), unit)
    if isinstance(value, Mapping):
        parts = []
        for k, v in value.items():
            if str(k) in STAT_LABELS:
                name, u = STAT_LABELS[str(k)], unit
            else:
                name, u = humanise(str(k))
            if k == "n":
                parts.append(f"{number(v)} {name}")
            else:
                parts.append(f"{name} {say(v, u or unit)}")
        return "; ".join(parts) or MISSING
    if isinstance(value, Sequence):
        items = list(value)
        if len(items) == 3 and all(isinstance(x, (int, float)) or x is None for x in items):
            return "; ".join(f"{a} {say(x, unit)}" for a, x in zip(("E", "N", "Up"), items, strict=True))
        if len(items) == 2 and all(isinstance(x, (int, float)) for x in items) and unit == "degC":
            return f"{number(items[0], 3)} to {number(items[1], 3)} degC"
        return ", ".join(say(x, unit) for x in items) or MISSING
    return str(value)


def key_figures(summary: Mapping) -> list[tuple[str, str]]:
    """The summary as (label, value with unit) rows, in the summary's order."""
    rows = []
    for key, value in summary.items():
        name, unit = label(str(key))
        if key == "rho" and isinstance(value, Mapping):
            rows.append((name, "; ".join(f"{a} {number(v, 3)}" for a, v in value.items()) or MISSING))
        else:
            rows.append((name, say(value, unit)))
    return rows


# ------------------------------------------------------------------------------ step findings in words
def skipped_images_text(names: list[str]) -> str:
    """``"none"`` or ``"3: a.jpg, b.jpg, c.jpg (see the ingest errors)"``."""
    return f"{len(names)}: {name_list(names)} (see the ingest errors)" if names else "none"


def screening_parts(screening: Mapping) -> list[str]:
    """What the ground-control screening found (:mod:`aerocal.adjust.control`), one statement each: the counts,
    then one per point it says something of."""
    if screening.get("datum") == "none":
        return list(screening.get("notes") or []) or ["none"]
    verdicts = screening.get("verdicts") or []
    kept = sum(v["status"] == "kept" for v in verdicts)
    untested = sum(v["status"] == "not tested" for v in verdicts)
    head = f"{kept} point(s) consistent with the block, {len(screening.get('demoted') or [])} demoted, " \
           f"{untested} not testable"
    return [head, *(screening.get("lines") or [])]


def screening_text(screening: Mapping) -> str:
    """One line of what the ground-control screening found: :func:`screening_parts` joined."""
    return "; ".join(screening_parts(screening))


def recorded_eo_text(checks: Mapping) -> str:
    """The recorded-EO checks of a diagnosis (``Diagnosis.recorded_eo``) in one line, ``"; "`` between them:
    name, estimate +- sigma (``?`` where none), units, status; led by the block they were tested on."""
    parts = []
    for name, c in checks.items():
        if "estimate" in c:
            est = ", ".join(f"{v:.3g}" for v in c["estimate"])
            sig = ", ".join("?" if v is None else f"{v:.2g}" for v in c["sigma"])
            parts.append(f"{name} {est} +- {sig} {c['units']} ({c['status']})")
        else:
            parts.append(f"{name}: {c['status']}")
    blocks = {c["block"] for c in checks.values() if c.get("block")}
    head = f"tested on {blocks.pop()}: " if len(blocks) == 1 else ""
    return head + "; ".join(parts) if parts else "no GNSS/IMU observations: not checked"


def recorded_eo_rows(checks: Mapping) -> list[tuple[str, str, str]]:
    """The recorded-EO checks as (check, estimate ± sigma with unit, finding) rows."""
    rows = []
    for name, c in checks.items():
        if "estimate" in c:
            unit = c.get("units") or ""
            sig = list(c.get("sigma") or [None] * len(c["estimate"]))
            known = CATALOGUE.get(name)
            parts = [with_unit(plus_minus(v, s, 3), unit) for v, s in zip(c["estimate"], sig, strict=False)]
            if known is not None and len(known.labels) == len(parts):
                parts = [f"{humanise(n)[0].lower()} {x}" for n, x in zip(known.labels, parts, strict=True)]
            finding = str(c.get("status") or MISSING) + (f" (tested on {c['block']})" if c.get("block") else "")
            rows.append((humanise(name)[0], "; ".join(parts), finding))
        else:
            rows.append((humanise(name)[0], "not estimated", str(c.get("status") or MISSING)))
    return rows


def effect_sentence(effect: Mapping) -> str:
    """One named effect of a diagnosis (:meth:`aerocal.diagnose.engine.NamedEffect.to_dict`) in words."""
    name = str(effect["name"])
    known = CATALOGUE.get(name)
    title = humanise(name)[0]
    mags = effect.get("magnitude")
    sigs = effect.get("sigma")
    mags = list(mags) if isinstance(mags, (list, tuple)) else [mags]
    sigs = list(sigs) if isinstance(sigs, (list, tuple)) else [sigs] * len(mags)
    names = list(known.labels) if known is not None and len(known.labels) == len(mags) else []
    units = str(effect.get("units") or "")
    sizes = ", ".join(
        (f"{humanise(n)[0].lower()} " if n else "") + with_unit(plus_minus(m, s, 3), units)
        for n, m, s in zip(names or [""] * len(mags), mags, sigs, strict=True)
    )
    text = f"{title}"
    if known is not None:
        text += f" ({known.description})"
    text += f": {sizes}"
    p = effect.get("p_value")
    if p is not None and math.isfinite(float(p)):
        text += ", p-value below 1e-6" if float(p) < 1e-6 else f", p-value {number(p, 2)}"
    text += "."
    held = effect.get("held_out") or {}
    if held.get("gain") is not None:
        text += (f" On images the fit did not use it reduces the misfit by {number(100 * held['gain'], 3)} +- "
                 f"{number(100 * (held.get('sigma') or 0.0), 2)} % ({held.get('n_images')} held-out images, "
                 f"{held.get('units')}).")
    check = effect.get("check_points") or {}
    if check.get("gain") is not None:
        spread = number(100 * (check.get("sigma") or 0.0), 2)
        text += f" On the check points: {number(100 * check['gain'], 3)} +- {spread} % of their squared error."
    alts = effect.get("alternatives") or []
    if alts:
        text += (" The block cannot tell it apart from " + ", ".join(humanise(a)[0].lower() for a in alts)
                 + ": they explain the residuals almost as well.")
    return text


def diagnosis_sentences(diagnosis: Mapping) -> list[str]:
    """What the diagnosis found (``Diagnosis.to_dict``), in sentences."""
    out = []
    effects = diagnosis.get("effects") or []
    tested = len({h.get("name") for h in diagnosis.get("hypotheses") or []})
    if not effects:
        out.append("No systematic effect found: the residuals are what the camera model and the measurement "
                   "noise explain" + (f" ({tested} candidate effects tested)." if tested else "."))
    else:
        out.append(f"{len(effects)} systematic effect{'s' if len(effects) > 1 else ''} the camera model does "
                   "not hold " + ("was" if len(effects) == 1 else "were") + " found in the residuals"
                   + (f" ({tested} candidate effects tested):" if tested else ":"))
        out.extend(effect_sentence(e) for e in effects)
    for pair in diagnosis.get("pairs") or []:
        names = [humanise(n)[0].lower() for n in pair["effects"]]
        names = [f"{'an' if n[:1] in 'aeiou' else 'a'} {n}" for n in names]
        listed = ", ".join(names[:-1]) + f" and {names[-1]}"
        out.append(f"{listed[0].upper()}{listed[1:]} explain the residuals alike and this block cannot tell them "
                   f"apart ({pair.get('conditional')}): "
                   f"{'neither' if len(names) == 2 else 'none'} is named nor applied. "
                   f"{sentence(pair.get('separated_by'))}")
    s0 = diagnosis.get("sigma0") or {}
    before, after = s0.get("before"), s0.get("after")
    if effects and before is not None and after is not None:
        out.append(f"Modelling {'it' if len(effects) == 1 else 'them'} changes sigma naught from "
                   f"{number(before, 3)} to {number(after, 3)}.")
    gain = diagnosis.get("gain")
    if gain and gain.get("before") is not None and gain.get("after") is not None:
        name, unit = humanise(str(gain.get("metric", "")))
        out.append(f"{name or 'Error'}: {with_unit(number(gain['before'], 3), unit)} before, "
                   f"{with_unit(number(gain['after'], 3), unit)} after the correction.")
    od = diagnosis.get("overdispersion")
    if od is not None and math.isfinite(float(od)) and float(od) > 1.0:
        out.append(f"The statistics were divided by the block's measured overdispersion {number(od, 3)} "
                   "(formal statistics are optimistic on real matches).")
    out.extend(sentence(name_effects(n)) for n in diagnosis.get("notes") or [])
    return out


def extension_view(extension: Mapping) -> dict:
    """The block's extension by its diagnosis (:func:`aerocal.pipeline.extend_step.extension_record`) for the
    report: a lead sentence, the terms (name, size, evidence) and the block before and after, row by row."""
    terms = [(humanise(t["name"])[0], ", ".join(plus_minus(v, sg, 4) for v, sg in zip(t["values"], t["sigmas"],
                                                                                    strict=True)) + f" {t['units']}",
              t.get("evidence") or "") for t in extension.get("terms") or []]
    b, a = extension.get("before") or {}, extension.get("after") or {}
    rows = [("Certificate", str(b.get("certificate_id") or MISSING), str(a.get("certificate_id") or MISSING)),
            ("Sigma naught", number(b.get("sigma0"), 4), number(a.get("sigma0"), 4))]
    cb, ca = b.get("check_points") or {}, a.get("check_points") or {}
    def check(c: Mapping, axis: str) -> str:
        return f"{number((c.get('rmse_m') or {}).get(axis), 3)} ({number((c.get('rho') or {}).get(axis), 3)})"

    for axis in ("E", "N", "U"):
        if (cb.get("rmse_m") or {}).get(axis) is not None:
            rows.append((f"Check points {axis}: RMSE m (rho)", check(cb, axis), check(ca, axis)))
    rows.append(("The twin", str(b.get("twin") or MISSING), str(a.get("twin") or MISSING)))
    rows.append(("Diagnosis", str(b.get("diagnosis") or MISSING), str(a.get("diagnosis") or MISSING)))
    camera = extension.get("camera_terms") or []
    lead = ("The diagnosis named what follows, each with a gain on data the fit did not use; the block was adjusted "
            "again with them and every product of this report comes from the extended block")
    lead += (f"; {', '.join(humanise(n)[0].lower() for n in camera)} belong to the camera and went into its "
             f"certificate {a.get('certificate_id')}." if camera else ".")
    return {"lead": lead, "terms": terms, "rows": rows}


def name_effects(text: str) -> str:
    """``text`` with every catalogue effect's machine name (``rolling_shutter``) as words (rolling shutter)."""
    names = sorted([*CATALOGUE, *EXTRA_EFFECTS], key=len, reverse=True)
    return re.sub(r"\b(" + "|".join(map(re.escape, names)) + r")\b",
                  lambda m: EXTRA_EFFECTS.get(m.group(1), humanise(m.group(1))[0].lower()), str(text))


def sentence(text) -> str:
    t = str(text).strip()
    if not t:
        return t
    t = t[:1].upper() + t[1:]
    return t if t.endswith((".", "!", "?", ")")) else t + "."


# ------------------------------------------------------------------------------ the certificate
def parameter_rows(cert: Certificate) -> list[dict[str, str]]:
    """Every interior-orientation parameter of ``cert`` as a row: label, value, sigma, unit, how it was
    determined (estimated with its t and significance, or held fixed)."""
    rows = []
    for name in PARAM_NAMES:
        value = getattr(cert.camera, name)
        unit = "" if PARAM_UNITS[name] == "1" else PARAM_UNITS[name]
        sig = cert.significance.get(name)
        estimated = name in cert.estimated
        if estimated:
            how = "estimated"
            if sig is not None:
                how += f", t {number(sig.t, 3)}, " + ("significant" if sig.significant else "not significant")
        else:
            how = "held fixed"
            if sig is not None and sig.dropped:
                how += f": {sig.dropped}"
            elif value == 0.0:
                how += " at zero"
        sigma = cert.sigmas.get(name) if estimated else (sig.prior_sigma if sig is not None else None)
        rows.append({"name": PARAM_LABELS.get(name, name), "value": number(value, 6),
                     "sigma": number(sigma, 2) if sigma is not None else "",
                     "unit": unit, "how": how})
    return rows


def thermal_sentence(cert: Certificate) -> str:
    """The certificate's thermal model of the interior orientation in one sentence."""
    th = cert.thermal
    if th is None:
        return ("The certificate has no thermal model: the interior orientation is taken as constant over "
                "the sensor's temperature.")
    vr = ("an unrecorded temperature range" if th.valid_range is None
          else f"{number(th.valid_range[0], 3)} to {number(th.valid_range[1], 3)} degC")
    d = th.model.to_dict()
    kind = d.get("kind", "thermal")
    if kind == "linear":
        slopes = []
        for key, what in (("df_dt", "focal length"), ("dcx_dt", "principal point x"),
                          ("dcy_dt", "principal point y")):
            v = d.get(key)
            if v is not None:
                slopes.append(f"{what} {plus_minus(v, th.sigmas.get(key), 3)} px/degC")
        return (f"Linear thermal model about {number(d.get('t0'), 4)} degC: " + ", ".join(slopes)
                + f"; valid over {vr}.")
    if kind == "similarity":
        n = len(d.get("temperatures") or [])
        return (f"Similarity thermal model (a scale and shift of the image measurements) fitted at {n} "
                f"temperatures; valid over {vr}.")
    return f"{humanise(kind)[0]} thermal model of the image measurements; valid over {vr}."


def conditions_rows(conditions: Conditions) -> list[tuple[str, str]]:
    """What the calibration was made under, as (what, value) rows."""
    c = conditions
    rows = [("Date of the calibration flight", c.date or MISSING)]
    rows.append(("Sensor temperatures", MISSING if c.temperature_range is None
                 else f"{number(c.temperature_range[0], 3)} to {number(c.temperature_range[1], 3)} degC"))
    rows.append(("Images", number(c.n_images)))
    strips = number(c.strips)
    transversal = {None: "not recorded whether", True: "with", False: "without"}[c.transversal_strip]
    rows.append(("Strips", f"{strips}, {transversal} a transversal strip"))
    rows.append(("Ground control points", number(c.n_gcp)))
    if c.priors:
        for k, v in c.priors.items():
            name, unit = humanise(k)
            rows.append((f"Prior standard deviation: {name}", with_unit(number(v, 3), unit)))
    else:
        rows.append(("Priors", "none"))
    if c.images:
        rows.append(("Calibration images", f"{len(c.images)}: {name_list(list(c.images), 8)}"))
    return rows


def review_text(cert: Certificate) -> str:
    """The certificate's review in one line: the first note of a certificate made elsewhere, else the
    review's summary."""
    if cert.review is None:
        return "not reviewed (made elsewhere)"
    if cert.review.notes and not cert.estimated:
        return str(cert.review.notes[0])
    return cert.review.summary()


def step_rows(step_seconds: Mapping[str, float]) -> list[tuple[str, str]]:
    """Step times as (step, duration) rows with the total last."""
    rows = [(STEP_LABELS.get(k, humanise(k)[0]), duration(v)) for k, v in step_seconds.items()]
    rows.append(("Total of the steps above", duration(sum(float(v) for v in step_seconds.values()))))
    return rows


def duration(seconds: float) -> str:
    """``"0.42 s"``, ``"12.3 s"``, ``"4 min 05 s"``, ``"2 h 03 min"``."""
    s = float(seconds)
    if not math.isfinite(s):
        return MISSING
    if s < 10:
        return f"{s:.2f} s"
    if s < 60:
        return f"{s:.1f} s"
    m, r = divmod(int(round(s)), 60)
    return f"{m} min {r:02d} s" if m < 60 else f"{m // 60} h {m % 60:02d} min"



def twin_view(twin: Mapping) -> dict:
    """The comparison of the block with its simulated twins (:meth:`aerocal.diagnose.twin.TwinComparison.to_dict`):
    a ``lead`` sentence, ``rows`` (statistic, block value, twins' mean ± spread, what a difference means) for
    the statistics that differ, and ``sentences`` on the likely causes."""
    if not twin or "real" not in twin:
        return {"lead": sentence(str(twin["summary"])) if twin.get("summary") else
                "No simulated twin of the block was made.", "rows": [], "sentences": []}
    n = twin.get("n_twins")
    differs = twin.get("differs") or {}
    if not differs:
        return {"lead": f"Simulated twins of the block ({number(n)}, the block's geometry with simulated noise "
                        "only): every statistic of the block is within their spread, the simulation explains the "
                        "block.", "rows": [], "sentences": []}
    rows = [(TWIN_LABELS.get(k, humanise(k)[0]), number(twin["real"].get(k), 3),
             plus_minus(twin["twin_mean"].get(k), twin["twin_sd"].get(k), 3), sentence(str(why)))
            for k, why in differs.items()]
    lead = (f"{len(differs)} statistic{'s' if len(differs) > 1 else ''} of the block differ from {number(n)} "
            "simulated twins (the block's geometry with simulated noise only):")
    out = []
    extended = twin.get("extended") or {}
    cause = twin.get("cause") or {}
    for name in dict.fromkeys(cause.values()):
        ext = extended.get(name) or {}
        stats = [TWIN_LABELS.get(k, humanise(k)[0]).lower().removesuffix(" (px)") for k, v in cause.items()
                 if v == name]
        size = with_unit(number(ext.get("physical"), 2), str(ext.get("unit") or "")) if ext else ""
        out.append(f"Likely cause of the {' and the '.join(stats)}: {name}" + (f" of {size}." if size else "."))
    for name, ext in extended.items():
        if ext.get("plausible") is False:
            out.append(f"A {name} would need {with_unit(number(ext.get('physical'), 2), str(ext.get('unit') or ''))}, "
                       "beyond what is physically possible: it is not the cause.")
    combined = twin.get("combined") or {}
    if combined.get("extensions"):
        def labels(key: str) -> list[str]:
            return [TWIN_LABELS.get(k, humanise(k)[0]).lower() for k in combined.get(key) or []]

        still, over, undecided = labels("still_differs"), labels("overshoots"), labels("undecided")
        missed = still + over + undecided
        out.append(f"The simulation extended with {', '.join(combined['extensions'])} at once reproduces the block"
                   + (f" except the {', '.join(missed)}." if missed else "."))
        if over:
            out.append(f"It overshoots the {', '.join(over)}: the causes' sizes, each found on its own, add up when "
                       "applied together; they are upper bounds, not measurements.")
        if undecided:
            out.append(f"The {', '.join(undecided)} {'is' if len(undecided) == 1 else 'are'} within the extended "
                       "twins' spread only because that spread is wide: the twins cannot decide.")
    return {"lead": lead, "rows": rows, "sentences": out}


def two_view_text(dense: Mapping[str, object]) -> str:
    """The share of a dense DSM's measured cells that stand on one pair only (``dense``: the products step's
    ``dense`` record), as ", N % of it by one pair only (band 3 of dsm.tif)"; "" below half a percent."""
    share = float(dense.get("two_view_fraction") or 0.0)
    return f", {100 * share:.0f} % of it by one pair only (band 3 of dsm.tif)" if share >= 0.005 else ""
