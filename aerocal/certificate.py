"""Calibration certificates: immutable, versioned, JSON-serialisable records of one camera's IO.

A :class:`Certificate` holds, for one camera (:class:`CameraIdentity`: make, model, serial, lens):

* the Brown camera model (:class:`aerocal.camera.Camera`, pixels, origin at the top-left corner of the
  top-left pixel) with the standard deviation of every estimated parameter and their full correlation
  matrix;
* which parameters were estimated and the significance of each (t statistic, significant at 95 %, and
  the reason a parameter was dropped);
* the thermal model where one was estimated (:class:`ThermalCalibration`: the model, the sigmas of its
  slopes, the temperature range it is valid over);
* the conditions it was made under, its quality figures and its provenance.

A certificate is never edited: a new calibration supersedes an old one. ``version`` and ``supersedes``
are assigned by the certificate store (:meth:`Certificate.with_version` returns the numbered copy).

The JSON document (``schema`` ``aerocal.certificate/1``) has a fixed shape that the storage layer
indexes::

    {"schema": "aerocal.certificate/1", "id": <uuid4 hex>,
     "camera": {"make", "model", "serial", "lens"},
     "version": int | null, "supersedes": <id> | null, "issued": "<ISO-8601 UTC, Z suffix>",
     "model": {"kind": "brown", "width", "height", "pixel_size_mm",
               "params": {"f", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "b1", "b2"}},
     "sigmas": {name: float}, "estimated": [names],
     "correlation": {"names": [...], "matrix": [[...]]},
     "significance": {name: {"t": float, "significant": bool, "dropped": str | null}},
     "thermal": null | {"kind": "linear" | "similarity" | "polynomial", <model fields>, "sigmas": {...}},
     "conditions": {"date": "YYYY-MM-DD" | null, "temperature_range": [lo, hi] | null, "n_images",
                    "strips", "transversal_strip", "n_gcp", "priors": {name: sigma}, "images": [...]},
     "quality": {"sigma0", "reprojection_rms_px", "dof"},
     "provenance": {"flow_run": str | null, "code_version": str, "inputs": {name: sha256 hex}}}

Units: f, cx, cy, b1, b2 and their sigmas in pixels; k1..k3, p1, p2 dimensionless; temperatures in
degrees Celsius; thermal slopes in pixels per degree Celsius; ``pixel_size_mm`` in millimetres.
Values that a certificate imported from a foreign format cannot know (date, image counts, quality
figures) are ``null``.

:meth:`Certificate.from_dict` validates strictly: every malformed document raises
:class:`CertificateError` with one line naming the field path (``model.params.f``), what was expected,
what was found and how to fix it.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import json
import math
import re
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aerocal.camera import (
    PARAM_NAMES,
    PARAM_UNITS,
    Camera,
    LinearThermalModel,
    SimilarityThermalModel,
    ThermalModel,
    thermal_model_from_dict,
)
from aerocal.decision import ACCEPTED, REJECTED, STATUSES, Review

#: The schema identifier written into, and required from, every certificate document.
SCHEMA = "aerocal.certificate/1"

#: Names of the slopes of :class:`aerocal.camera.LinearThermalModel` (pixels per degree Celsius).
THERMAL_SLOPE_NAMES: tuple[str, ...] = ("df_dt", "dcx_dt", "dcy_dt")

#: Fields left out of :meth:`Certificate.content_hash`: they identify an issue, not the calibration.
HASH_EXCLUDED_FIELDS: tuple[str, ...] = ("id", "issued", "version", "supersedes")

_HEX32 = re.compile(r"^[0-9a-f]{32}$")
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_DATE = re.compile(r"^\d{4}-\d{2}-\d{2}$")
_CORRELATION_TOL = 1e-9


class CertificateError(ValueError):
    """A certificate document or object is malformed; the message names the field path and the fix."""


# =============================================================================== immutable containers
class FrozenMap(dict):
    """A ``dict`` that refuses mutation: hashable, picklable, JSON-serialisable as a plain object."""

    def _refuse(self, *args: object, **kwargs: object) -> None:
        raise TypeError("certificate content is immutable; build a new certificate instead")

    __setitem__ = __delitem__ = _refuse  # type: ignore[assignment]
    clear = pop = popitem = setdefault = update = __ior__ = _refuse  # type: ignore[assignment]

    def __hash__(self) -> int:  # type: ignore[override]
        return hash(tuple(sorted(self.items())))

    def __reduce__(self) -> tuple:
        return (type(self), (dict(self),))

    def __repr__(self) -> str:
        return f"FrozenMap({dict.__repr__(self)})"


def _freeze_map(m: Mapping | None) -> FrozenMap:
    return m if isinstance(m, FrozenMap) else FrozenMap(m or {})


def _freeze_seq(s: Iterable | None) -> tuple:
    return tuple(s) if s is not None else ()


# =============================================================================== parts of a certificate
@dataclass(frozen=True)
class CameraIdentity:
    """Which physical camera a certificate belongs to. Empty or unknown parts are ``"unknown"``."""

    make: str = "unknown"
    model: str = "unknown"
    serial: str = "unknown"
    lens: str = "unknown"

    @property
    def key(self) -> str:
        """``"make|model|serial|lens"``: the key the certificate store groups certificates by."""
        return "|".join((self.make, self.model, self.serial, self.lens))

    @classmethod
    def unknown(cls) -> CameraIdentity:
        return cls()

    @classmethod
    def from_key(cls, key: str) -> CameraIdentity:
        """Inverse of :attr:`key`."""
        parts = key.split("|")
        if len(parts) != 4:
            raise CertificateError(
                f"camera key {key!r}: expected 4 parts 'make|model|serial|lens', got {len(parts)}; "
                "write the key as make|model|serial|lens (use 'unknown' for a missing part)"
            )
        return cls(*parts)


@dataclass(frozen=True)
class ParameterSignificance:
    """Significance test of one parameter: t = value / sigma, significant at the 95 % level, why a
    parameter was dropped from the model (``None`` when it was kept), and where it was measured, its gain on
    data the fit did not use (:mod:`aerocal.heldout`: relative reduction of the held-out mean squared
    residual, with its standard error) and its t calibrated against the null measured on the block (formal t over
    the square root of the overdispersion of pure-noise hypotheses: formal statistics are optimistic on real
    matches)."""

    t: float
    significant: bool
    dropped: str | None = None
    held_out_gain: float | None = None  # relative gain on held-out strips (aerocal.heldout), None: not measured
    held_out_sigma: float | None = None  # its standard error
    calibrated_t: float | None = None  # t over the square root of the block's measured overdispersion
    #: for a parameter held at its nominal value because the block could not determine it: the standard
    #: deviation of that nominal value (units of the parameter), which the diagnosis carries as the IO's
    #: uncertainty instead of treating the nominal as exact
    prior_sigma: float | None = None


@dataclass(frozen=True)
class Correlation:
    """Correlation matrix of the estimated parameters: ``matrix[i][j]`` correlates ``names[i]`` and
    ``names[j]``. Names are IO parameter names (:data:`aerocal.camera.PARAM_NAMES`) and, where the
    thermal model was estimated jointly, its slope names."""

    names: tuple[str, ...] = ()
    matrix: tuple[tuple[float, ...], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(str(n) for n in _freeze_seq(self.names)))
        n = len(self.names)
        try:
            rows = np.asarray(self.matrix, dtype=float).reshape(n, n) if n else np.zeros((0, 0))
        except ValueError:
            raise CertificateError(
                f"correlation.matrix: expected {n} x {n} numbers for names {list(self.names)}; "
                "give one row and one column per name"
            ) from None
        object.__setattr__(self, "matrix", tuple(tuple(float(v) for v in r) for r in rows))

    def array(self) -> np.ndarray:
        """The matrix as an (n, n) array."""
        return np.asarray(self.matrix, dtype=float).reshape(len(self.names), len(self.names))

    def value(self, a: str, b: str) -> float:
        """The correlation between parameters ``a`` and ``b``."""
        i, j = self.names.index(a), self.names.index(b)
        return self.matrix[i][j]

    def high_pairs(self, threshold: float = 0.9) -> list[tuple[str, str, float]]:
        """Pairs with ``|r| > threshold``, strongest first."""
        m = self.array()
        i, j = np.triu_indices(len(self.names), k=1)
        keep = np.abs(m[i, j]) > threshold
        pairs = [(self.names[a], self.names[b], float(m[a, b]))
                 for a, b in zip(i[keep], j[keep], strict=True)]
        return sorted(pairs, key=lambda p: -abs(p[2]))


def sigmas_and_correlation(
    names: Iterable[str], covariance: np.ndarray
) -> tuple[dict[str, float], Correlation]:
    """Standard deviations and correlation matrix from a covariance matrix of the named parameters.

    ``covariance`` in the parameters' units squared (pixels^2 for f, cx, cy, b1, b2), already scaled by
    the a-posteriori variance factor if that is wanted.
    """
    names = tuple(names)
    cov = np.asarray(covariance, dtype=float)
    if cov.shape != (len(names), len(names)):
        raise CertificateError(
            f"covariance: expected shape {(len(names), len(names))} for parameters {list(names)}, got "
            f"{cov.shape}; pass one row and column per parameter"
        )
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov / np.outer(sig, sig)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    corr = np.clip(0.5 * (corr + corr.T), -1.0, 1.0)
    np.fill_diagonal(corr, 1.0)
    return dict(zip(names, sig.tolist(), strict=True)), Correlation(names, corr)


@dataclass(frozen=True)
class ThermalCalibration:
    """A thermal IO model with the sigmas of its estimated coefficients and its valid range (degC).

    For :class:`~aerocal.camera.LinearThermalModel` the valid range is the model's own ``valid_range``
    (given here or there, not differently in both); for the other kinds it is kept here.
    ``sigmas`` of a linear model are keyed by :data:`THERMAL_SLOPE_NAMES` (pixels per degC).
    """

    model: ThermalModel
    sigmas: Mapping[str, float] = field(default_factory=FrozenMap)
    valid_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "sigmas", _freeze_map(self.sigmas))
        vr = None if self.valid_range is None else tuple(float(v) for v in self.valid_range)
        if isinstance(self.model, LinearThermalModel):
            own = self.model.valid_range
            if vr is not None and own is not None and tuple(own) != vr:
                raise CertificateError(
                    f"thermal.valid_range: given {list(vr)} here and {list(own)} in the linear model; "
                    "give it once, in LinearThermalModel.valid_range"
                )
            if vr is not None and own is None:
                object.__setattr__(self, "model", dataclasses.replace(self.model, valid_range=vr))
            vr = None if self.model.valid_range is None else tuple(float(v) for v in self.model.valid_range)
        elif vr is None and isinstance(self.model, SimilarityThermalModel) and self.model.temperatures:
            vr = (float(min(self.model.temperatures)), float(max(self.model.temperatures)))
        object.__setattr__(self, "valid_range", vr)

    @property
    def kind(self) -> str:
        return self.model.to_dict()["kind"]

    def to_dict(self) -> dict:
        d = _plain(self.model.to_dict())
        if not isinstance(self.model, LinearThermalModel):
            d["valid_range"] = None if self.valid_range is None else list(self.valid_range)
        d["sigmas"] = dict(self.sigmas)
        return d


@dataclass(frozen=True)
class Conditions:
    """What the calibration was made under. ``None`` means unknown (e.g. imported from a foreign format).

    ``date`` is ``YYYY-MM-DD`` (the flight's date); ``temperature_range`` (degC) spans the sensor
    temperatures of the calibration images; ``priors`` maps each prior used to its sigma, the unit in
    the name (e.g. ``{"gnss_position_m": 0.05, "imu_attitude_deg": 0.02}``); ``images`` are the names of
    the subset's images (``n_images`` equals their number when they are listed).
    """

    date: str | None = None
    temperature_range: tuple[float, float] | None = None
    n_images: int | None = None
    strips: int | None = None
    transversal_strip: bool | None = None
    n_gcp: int | None = None
    priors: Mapping[str, float] = field(default_factory=FrozenMap)
    images: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.date, dt.date):
            object.__setattr__(self, "date", self.date.isoformat())
        if self.temperature_range is not None:
            object.__setattr__(self, "temperature_range", tuple(self.temperature_range))
        object.__setattr__(self, "priors", _freeze_map(self.priors))
        object.__setattr__(self, "images", _freeze_seq(self.images))

    def to_dict(self) -> dict:
        return {
            "date": self.date,
            "temperature_range": None if self.temperature_range is None else list(self.temperature_range),
            "n_images": self.n_images,
            "strips": self.strips,
            "transversal_strip": self.transversal_strip,
            "n_gcp": self.n_gcp,
            "priors": dict(self.priors),
            "images": list(self.images),
        }


@dataclass(frozen=True)
class Quality:
    """A-posteriori sigma0 (unitless), RMS reprojection error (pixels), degrees of freedom."""

    sigma0: float | None = None
    reprojection_rms_px: float | None = None
    dof: int | None = None

    def to_dict(self) -> dict:
        return {"sigma0": self.sigma0, "reprojection_rms_px": self.reprojection_rms_px, "dof": self.dof}


def code_version() -> str:
    """The running aerocal version (package metadata), or ``"unknown"`` when it is not installed."""
    import importlib.metadata

    try:
        return importlib.metadata.version("aerocal")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class Provenance:
    """Where a certificate came from: the flow run that made it, the code version, and the sha256 (hex)
    of every input, keyed by a name the producer chooses (file name, table name)."""

    flow_run: str | None = None
    code_version: str = field(default_factory=code_version)
    inputs: Mapping[str, str] = field(default_factory=FrozenMap)

    def __post_init__(self) -> None:
        object.__setattr__(self, "inputs", _freeze_map(self.inputs))

    def to_dict(self) -> dict:
        return {"flow_run": self.flow_run, "code_version": self.code_version, "inputs": dict(self.inputs)}


def _now_utc() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _new_id() -> str:
    return uuid.uuid4().hex


# =============================================================================== the certificate
@dataclass(frozen=True)
class Certificate:
    """An immutable calibration record for one camera; see the module docstring for its JSON shape.

    Build one with at least ``identity`` and ``camera``; ``id`` (uuid4 hex) and ``issued`` (now, UTC)
    are filled in. Every construction is validated as :meth:`from_dict` validates a document, so a
    certificate that exists always serialises to a valid document. ``sigmas`` hold the standard
    deviations of the estimated IO parameters (units of :data:`aerocal.camera.PARAM_UNITS`).
    """

    identity: CameraIdentity
    camera: Camera
    sigmas: Mapping[str, float] = field(default_factory=FrozenMap)
    estimated: tuple[str, ...] = ()
    correlation: Correlation = field(default_factory=Correlation)
    significance: Mapping[str, ParameterSignificance] = field(default_factory=FrozenMap)
    thermal: ThermalCalibration | None = None
    conditions: Conditions = field(default_factory=Conditions)
    quality: Quality = field(default_factory=Quality)
    provenance: Provenance = field(default_factory=Provenance)
    id: str = field(default_factory=_new_id)
    issued: dt.datetime = field(default_factory=_now_utc)
    version: int | None = None
    supersedes: str | None = None
    review: Review | None = None

    @property
    def status(self) -> str:
        """"accepted" or "rejected" (:class:`aerocal.decision.Review`); a certificate without a review (made
        elsewhere and imported) counts as accepted once its values pass the import checks."""
        return self.review.status if self.review is not None else ACCEPTED

    def __post_init__(self) -> None:
        object.__setattr__(self, "sigmas", _freeze_map(self.sigmas))
        object.__setattr__(self, "estimated", _freeze_seq(self.estimated))
        object.__setattr__(self, "significance", _freeze_map(self.significance))
        # Validate (and normalise: numpy scalars and numbers to float, containers to immutable)
        # through the document.
        for name, value in _parse_document(_plain(self.to_dict())).items():
            object.__setattr__(self, name, value)

    # ----------------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        """The JSON document (plain dicts, lists, str, float, int, bool, None)."""
        cam = self.camera
        issued = self.issued
        if isinstance(issued, dt.datetime) and issued.tzinfo is not None:
            issued_text = issued.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")
        else:
            issued_text = issued.isoformat() if isinstance(issued, dt.datetime) else issued
        return {
            "schema": SCHEMA,
            "id": self.id,
            "camera": dataclasses.asdict(self.identity),
            "version": self.version,
            "supersedes": self.supersedes,
            "issued": issued_text,
            "model": {
                "kind": "brown",
                "width": cam.width,
                "height": cam.height,
                "pixel_size_mm": cam.pixel_size_mm,
                "params": {n: getattr(cam, n) for n in PARAM_NAMES},
            },
            "sigmas": dict(self.sigmas),
            "estimated": list(self.estimated),
            "correlation": {"names": list(self.correlation.names),
                            "matrix": [list(r) for r in self.correlation.matrix]},
            "significance": {
                n: (_significance_dict(s) if isinstance(s, ParameterSignificance) else s)
                for n, s in self.significance.items()
            },
            "thermal": None if self.thermal is None else self.thermal.to_dict(),
            "conditions": self.conditions.to_dict(),
            "quality": self.quality.to_dict(),
            "provenance": self.provenance.to_dict(),
            **({"review": self.review.to_dict()} if self.review is not None else {}),
        }

    @classmethod
    def from_dict(cls, doc: Any) -> Certificate:
        """Validate a document strictly and build the certificate; :class:`CertificateError` otherwise."""
        return cls(**_parse_document(doc))

    def to_json(self, indent: int | None = 2) -> str:
        """The document as JSON text (no NaN or Infinity: strict JSON)."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False, ensure_ascii=False)

    @classmethod
    def from_json(cls, text: str | bytes) -> Certificate:
        """Parse JSON text and validate it; a syntax error names the line and column."""
        try:
            doc = json.loads(text, parse_constant=_refuse_constant)
        except json.JSONDecodeError as e:
            raise CertificateError(
                f"line {e.lineno} column {e.colno}: invalid JSON ({e.msg}); fix the syntax there"
            ) from None
        return cls.from_dict(doc)

    def content_hash(self) -> str:
        """sha256 (hex) of the canonical JSON of the calibration's content.

        Canonical: keys sorted, no whitespace, floats in shortest round-trip form; the fields of
        :data:`HASH_EXCLUDED_FIELDS` (id, issued, version, supersedes) are left out, so the same
        calibration issued twice has the same hash.
        """
        doc = {k: v for k, v in self.to_dict().items() if k not in HASH_EXCLUDED_FIELDS}
        text = json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=False, ensure_ascii=False)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    # ----------------------------------------------------------------- store support
    def with_version(self, version: int, supersedes: str | None) -> Certificate:
        """A copy numbered ``version`` that supersedes certificate id ``supersedes`` (or none)."""
        return dataclasses.replace(self, version=version, supersedes=supersedes)

    @property
    def valid_temperature_range(self) -> tuple[float, float] | None:
        """The temperatures (degC) the certificate is valid for: the thermal model's valid range where
        there is one, else the temperature range of the calibration images, else ``None``."""
        if self.thermal is not None and self.thermal.valid_range is not None:
            return self.thermal.valid_range
        return self.conditions.temperature_range

    def covers(self, temperature_range: tuple[float, float] | None, margin: float = 0.0) -> bool:
        """Whether the certificate is valid over ``temperature_range`` (degC, ``(lo, hi)``).

        ``None`` (a flight without temperatures) is always covered. A certificate that records no
        temperature range covers no given range: nothing says it holds there. ``margin`` (degC) widens
        the certificate's range on both sides.
        """
        if temperature_range is None:
            return True
        lo, hi = (float(v) for v in temperature_range)
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
            raise CertificateError(
                f"temperature_range: expected finite (lo, hi) with lo <= hi, got {temperature_range!r}; "
                "pass the flight's minimum and maximum sensor temperature in degC"
            )
        valid = self.valid_temperature_range
        if valid is None:
            return False
        return valid[0] - margin <= lo and hi <= valid[1] + margin

    # ----------------------------------------------------------------- text rendering
    def render_text(self, correlation_threshold: float = 0.9) -> str:
        """A human-readable summary: parameters ± sigma with units, significance, strong correlations."""
        cam = self.camera
        lines = [f"Calibration certificate {self.id}"]
        ver = "unversioned" if self.version is None else f"version {self.version}"
        if self.supersedes:
            ver += f", supersedes {self.supersedes}"
        lines.append(f"  camera   {self.identity.key}  ({ver})")
        made = self.conditions.date or "unknown date"
        lines.append(f"  issued   {self.to_dict()['issued']}   made on {made}")
        size = f"{cam.width} x {cam.height} px"
        if cam.pixel_size_mm is not None:
            size += f", pixel {cam.pixel_size_mm * 1000:.3g} um, focal {cam.focal_mm:.4f} mm"
        lines.append(f"  model    Brown, {size}")
        lines.append("  parameters (value ± sigma):")
        for name in PARAM_NAMES:
            value = getattr(cam, name)
            unit = "" if PARAM_UNITS[name] == "1" else f" {PARAM_UNITS[name]}"
            sig = self.significance.get(name)
            if name in self.estimated:
                text = _pm(value, self.sigmas.get(name)) + unit
                status = "estimated"
            else:
                text = _pm(value, None) + unit
                status = "fixed"
            if sig is not None:
                status += f", t = {sig.t:.3g}, " + ("significant" if sig.significant else "not significant")
                if sig.calibrated_t is not None:
                    status += f" (calibrated t {sig.calibrated_t:.3g})"
                if sig.held_out_gain is not None:
                    spread = 100 * (sig.held_out_sigma or 0.0)
                    status += f", held-out gain {100 * sig.held_out_gain:+.2f} +- {spread:.2f} %"
                if sig.dropped:
                    status += f", dropped: {sig.dropped}"
            lines.append(f"    {name:<3} {text:>28}   {status}")
        pairs = self.correlation.high_pairs(correlation_threshold)
        if pairs:
            lines.append(f"  correlations above {correlation_threshold:g}: "
                         + ", ".join(f"{a}-{b} {r:+.3f}" for a, b, r in pairs))
        elif self.correlation.names:
            lines.append(f"  no correlation above {correlation_threshold:g}")
        lines.extend(self._render_thermal())
        c = self.conditions
        strips = "?" if c.strips is None else str(c.strips)
        transversal = {None: "unknown", True: "yes", False: "no"}[c.transversal_strip]
        lines.append(
            f"  conditions: {_or_q(c.n_images)} images, {strips} strips (transversal: {transversal}), "
            f"{_or_q(c.n_gcp)} GCPs"
            + ("" if c.temperature_range is None
               else f", {c.temperature_range[0]:.1f} to {c.temperature_range[1]:.1f} degC")
        )
        if c.priors:
            lines.append("  priors (sigma): " + ", ".join(f"{k} {v:g}" for k, v in c.priors.items()))
        q = self.quality
        sigma0 = "?" if q.sigma0 is None else f"{q.sigma0:.3f}"
        rms = "?" if q.reprojection_rms_px is None else f"{q.reprojection_rms_px:.3f} px"
        lines.append(f"  quality: sigma0 {sigma0}, reprojection RMS {rms}, dof {_or_q(q.dof)}")
        if self.review is not None:
            lines.append(f"  review: {self.review.status.upper()}")
            lines.extend(f"    problem: {x}" for x in self.review.problems)
            lines.extend(f"    note: {x}" for x in self.review.notes)
            lines.extend(f"    check: {x}" for x in self.review.checks)
        p = self.provenance
        lines.append(f"  provenance: flow run {p.flow_run or '-'}, code {p.code_version}, "
                     f"{len(p.inputs)} inputs hashed")
        lines.append(f"  content sha256 {self.content_hash()}")
        return "\n".join(lines)

    def _render_thermal(self) -> list[str]:
        th = self.thermal
        if th is None:
            return ["  thermal model: none"]
        vr = ("unknown" if th.valid_range is None
              else f"{th.valid_range[0]:.1f} to {th.valid_range[1]:.1f} degC")
        m = th.model
        if isinstance(m, LinearThermalModel):
            slopes = ", ".join(
                f"{n} {_pm(getattr(m, n), th.sigmas.get(n))} px/degC" for n in THERMAL_SLOPE_NAMES
            )
            return [f"  thermal model: linear, T0 {m.t0:.2f} degC, {slopes}; valid {vr}"]
        if isinstance(m, SimilarityThermalModel):
            return [f"  thermal model: similarity at {len(m.temperatures)} temperatures; valid {vr}"]
        return [f"  thermal model: polynomial of degree {m.degree}, T0 {m.t0:.2f} degC; valid {vr}"]


# =============================================================================== document validation
def _show(value: Any) -> str:
    try:
        text = json.dumps(value, allow_nan=True, default=repr)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _fail(path: str, expected: str, got: Any, fix: str) -> CertificateError:
    return CertificateError(f"{path}: expected {expected}, got {_show(got)}; {fix}")


def _refuse_constant(name: str) -> None:
    raise CertificateError(f"JSON constant {name} is not allowed (strict JSON); "
                           "write a finite number or null")


def _object(v: Any, path: str, keys: Iterable[str], optional: Iterable[str] = ()) -> Mapping:
    keys, optional = tuple(keys), tuple(optional)
    if not isinstance(v, Mapping):
        raise _fail(path or "document", "a JSON object", v, "write an object {...} here")
    for k in v:
        if k not in keys and k not in optional:
            raise CertificateError(
                f"{_join(path, k)}: unknown field; valid fields of {path or 'the document'}: "
                f"{', '.join(keys + optional)}; remove or rename it"
            )
    for k in keys:
        if k not in v:
            raise CertificateError(f"{_join(path, k)}: missing; add it (null where the value is unknown and "
                                   "null is allowed)")
    return v


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


def _number(v: Any, path: str, *, positive: bool = False, nonneg: bool = False, nullable: bool = False,
            fix: str = "write a finite JSON number") -> float | None:
    if v is None and nullable:
        return None
    what = "a positive number" if positive else "a non-negative number" if nonneg else "a finite number"
    if nullable:
        what += " or null"
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _fail(path, what, v, fix)
    try:
        x = float(v)
    except OverflowError:  # an integer written out with hundreds of digits
        raise _fail(path, what, v, fix) from None
    if not math.isfinite(x) or (positive and x <= 0) or (nonneg and x < 0):
        raise _fail(path, what, v, fix)
    return x


def _integer(v: Any, path: str, *, minimum: int = 0, nullable: bool = False, fix: str = "") -> int | None:
    if v is None and nullable:
        return None
    what = f"an integer >= {minimum}" + (" or null" if nullable else "")
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise _fail(path, what, v, fix or "write a whole JSON number without a decimal point")
    return int(v)


def _string(v: Any, path: str, *, nullable: bool = False, nonempty: bool = True, fix: str = "") -> str | None:
    if v is None and nullable:
        return None
    if not isinstance(v, str) or (nonempty and not v):
        what = ("a non-empty string" if nonempty else "a string") + (" or null" if nullable else "")
        raise _fail(path, what, v, fix or "write a JSON string in double quotes")
    return v


def _boolean(v: Any, path: str, *, nullable: bool = False) -> bool | None:
    if v is None and nullable:
        return None
    if not isinstance(v, bool):
        raise _fail(path, "true or false" + (" or null" if nullable else ""), v, "write true or false")
    return v


def _array(v: Any, path: str, *, length: int | None = None) -> list | tuple:
    if not isinstance(v, list | tuple) or (length is not None and len(v) != length):
        what = "a JSON array" if length is None else f"an array of {length} elements"
        raise _fail(path, what, v, "write [...] here")
    return v


def _range(v: Any, path: str, *, nullable: bool = True) -> tuple[float, float] | None:
    if v is None and nullable:
        return None
    a = _array(v, path, length=2)
    lo = _number(a[0], f"{path}[0]", fix="write [lowest, highest] in degC")
    hi = _number(a[1], f"{path}[1]", fix="write [lowest, highest] in degC")
    if lo > hi:
        raise _fail(path, "[lo, hi] with lo <= hi", v, "swap the two values")
    return (lo, hi)


def _name_map(v: Any, path: str, names: Iterable[str] | None, value_fn) -> FrozenMap:
    if not isinstance(v, Mapping):
        raise _fail(path, "a JSON object {name: value}", v, "write an object here ({} when empty)")
    allowed = None if names is None else tuple(names)
    out = {}
    for k, x in v.items():
        if not isinstance(k, str) or not k:
            raise _fail(path, "non-empty string keys", k, "name each entry")
        if allowed is not None and k not in allowed:
            raise CertificateError(f"{_join(path, k)}: unknown name; valid names: {', '.join(allowed)}; "
                                   "remove or rename it")
        out[k] = value_fn(x, _join(path, k))
    return FrozenMap(out)


def _parse_model(v: Any) -> Camera:
    m = _object(v, "model", ("kind", "width", "height", "pixel_size_mm", "params"))
    if m["kind"] != "brown":
        raise _fail("model.kind", '"brown"', m["kind"], 'write "brown" (the only camera model of schema 1)')
    width = _integer(m["width"], "model.width", minimum=1, fix="write the image width in pixels")
    height = _integer(m["height"], "model.height", minimum=1, fix="write the image height in pixels")
    pix = _number(m["pixel_size_mm"], "model.pixel_size_mm", positive=True, nullable=True,
                  fix="write the pixel pitch in millimetres (e.g. 0.017), or null when unknown")
    p = _object(m["params"], "model.params", PARAM_NAMES)
    params = {}
    for n in PARAM_NAMES:
        unit = "pixels" if PARAM_UNITS[n] == "px" else "a dimensionless coefficient"
        params[n] = _number(p[n], f"model.params.{n}", positive=(n == "f"),
                            fix=f"write {n} as a JSON number ({unit})")
    _sane_model(width, height, pix, params)
    return Camera(width=width, height=height, pixel_size_mm=pix, **params)


#: Bounds no real frame camera leaves (a document outside them is corrupt or hostile, not a camera): image
#: side in pixels, focal length in image sides, principal point within one image side of the image,
#: distortion coefficients, affinity and skew in focal lengths, pixel pitch in millimetres.
MAX_IMAGE_SIDE_PX = 200_000
MAX_FOCAL_IN_SIDES = 1000.0
MAX_DISTORTION_COEFFICIENT = 100.0
MAX_PIXEL_SIZE_MM = 1.0


def validate_camera(camera: Camera) -> None:
    """Raise :class:`CertificateError` naming the field when ``camera`` holds a value no real frame camera
    has (non-finite, or outside the bounds above): a nominal camera from ``camera.json`` gets the checks
    a certificate gets."""
    params = {n: float(getattr(camera, n)) for n in PARAM_NAMES}
    for n, x in params.items():
        if not math.isfinite(x) or (n == "f" and x <= 0):
            raise _fail(f"model.params.{n}", "a positive number" if n == "f" else "a finite number", x,
                        f"write {n} as a finite number")
    _sane_model(int(camera.width), int(camera.height), camera.pixel_size_mm, params)


def _sane_model(width: int, height: int, pix: float | None, params: dict[str, float]) -> None:
    side = max(width, height)
    for name, size in (("width", width), ("height", height)):
        if size > MAX_IMAGE_SIDE_PX:
            raise _fail(f"model.{name}", f"at most {MAX_IMAGE_SIDE_PX} pixels", size, "write the image size in pixels")
    if params["f"] > MAX_FOCAL_IN_SIDES * side:
        raise _fail("model.params.f", f"at most {MAX_FOCAL_IN_SIDES:g} x the larger image side "
                    f"({MAX_FOCAL_IN_SIDES * side:g} px)", params["f"], "write the focal length in pixels")
    for name, size in (("cx", width), ("cy", height)):
        if not -size <= params[name] <= 2 * size:
            raise _fail(f"model.params.{name}", f"within one image side of the image ({-size} to {2 * size} px)",
                        params[name], "write the principal point in pixels from the top-left corner")
    for name in ("k1", "k2", "k3", "p1", "p2"):
        if abs(params[name]) > MAX_DISTORTION_COEFFICIENT:
            raise _fail(f"model.params.{name}", f"a coefficient of magnitude at most {MAX_DISTORTION_COEFFICIENT:g}",
                        params[name], "write the Brown coefficient for normalised coordinates")
    for name in ("b1", "b2"):
        if abs(params[name]) > params["f"]:
            raise _fail(f"model.params.{name}", "smaller in magnitude than f", params[name],
                        "write the affinity/skew in pixels")
    if pix is not None and pix > MAX_PIXEL_SIZE_MM:
        raise _fail("model.pixel_size_mm", f"at most {MAX_PIXEL_SIZE_MM:g} mm", pix,
                    "write the pixel pitch in millimetres (e.g. 0.017)")


def _parse_correlation(v: Any) -> Correlation:
    c = _object(v, "correlation", ("names", "matrix"))
    names = [_string(x, f"correlation.names[{i}]")
             for i, x in enumerate(_array(c["names"], "correlation.names"))]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise _fail("correlation.names", "unique names", dup, "list each parameter once")
    rows = _array(c["matrix"], "correlation.matrix", length=len(names))
    matrix = []
    for i, row in enumerate(rows):
        row = _array(row, f"correlation.matrix[{i}]", length=len(names))
        matrix.append([_number(x, f"correlation.matrix[{i}][{j}]", fix="write a correlation in [-1, 1]")
                       for j, x in enumerate(row)])
    m = np.asarray(matrix, dtype=float).reshape(len(names), len(names))
    if m.size:
        bad = np.argwhere(np.abs(m) > 1.0 + _CORRELATION_TOL)
        if len(bad):
            i, j = bad[0]
            raise _fail(f"correlation.matrix[{i}][{j}]", "a correlation in [-1, 1]", matrix[i][j],
                        "write correlations, not covariances")
        diag = np.flatnonzero(np.abs(np.diag(m) - 1.0) > _CORRELATION_TOL)
        if len(diag):
            i = int(diag[0])
            raise _fail(f"correlation.matrix[{i}][{i}]", "1 on the diagonal", matrix[i][i],
                        "write correlations, not covariances")
        asym = np.argwhere(np.abs(m - m.T) > _CORRELATION_TOL)
        if len(asym):
            i, j = asym[0]
            raise _fail(f"correlation.matrix[{i}][{j}]", f"the same value as [{j}][{i}] ({matrix[j][i]})",
                        matrix[i][j], "make the matrix symmetric")
    return Correlation(tuple(names), m)


def _parse_significance(v: Any) -> FrozenMap:
    def one(x: Any, path: str) -> ParameterSignificance:
        s = _object(x, path, ("t", "significant", "dropped"),
                    optional=("held_out_gain", "held_out_sigma", "calibrated_t", "prior_sigma"))
        return ParameterSignificance(
            t=_number(s["t"], f"{path}.t", fix="write the t statistic (value / sigma)"),
            significant=_boolean(s["significant"], f"{path}.significant"),
            dropped=_string(s["dropped"], f"{path}.dropped", nullable=True,
                            fix="write why the parameter was dropped, or null when it was kept"),
            held_out_gain=_number(s.get("held_out_gain"), f"{path}.held_out_gain", nullable=True,
                                  fix="write the relative held-out gain, or null when not measured"),
            held_out_sigma=_number(s.get("held_out_sigma"), f"{path}.held_out_sigma", nullable=True, nonneg=True,
                                   fix="write the held-out gain's standard error, or null"),
            calibrated_t=_number(s.get("calibrated_t"), f"{path}.calibrated_t", nullable=True,
                                 fix="write t over the square root of the block's overdispersion, or null"),
            prior_sigma=_number(s.get("prior_sigma"), f"{path}.prior_sigma", nullable=True, nonneg=True,
                                fix="write the standard deviation of the nominal value held, or null"),
        )

    return _name_map(v, "significance", PARAM_NAMES + THERMAL_SLOPE_NAMES, one)


def _numbers(v: Any, path: str, *, length: int | None = None) -> tuple[float, ...]:
    a = _array(v, path, length=length)
    return tuple(_number(x, f"{path}[{i}]") for i, x in enumerate(a))


def _parse_thermal(v: Any) -> ThermalCalibration | None:
    if v is None:
        return None
    if not isinstance(v, Mapping):
        raise _fail("thermal", "an object or null", v, "write the thermal model object, or null when none")
    kind = v.get("kind")
    sigma_fn = lambda x, p: _number(x, p, nonneg=True, fix="write a standard deviation >= 0")  # noqa: E731
    if kind == "linear":
        t = _object(v, "thermal", ("kind", "t0", "df_dt", "dcx_dt", "dcy_dt", "valid_range", "sigmas"))
        model = LinearThermalModel(
            t0=_number(t["t0"], "thermal.t0", fix="write the reference temperature in degC"),
            **{n: _number(t[n], f"thermal.{n}", fix="write the slope in pixels per degC")
               for n in THERMAL_SLOPE_NAMES},
            valid_range=_range(t["valid_range"], "thermal.valid_range"),
        )
        sigmas = _name_map(t["sigmas"], "thermal.sigmas", THERMAL_SLOPE_NAMES, sigma_fn)
        return ThermalCalibration(model, sigmas)
    if kind == "similarity":
        t = _object(v, "thermal", ("kind", "temperatures", "tx", "ty", "scale", "theta", "centre",
                                   "valid_range", "sigmas"))
        temps = _numbers(t["temperatures"], "thermal.temperatures")
        if not temps:
            raise _fail("thermal.temperatures", "at least one temperature", [],
                        "list the tabulated temperatures")
        cols = {n: _numbers(t[n], f"thermal.{n}", length=len(temps)) for n in ("tx", "ty", "scale", "theta")}
        centre = _numbers(t["centre"], "thermal.centre", length=2)
        model = SimilarityThermalModel(temperatures=temps, centre=centre, **cols)
    elif kind == "polynomial":
        t = _object(v, "thermal", ("kind", "t0", "centre", "norm", "coefficients", "degree", "valid_range",
                                   "sigmas"))
        degree = _integer(t["degree"], "thermal.degree", minimum=0)
        shape = (2, 3, degree + 1, degree + 1)
        try:
            coef = np.asarray(t["coefficients"], dtype=float)
        except (TypeError, ValueError):
            coef = None
        if coef is None or coef.shape != shape or not np.all(np.isfinite(coef)):
            raise _fail("thermal.coefficients", f"finite numbers nested with shape {list(shape)}",
                        t["coefficients"], "write coefficients[axis][power of dT - 1][i][j]")
        model = thermal_model_from_dict({
            "kind": "polynomial",
            "t0": _number(t["t0"], "thermal.t0", fix="write the reference temperature in degC"),
            "centre": _numbers(t["centre"], "thermal.centre", length=2),
            "norm": _number(t["norm"], "thermal.norm", positive=True,
                            fix="write the normalisation in pixels"),
            "coefficients": coef, "degree": degree,
        })
    else:
        raise _fail("thermal.kind", '"linear", "similarity" or "polynomial"', kind,
                    "write one of the thermal model kinds of aerocal.camera")
    sigmas = _name_map(t["sigmas"], "thermal.sigmas", None, sigma_fn)
    return ThermalCalibration(model, sigmas, valid_range=_range(t["valid_range"], "thermal.valid_range"))


def _parse_conditions(v: Any) -> Conditions:
    c = _object(v, "conditions", ("date", "temperature_range", "n_images", "strips", "transversal_strip",
                                  "n_gcp", "priors", "images"))
    date = _string(c["date"], "conditions.date", nullable=True, fix='write the date as "YYYY-MM-DD"')
    if date is not None:
        try:
            ok = bool(_DATE.match(date)) and dt.date.fromisoformat(date) is not None
        except ValueError:
            ok = False
        if not ok:
            raise _fail("conditions.date", 'a date "YYYY-MM-DD" or null', date, 'write e.g. "2024-05-17"')
    images = tuple(_string(x, f"conditions.images[{i}]")
                   for i, x in enumerate(_array(c["images"], "conditions.images")))
    n_images = _integer(c["n_images"], "conditions.n_images", nullable=True)
    if images and n_images != len(images):
        raise _fail("conditions.n_images", f"{len(images)} (the number of names in conditions.images)",
                    n_images, "make n_images equal the length of images")
    return Conditions(
        date=date,
        temperature_range=_range(c["temperature_range"], "conditions.temperature_range"),
        n_images=n_images,
        strips=_integer(c["strips"], "conditions.strips", nullable=True),
        transversal_strip=_boolean(c["transversal_strip"], "conditions.transversal_strip", nullable=True),
        n_gcp=_integer(c["n_gcp"], "conditions.n_gcp", nullable=True),
        priors=_name_map(c["priors"], "conditions.priors", None, _prior_sigma),
        images=images,
    )


def _prior_sigma(x: Any, path: str) -> float:
    return _number(x, path, positive=True, fix="write the prior's sigma, its unit in the name (e.g. gnss_m)")


def _parse_issued(v: Any) -> dt.datetime:
    fix = 'write UTC time as ISO-8601 with a Z suffix, e.g. "2024-05-17T09:30:00Z"'
    s = _string(v, "issued", fix=fix)
    try:
        t = dt.datetime.fromisoformat(s)
    except ValueError:
        raise _fail("issued", "an ISO-8601 UTC time", v, fix) from None
    if t.tzinfo is None or t.utcoffset() != dt.timedelta(0):
        raise _fail("issued", "a UTC time (Z suffix)", v, fix)
    return t.astimezone(dt.UTC)


def _parse_document(doc: Any) -> dict[str, Any]:
    """Validate a certificate document; return the keyword arguments of :class:`Certificate`."""
    if isinstance(doc, Mapping) and "schema" in doc and doc["schema"] != SCHEMA:
        raise _fail("schema", f'"{SCHEMA}"', doc["schema"], "this aerocal reads certificate schema 1 only; "
                    "re-export the certificate or upgrade aerocal")
    d = _object(doc, "", ("schema", "id", "camera", "version", "supersedes", "issued", "model", "sigmas",
                          "estimated", "correlation", "significance", "thermal", "conditions", "quality",
                          "provenance"), optional=("review",))
    cid = _string(d["id"], "id")
    if not _HEX32.match(cid):
        raise _fail("id", "32 lowercase hex digits (uuid4().hex)", cid, "write uuid.uuid4().hex")
    cam = _object(d["camera"], "camera", ("make", "model", "serial", "lens"))
    identity = CameraIdentity(**{k: _string(cam[k], f"camera.{k}", fix=f'write the camera {k}, or "unknown"')
                                 for k in ("make", "model", "serial", "lens")})
    for k in ("make", "model", "serial", "lens"):
        text = getattr(identity, k)
        if "|" in text or any(ord(ch) < 32 or ord(ch) == 127 for ch in text):
            raise _fail(f"camera.{k}", "one line of text without '|'", text,
                        "remove the '|' (it separates the parts of the camera key) and control characters")
    version = _integer(d["version"], "version", minimum=1, nullable=True,
                       fix="leave null; the certificate store numbers versions from 1")
    supersedes = _string(d["supersedes"], "supersedes", nullable=True)
    if supersedes is not None and not _HEX32.match(supersedes):
        raise _fail("supersedes", "the id (32 hex digits) of the superseded certificate, or null", supersedes,
                    "write the id of the certificate this one replaces")
    camera = _parse_model(d["model"])
    estimated = tuple(_string(x, f"estimated[{i}]")
                      for i, x in enumerate(_array(d["estimated"], "estimated")))
    for i, n in enumerate(estimated):
        if n not in PARAM_NAMES:
            raise _fail(f"estimated[{i}]", f"one of {', '.join(PARAM_NAMES)}", n,
                        "use the parameter names of aerocal.camera.PARAM_NAMES")
        if estimated.index(n) != i:
            raise _fail(f"estimated[{i}]", "each parameter once", n, "remove the duplicate")
    sigmas = _name_map(d["sigmas"], "sigmas", PARAM_NAMES,
                       lambda x, p: _number(x, p, nonneg=True, fix="write the standard deviation (>= 0)"))
    for n in sigmas:
        if n not in estimated:
            raise CertificateError(f"sigmas.{n}: {n} has a sigma but is not in estimated; "
                                   f"add {n} to estimated or remove its sigma")
    thermal = _parse_thermal(d["thermal"])
    correlation = _parse_correlation(d["correlation"])
    thermal_names = set(thermal.sigmas) | set(THERMAL_SLOPE_NAMES) if thermal is not None else set()
    for i, n in enumerate(correlation.names):
        if n not in estimated and n not in thermal_names:
            raise _fail(f"correlation.names[{i}]", "an estimated parameter (listed in estimated) or a "
                        "thermal slope", n, "add it to estimated or remove its row and column")
    significance = _parse_significance(d["significance"])
    for n, s in significance.items():
        if n in THERMAL_SLOPE_NAMES and thermal is None:
            raise CertificateError(f"significance.{n}: a thermal slope but thermal is null; "
                                   "add the thermal model or remove this entry")
        if s.dropped is not None and n in estimated:
            raise CertificateError(f"significance.{n}.dropped: {n} is marked dropped but is listed in "
                                   "estimated; remove it from estimated or set dropped to null")
    q = _object(d["quality"], "quality", ("sigma0", "reprojection_rms_px", "dof"))
    quality = Quality(
        sigma0=_number(q["sigma0"], "quality.sigma0", positive=True, nullable=True,
                       fix="write the a-posteriori sigma0 (unitless), or null when unknown"),
        reprojection_rms_px=_number(q["reprojection_rms_px"], "quality.reprojection_rms_px", nonneg=True,
                                    nullable=True, fix="write the RMS reprojection error in pixels, or null"),
        dof=_integer(q["dof"], "quality.dof", nullable=True),
    )
    p = _object(d["provenance"], "provenance", ("flow_run", "code_version", "inputs"))

    def sha(x: Any, path: str) -> str:
        s = _string(x, path)
        if not _SHA256.match(s):
            raise _fail(path, "a sha256 as 64 lowercase hex digits", s,
                        "write hashlib.sha256(data).hexdigest()")
        return s

    provenance = Provenance(
        flow_run=_string(p["flow_run"], "provenance.flow_run", nullable=True),
        code_version=_string(p["code_version"], "provenance.code_version",
                             fix='write the version, or "unknown"'),
        inputs=_name_map(p["inputs"], "provenance.inputs", None, sha),
    )
    return {
        "identity": identity, "camera": camera, "sigmas": sigmas, "estimated": estimated,
        "correlation": correlation, "significance": significance, "thermal": thermal,
        "conditions": _parse_conditions(d["conditions"]), "quality": quality, "provenance": provenance,
        "id": cid, "issued": _parse_issued(d["issued"]), "version": version, "supersedes": supersedes,
        "review": _parse_review(d.get("review")),
    }


def _parse_review(v: Any) -> Review | None:
    if v is None:
        return None
    r = _object(v, "review", ("status", "problems", "checks", "notes"))
    status = _string(r["status"], "review.status")
    if status not in STATUSES:
        raise _fail("review.status", " or ".join(f'"{x}"' for x in STATUSES), status,
                    "write the verdict of the calibration's review")
    lists = {k: tuple(_string(x, f"review.{k}[{i}]") for i, x in enumerate(_array(r[k], f"review.{k}")))
             for k in ("problems", "checks", "notes")}
    if status == ACCEPTED and lists["problems"]:
        raise CertificateError("review.problems: an accepted certificate lists problems; a problem rejects it "
                               '(write "rejected") or remove the problems')
    if status == REJECTED and not lists["problems"]:
        raise CertificateError("review.problems: a rejected certificate must say why; list the problems")
    return Review(status, **lists)


def _significance_dict(s: ParameterSignificance) -> dict:
    out = {"t": s.t, "significant": s.significant, "dropped": s.dropped}
    if s.held_out_gain is not None or s.held_out_sigma is not None:
        out.update(held_out_gain=s.held_out_gain, held_out_sigma=s.held_out_sigma)
    if s.calibrated_t is not None:
        out["calibrated_t"] = s.calibrated_t
    if s.prior_sigma is not None:
        out["prior_sigma"] = s.prior_sigma
    return out


# =============================================================================== helpers for rendering
def _plain(obj: Any) -> Any:
    """Tuples to lists, numpy scalars to Python numbers (JSON-ready)."""
    if isinstance(obj, Mapping):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | np.ndarray):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _pm(value: float, sigma: float | None) -> str:
    """``value ± sigma`` with the value rounded to the sigma's second significant digit."""
    if sigma is None or sigma <= 0 or not math.isfinite(sigma):
        return f"{value:.6g}"
    decimals = max(0, 1 - math.floor(math.log10(sigma)))
    if decimals > 6:
        return f"{value:.4e} ± {sigma:.2g}"
    return f"{value:.{decimals}f} ± {sigma:.{decimals}f}"


def _or_q(v: int | None) -> str:
    return "?" if v is None else str(v)


__all__ = [
    "SCHEMA",
    "THERMAL_SLOPE_NAMES",
    "CameraIdentity",
    "Certificate",
    "CertificateError",
    "Conditions",
    "Correlation",
    "FrozenMap",
    "ParameterSignificance",
    "Provenance",
    "Quality",
    "ThermalCalibration",
    "code_version",
    "sigmas_and_correlation",
]
