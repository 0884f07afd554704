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
     "quality": {"sigma0", "reprojection_rms_px", "dof", "overdispersion" (optional)},
     "provenance": {"flow_run": str | null, "code_version": str, "inputs": {name: sha256 hex}}}

Units: f, cx, cy, b1, b2 and their sigmas in pixels; k1..k3, p1, p2 dimensionless; temperatures in
degrees Celsius; thermal slopes in pixels per degree Celsius; ``pixel_size_mm`` in millimetres.
Values that a certificate imported from a foreign format cannot know (date, image counts, quality
figures) are ``null``.

The document's schema is :class:`aerocal.certificates.schema.CertificateDocument`, the one definition the
engine, the certificate store and the exchange formats validate with. :meth:`Certificate.from_dict` validates
strictly: every malformed document raises :class:`CertificateError` with one line naming the field path
(``model.params.f``), what was expected, what was found and how to fix it. The camera identity is
:class:`aerocal.certificates.identity.CameraIdentity` (re-exported here).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import importlib.metadata
import json
import math
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
from aerocal.certificates.identity import CameraIdentity
from aerocal.certificates.review import ACCEPTED, Review
from aerocal.certificates.schema import MAX_FOCAL_IN_SIDES as MAX_FOCAL_IN_SIDES  # re-exported
from aerocal.certificates.schema import MAX_IMAGE_SIDE_PX as MAX_IMAGE_SIDE_PX  # re-exported
from aerocal.certificates.schema import MAX_PIXEL_SIZE_MM as MAX_PIXEL_SIZE_MM  # re-exported
from aerocal.certificates.schema import MAX_TERM_DISPLACEMENT as MAX_TERM_DISPLACEMENT  # re-exported
from aerocal.certificates.schema import (
    SCHEMA,
    THERMAL_SLOPE_NAMES,
    CertificateDocument,
    CertificateError,
    LinearThermalSection,
    SimilarityThermalSection,
    camera_problem,
    parse_json,
    problem,
    validate_document,
)

#: Fields left out of :meth:`Certificate.content_hash`: they identify an issue, not the calibration.
HASH_EXCLUDED_FIELDS: tuple[str, ...] = ("id", "issued", "version", "supersedes")


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
class ParameterSignificance:
    """Significance test of one parameter: t = value / sigma, significant at the 95 % level, why a
    parameter was dropped from the model (``None`` when it was kept), and where it was measured, its gain on
    data the fit did not use (:mod:`aerocal.calibrate.heldout`: relative reduction of the held-out mean squared
    residual, with its standard error) and its t calibrated against the null measured on the block (formal t over
    the square root of the overdispersion of pure-noise hypotheses: formal statistics are optimistic on real
    matches)."""

    t: float
    significant: bool
    dropped: str | None = None
    #: relative gain on held-out strips (aerocal.calibrate.heldout), None: not measured
    held_out_gain: float | None = None
    held_out_sigma: float | None = None  # its standard error
    calibrated_t: float | None = None  # t over the square root of the block's measured overdispersion
    #: for a parameter held at its nominal value because the block could not determine it: the standard
    #: deviation of that nominal value (units of the parameter), which the diagnosis carries as the IO's
    #: uncertainty instead of treating the nominal as exact
    prior_sigma: float | None = None


@dataclass(frozen=True)
class CameraTerm:
    """A camera term a flight's diagnosis found and confirmed on data the fit did not use (the document's
    ``effects`` entry): its ``values`` and ``sigmas`` in ``units`` (:mod:`aerocal.effects`), how it is ``applied``
    ("model": through ``model.params`` or the thermal model, which hold it; "measurements": the block adjustment
    corrects the measurements for it at the adjusted geometry, as for a rolling-shutter readout), the ``flights``
    whose diagnoses support it and the ``evidence`` in words."""

    values: tuple[float, ...]
    sigmas: tuple[float, ...]
    units: str
    applied: str
    flights: tuple[str, ...]
    evidence: str
    reference_temperature: float | None = None  # degC, of a term that depends on the temperature

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", tuple(float(v) for v in self.values))
        object.__setattr__(self, "sigmas", tuple(float(v) for v in self.sigmas))
        object.__setattr__(self, "flights", tuple(str(f) for f in self.flights))

    def to_dict(self) -> dict:
        out = {"values": list(self.values), "sigmas": list(self.sigmas), "units": self.units,
               "applied": self.applied, "flights": list(self.flights), "evidence": self.evidence}
        if self.reference_temperature is not None:
            out["reference_temperature"] = self.reference_temperature
        return out


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

    Raises:
        CertificateError: ``covariance`` is not square with one row and column per name of ``names``.
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
    """A-posteriori sigma0 (unitless), RMS reprojection error (pixels), degrees of freedom, and the calibration
    block's measured overdispersion.

    ``overdispersion``: how many times larger than chi-square the statistics of pure-noise hypotheses were on
    the calibration block (:func:`aerocal.diagnose.engine.overdispersion`; about 1 on a rendered block, well above 1
    on the real seneca flight's matches: ``benchmarks/history/engine_measurements.md``). Where
    it is recorded, the certificate's ``sigmas`` (and its thermal sigmas) are *calibrated*: the formal sigmas of
    the adjustment times the square root of ``max(overdispersion, 1)``, the precision the block supports;
    ``significance[...].t`` stays the formal t. ``None`` (documents written before it was recorded, imported
    certificates, a block where it could not be measured): the sigmas are as written, formal where they came
    from an adjustment."""

    sigma0: float | None = None
    reprojection_rms_px: float | None = None
    dof: int | None = None
    overdispersion: float | None = None

    @property
    def sigma_scale(self) -> float:
        """The factor the recorded sigmas carry over the formal ones (1 where none is recorded)."""
        if self.overdispersion is None or not math.isfinite(self.overdispersion):
            return 1.0
        return math.sqrt(max(self.overdispersion, 1.0))

    def sigmas_text(self) -> str:
        """What the certificate's sigmas are, in words (the certificate's text, ``certificates show``, the
        report)."""
        if self.overdispersion is None:
            return "as written (formal where they came from an adjustment; no overdispersion recorded)"
        if self.overdispersion <= 1.0:
            return (f"formal: the block's measured overdispersion {self.overdispersion:.3g} is not above 1 and "
                    "does not widen them")
        return (f"calibrated: formal x {self.sigma_scale:.3g}, the square root of the block's measured "
                f"overdispersion {self.overdispersion:.3g}")

    def to_dict(self) -> dict:
        d = {"sigma0": self.sigma0, "reprojection_rms_px": self.reprojection_rms_px, "dof": self.dof}
        if self.overdispersion is not None:
            d["overdispersion"] = self.overdispersion
        return d


def package_version() -> str:
    """The running aerocal version (package metadata), or ``"unknown"`` when it is not installed."""
    try:
        return importlib.metadata.version("aerocal")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class Provenance:
    """Where a certificate came from: the flow run that made it, the code version, and the sha256 (hex)
    of every input, keyed by a name the producer chooses (file name, table name)."""

    flow_run: str | None = None
    code_version: str = field(default_factory=package_version)
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
    deviations of the estimated IO parameters (units of :data:`aerocal.camera.PARAM_UNITS`): calibrated by the
    block's overdispersion where ``quality.overdispersion`` is recorded (:class:`Quality`), else as written.
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
    #: camera terms found by flights' diagnoses (:class:`CameraTerm`), by catalogue name; the document's ``effects``
    terms: Mapping[str, CameraTerm] = field(default_factory=FrozenMap)

    @property
    def status(self) -> str:
        """"accepted" or "rejected" (:class:`aerocal.certificates.review.Review`); a certificate without a review (made
        elsewhere and imported) counts as accepted once its values pass the import checks."""
        return self.review.status if self.review is not None else ACCEPTED

    def __post_init__(self) -> None:
        object.__setattr__(self, "sigmas", _freeze_map(self.sigmas))
        object.__setattr__(self, "estimated", _freeze_seq(self.estimated))
        object.__setattr__(self, "significance", _freeze_map(self.significance))
        object.__setattr__(self, "terms", _freeze_map(self.terms))
        # Validate (and normalise: numpy scalars and numbers to float, containers to immutable)
        # through the document.
        for name, value in _fields_of(validate_document(_plain(self.to_dict()))).items():
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
            "camera": self.identity.as_dict(),
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
            **({"effects": {n: (t.to_dict() if isinstance(t, CameraTerm) else t) for n, t in self.terms.items()}}
               if self.terms else {}),
        }

    @classmethod
    def from_dict(cls, doc: Any) -> Certificate:
        """Validate a document strictly and build the certificate; :class:`CertificateError` otherwise."""
        return cls.from_document(validate_document(doc))

    @classmethod
    def from_document(cls, document: CertificateDocument) -> Certificate:
        """The certificate of an already validated document (:func:`aerocal.certificates.schema.validate_document`),
        built without validating it a second time."""
        cert = object.__new__(cls)
        for name, value in _fields_of(document).items():
            object.__setattr__(cert, name, value)
        return cert

    def to_json(self, indent: int | None = 2) -> str:
        """The document as JSON text (no NaN or Infinity: strict JSON)."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False, ensure_ascii=False)

    @classmethod
    def from_json(cls, text: str | bytes) -> Certificate:
        """Parse JSON text and validate it; a syntax error names the line and column."""
        return cls.from_dict(parse_json(text))

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
    def linear_thermal(self) -> LinearThermalModel | None:
        """The thermal model when it is linear (the one the block adjustment and the diagnosis correct the
        measurements with), else ``None``."""
        model = None if self.thermal is None else self.thermal.model
        return model if isinstance(model, LinearThermalModel) else None

    @property
    def calibration_date(self) -> dt.date:
        """The date of the data the calibration was computed from (``conditions.date``), else the UTC date it
        was issued: a certificate applies to flights on or after it."""
        if self.conditions.date is not None:
            return dt.date.fromisoformat(self.conditions.date)
        return self.issued.astimezone(dt.UTC).date()

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

        Raises:
            CertificateError: ``temperature_range`` is not finite ``(lo, hi)`` with ``lo <= hi``.
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
        q = self.quality
        if q.overdispersion is not None:
            lines.append(f"  parameters (value ± sigma, {q.sigmas_text()}):")
        else:
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



# =============================================================================== checks and document reading
def validate_camera(camera: Camera) -> None:
    """Raise :class:`CertificateError` naming the field when ``camera`` holds a value no real frame camera
    has (non-finite, or outside the bounds of :mod:`aerocal.certificates.schema`): a nominal camera from
    ``camera.json`` gets the checks a certificate gets."""
    params = {n: float(getattr(camera, n)) for n in PARAM_NAMES}
    for n, x in params.items():
        if not math.isfinite(x) or (n == "f" and x <= 0):
            raise problem(f"model.params.{n}", "a positive number" if n == "f" else "a finite number", x,
                          f"write {n} as a finite number")
    found = camera_problem(int(camera.width), int(camera.height), camera.pixel_size_mm, params)
    if found is not None:
        path, expected, got, fix = found
        raise problem(f"model.{path}", expected, got, fix)

def _thermal_of(section: Any) -> ThermalCalibration | None:
    if section is None:
        return None
    sigmas = FrozenMap(section.sigmas)
    valid_range = section.valid_range
    if isinstance(section, LinearThermalSection):
        model = LinearThermalModel(t0=section.t0, df_dt=section.df_dt, dcx_dt=section.dcx_dt,
                                   dcy_dt=section.dcy_dt, valid_range=valid_range)
        return ThermalCalibration(model, sigmas)
    if isinstance(section, SimilarityThermalSection):
        model = SimilarityThermalModel(
            temperatures=tuple(section.temperatures), tx=tuple(section.tx), ty=tuple(section.ty),
            scale=tuple(section.scale), theta=tuple(section.theta), centre=tuple(section.centre),
        )
    else:
        model = thermal_model_from_dict({
            "kind": "polynomial", "t0": section.t0, "centre": tuple(section.centre), "norm": section.norm,
            "coefficients": np.asarray(section.coefficients, dtype=float), "degree": section.degree,
        })
    return ThermalCalibration(model, sigmas, valid_range=valid_range)


def _fields_of(d: CertificateDocument) -> dict[str, Any]:
    """The fields of :class:`Certificate` from a validated document."""
    m, c, q, p = d.model, d.conditions, d.quality, d.provenance
    params = m.params
    significance = FrozenMap({
        n: ParameterSignificance(t=s.t, significant=s.significant, dropped=s.dropped, held_out_gain=s.held_out_gain,
                                 held_out_sigma=s.held_out_sigma, calibrated_t=s.calibrated_t,
                                 prior_sigma=s.prior_sigma)
        for n, s in d.significance.items()
    })
    review = d.review
    return {
        "identity": CameraIdentity(d.camera.make, d.camera.model, d.camera.serial, d.camera.lens),
        "camera": Camera(width=m.width, height=m.height, pixel_size_mm=m.pixel_size_mm,
                         **{n: getattr(params, n) for n in PARAM_NAMES}),
        "sigmas": FrozenMap(d.sigmas),
        "estimated": tuple(d.estimated),
        "correlation": Correlation(tuple(d.correlation.names), d.correlation.matrix),
        "significance": significance,
        "thermal": _thermal_of(d.thermal),
        "conditions": Conditions(date=c.date, temperature_range=c.temperature_range, n_images=c.n_images,
                                 strips=c.strips, transversal_strip=c.transversal_strip, n_gcp=c.n_gcp,
                                 priors=FrozenMap(c.priors), images=tuple(c.images)),
        "quality": Quality(sigma0=q.sigma0, reprojection_rms_px=q.reprojection_rms_px, dof=q.dof,
                           overdispersion=q.overdispersion),
        "provenance": Provenance(flow_run=p.flow_run, code_version=p.code_version, inputs=FrozenMap(p.inputs)),
        "id": d.id,
        "issued": d.issued,
        "version": d.version,
        "supersedes": d.supersedes,
        "review": None if review is None else Review(review.status, tuple(review.problems), tuple(review.checks),
                                                     tuple(review.notes)),
        "terms": FrozenMap({n: CameraTerm(tuple(t.values), tuple(t.sigmas), t.units, t.applied, tuple(t.flights),
                                          t.evidence, t.reference_temperature) for n, t in (d.effects or {}).items()}),
    }

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
_SCALARS = frozenset((float, int, str, bool, type(None)))


def _plain(obj: Any) -> Any:
    """Tuples to lists, numpy scalars and arrays to Python numbers and lists (JSON-ready)."""
    if type(obj) in _SCALARS:
        return obj
    if isinstance(obj, dict | Mapping):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [v if type(v) in _SCALARS else _plain(v) for v in obj]
    if isinstance(obj, np.ndarray | np.generic):
        return obj.tolist()
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
    "HASH_EXCLUDED_FIELDS",
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
    "package_version",
    "sigmas_and_correlation",
    "validate_camera",
]
