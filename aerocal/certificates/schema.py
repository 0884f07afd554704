"""The certificate document schema, ``aerocal.certificate/1``: the one definition of a valid document.

:class:`CertificateDocument` (pydantic v2, strict: no coercion of text to numbers, no unknown fields) is what
the engine (:mod:`aerocal.certificates.document`), the certificate store (:mod:`storage.certificates`) and the exchange
formats (:mod:`aerocal.formats`) validate a document with. :func:`validate_document` runs it and turns the
first failure into a :class:`CertificateError` of one line: the path of the field (``model.params.f``,
``correlation.matrix[0][1]``), what was expected, what was found and the fix::

    model.params.f: expected a positive number, got "abc"; write f as a JSON number (pixels)

Each field's type carries an :class:`Expect` (what it must hold, how to fix it) that the message is built
from, whichever constraint failed. Checks that span fields (a sigma only for an estimated parameter, a
symmetric correlation matrix, a plausible camera) are validators of the section they belong to.

Why pydantic rather than jsonschema: the rules that span fields and the plausibility bounds need code in
either; pydantic keeps them beside the fields they check, validates in compiled code (pydantic-core) and
reports each failure with its location, input and constraint, from which the message above is built; it
also reads a document faster than the hand-written validator it replaced
(``benchmarks/history/engine_measurements.md``).

Units: f, cx, cy, b1, b2 and their sigmas in pixels; k1..k3, p1, p2 dimensionless; temperatures in degrees
Celsius; thermal slopes in pixels per degree Celsius; ``pixel_size_mm`` in millimetres.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import re
from dataclasses import dataclass
from types import UnionType
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    Strict,
    ValidationError,
    create_model,
    model_validator,
)
from pydantic_core import PydanticCustomError

from aerocal.camera import PARAM_NAMES, PARAM_UNITS
from aerocal.certificates.errors import CertificateError
from aerocal.certificates.review import ACCEPTED, REJECTED, STATUSES

#: The schema identifier written into, and required from, every certificate document.
SCHEMA = "aerocal.certificate/1"

#: Names of the slopes of :class:`aerocal.camera.LinearThermalModel` (pixels per degree Celsius).
THERMAL_SLOPE_NAMES: tuple[str, ...] = ("df_dt", "dcx_dt", "dcy_dt")

#: Bounds no real frame camera leaves (a document outside them is corrupt or hostile, not a camera): image
#: side in pixels, focal length in image sides, pixel pitch in millimetres, and what one distortion term
#: alone does at the farthest image corner, over that corner's radius. The principal point lies within one
#: image side of the image, affinity and skew are smaller than f.
#: The distortion bound is on the displacement, not the coefficient: Brown coefficients act on normalised
#: coordinates, so a narrow field takes large ones for a small effect (a 640 x 480 frame at f 1674 px has a
#: corner radius of 0.24: k3 = 200 moves its corners by 4 % of their radius; a bound of 100 on the
#: coefficient refused that camera and stopped a city flow at its calibration).
MAX_IMAGE_SIDE_PX = 200_000
MAX_FOCAL_IN_SIDES = 1000.0
MAX_TERM_DISPLACEMENT = 1.0
MAX_PIXEL_SIZE_MM = 1.0

#: How far (absolute) a correlation may leave [-1, 1], its diagonal 1 and its symmetry (rounding).
CORRELATION_TOLERANCE = 1e-9

_HEX32 = r"^[0-9a-f]{32}$"
_SHA256 = r"^[0-9a-f]{64}$"
_DATE = re.compile(r"^\d{4}-\d{2}-\d{2}$")
_ONE_LINE = re.compile(r"^[^|\x00-\x1f\x7f]*$")


# =============================================================================== messages
def show(value: Any) -> str:
    """``value`` as it reads in JSON, cut to 60 characters (an integer of 400 digits is shown by its start)."""
    try:
        text = json.dumps(value, allow_nan=True, default=repr)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def problem(path: str, expected: str, got: Any, fix: str) -> CertificateError:
    """``CertificateError("<path>: expected <expected>, got <got>; <fix>")``."""
    return CertificateError(f"{path}: expected {expected}, got {show(got)}; {fix}")


@dataclass(frozen=True)
class Expect:
    """What a field must hold and how to fix a value that does not: the two halves of its error message."""

    expected: str
    fix: str


def _refuse(path: str, expected: str, got: Any, fix: str) -> PydanticCustomError:
    """A failure inside a validator; ``path`` is relative to the validated node (``""``, ``"n_images"``,
    ``"[0][1]"``)."""
    return PydanticCustomError("certificate", "{text}", {"path": path, "text": f"expected {expected}, got "
                                                                          f"{show(got)}; {fix}"})


def _refuse_text(path: str, text: str) -> PydanticCustomError:
    return PydanticCustomError("certificate", "{text}", {"path": path, "text": text})


# =============================================================================== field types
def _number(expected: str = "a finite number", fix: str = "write a finite JSON number", **constraints: float):
    return Annotated[float, Strict(), Field(allow_inf_nan=False, **constraints), Expect(expected, fix)]


def _integer(minimum: int, expected: str, fix: str = "write a whole JSON number without a decimal point"):
    return Annotated[int, Strict(), Field(ge=minimum), Expect(expected, fix)]


def _text(expected: str = "a non-empty string", fix: str = "write a JSON string in double quotes"):
    return Annotated[str, Strict(), Field(min_length=1), Expect(expected, fix)]


def _ordered(value: list[float]) -> tuple[float, float]:
    if value[0] > value[1]:
        raise _refuse("", "[lo, hi] with lo <= hi", value, "swap the two values")
    return (value[0], value[1])


def _array(item: Any, length: int | None = None, *, minimum: int | None = None, expected: str | None = None,
           fix: str = "write [...] here"):
    """A JSON array (a tuple is taken too); ``length`` fixes its number of elements."""
    what = expected or ("a JSON array" if length is None else f"an array of {length} elements")
    bounds = {"min_length": length, "max_length": length} if length is not None else {"min_length": minimum}
    return Annotated[list[item], Field(strict=False, **bounds), Expect(what, fix)]


_Finite = _number()
_NonNegative = _number("a non-negative number", "write the standard deviation (>= 0)", ge=0.0)
_Sigma = _number("a non-negative number", "write a standard deviation >= 0", ge=0.0)
_Name = _text("a non-empty string", "name each entry")
_TemperatureRange = Annotated[
    _array(_number("a finite number", "write [lowest, highest] in degC"), 2),
    AfterValidator(_ordered),
]
_Pair = _array(_Finite, 2)


def _one_line(value: str) -> str:
    if not _ONE_LINE.match(value):
        raise _refuse("", "one line of text without '|'", value,
                      "remove the '|' (it separates the parts of the camera key) and control characters")
    return value


def _identity_part(name: str):
    return Annotated[str, Strict(), Field(min_length=1),
                     Expect("a non-empty string", f'write the camera {name}, or "unknown"'),
                     AfterValidator(_one_line)]


def _utc_time(value: Any) -> dt.datetime:
    fix = 'write UTC time as ISO-8601 with a Z suffix, e.g. "2024-05-17T09:30:00Z"'
    if not isinstance(value, str) or not value:
        raise _refuse("", "a non-empty string", value, fix)
    try:
        t = dt.datetime.fromisoformat(value)
    except ValueError:
        raise _refuse("", "an ISO-8601 UTC time", value, fix) from None
    if t.tzinfo is None or t.utcoffset() != dt.timedelta(0):
        raise _refuse("", "a UTC time (Z suffix)", value, fix)
    return t.astimezone(dt.UTC)


def _calendar_date(value: str | None) -> str | None:
    if value is not None:
        try:
            ok = bool(_DATE.match(value)) and dt.date.fromisoformat(value) is not None
        except ValueError:
            ok = False
        if not ok:
            raise _refuse("", 'a date "YYYY-MM-DD" or null', value, 'write e.g. "2024-05-17"')
    return value


class _Section(BaseModel):
    """A JSON object of the document: strict types, no unknown fields, immutable."""

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True, revalidate_instances="never")


# =============================================================================== sections
def _param_type(name: str):
    unit = "pixels" if PARAM_UNITS[name] == "px" else "a dimensionless coefficient"
    if name == "f":
        return _number("a positive number", f"write {name} as a JSON number ({unit})", gt=0.0)
    return _number("a finite number", f"write {name} as a JSON number ({unit})")


#: ``model.params``: the Brown parameters of :data:`aerocal.camera.PARAM_NAMES`.
BrownParameters = create_model(
    "BrownParameters", __base__=_Section, **{n: (_param_type(n), ...) for n in PARAM_NAMES}
)


def camera_problem(width: int, height: int, pixel_size_mm: float | None,
                   params: dict[str, float]) -> tuple[str, str, Any, str] | None:
    """The first value no real frame camera has (see the bounds above), as ``(path under model, expected,
    got, fix)``, or ``None`` when the camera is plausible."""
    side = max(width, height)
    for name, size in (("width", width), ("height", height)):
        if size > MAX_IMAGE_SIDE_PX:
            return name, f"at most {MAX_IMAGE_SIDE_PX} pixels", size, "write the image size in pixels"
    if params["f"] > MAX_FOCAL_IN_SIDES * side:
        return ("params.f", f"at most {MAX_FOCAL_IN_SIDES:g} x the larger image side ({MAX_FOCAL_IN_SIDES * side:g} "
                "px)", params["f"], "write the focal length in pixels")
    for name, size in (("cx", width), ("cy", height)):
        if not -size <= params[name] <= 2 * size:
            return (f"params.{name}", f"within one image side of the image ({-size} to {2 * size} px)", params[name],
                    "write the principal point in pixels from the top-left corner")
    corner = math.hypot(max(params["cx"], width - params["cx"]), max(params["cy"], height - params["cy"]))
    r = min(corner / params["f"], 1e50)  # the farthest corner's radius in normalised coordinates (no overflow)
    # each term alone at that corner, over its radius: k_i r^(2i); p1, p2 at most 3 |p| r
    powers = {"k1": r**2, "k2": r**4, "k3": r**6, "p1": 3.0 * r, "p2": 3.0 * r}
    for name, power in powers.items():
        if abs(params[name]) * power > MAX_TERM_DISPLACEMENT:
            limit = MAX_TERM_DISPLACEMENT / power
            return (f"params.{name}", f"a coefficient that alone moves the farthest image corner by at most "
                    f"{MAX_TERM_DISPLACEMENT:g} x its radius (|{name}| <= {limit:.3g} for this camera)",
                    params[name], "write the Brown coefficient for normalised coordinates")
    for name in ("b1", "b2"):
        if abs(params[name]) > params["f"]:
            return f"params.{name}", "smaller in magnitude than f", params[name], "write the affinity/skew in pixels"
    if pixel_size_mm is not None and pixel_size_mm > MAX_PIXEL_SIZE_MM:
        return ("pixel_size_mm", f"at most {MAX_PIXEL_SIZE_MM:g} mm", pixel_size_mm,
                "write the pixel pitch in millimetres (e.g. 0.017)")
    return None


class ModelSection(_Section):
    """``model``: the Brown camera model, image size in pixels, pixel pitch in millimetres."""

    kind: Annotated[Literal["brown"], Expect('"brown"', 'write "brown" (the only camera model of schema 1)')]
    width: _integer(1, "an integer >= 1", "write the image width in pixels")
    height: _integer(1, "an integer >= 1", "write the image height in pixels")
    pixel_size_mm: _number("a positive number or null",
                           "write the pixel pitch in millimetres (e.g. 0.017), or null when unknown", gt=0.0) | None
    params: BrownParameters

    @model_validator(mode="after")
    def _plausible(self) -> ModelSection:
        found = camera_problem(self.width, self.height, self.pixel_size_mm, self.params.model_dump())
        if found is not None:
            raise _refuse(*found)
        return self


class CorrelationSection(_Section):
    """``correlation``: ``matrix[i][j]`` correlates ``names[i]`` and ``names[j]``."""

    names: _array(_text())
    matrix: _array(_array(_number("a finite number", "write a correlation in [-1, 1]")))

    @model_validator(mode="after")
    def _correlation_matrix(self) -> CorrelationSection:
        names, rows = self.names, self.matrix
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise _refuse("names", "unique names", dup, "list each parameter once")
        n = len(names)
        if len(rows) != n:
            raise _refuse("matrix", f"an array of {n} elements", rows, "write [...] here")
        for i, row in enumerate(rows):
            if len(row) != n:
                raise _refuse(f"matrix[{i}]", f"an array of {n} elements", row, "write [...] here")
        # plain loops: for the 8 to 20 parameters of a certificate they are faster than building an array
        for i, row in enumerate(rows):
            for j, r in enumerate(row):
                if abs(r) > 1.0 + CORRELATION_TOLERANCE:
                    raise _refuse(f"matrix[{i}][{j}]", "a correlation in [-1, 1]", r,
                                  "write correlations, not covariances")
        for i in range(n):
            if abs(rows[i][i] - 1.0) > CORRELATION_TOLERANCE:
                raise _refuse(f"matrix[{i}][{i}]", "1 on the diagonal", rows[i][i],
                              "write correlations, not covariances")
        for i in range(n):
            for j in range(i + 1, n):
                if abs(rows[i][j] - rows[j][i]) > CORRELATION_TOLERANCE:
                    raise _refuse(f"matrix[{i}][{j}]", f"the same value as [{j}][{i}] ({rows[j][i]})", rows[i][j],
                                  "make the matrix symmetric")
        return self


class SignificanceEntry(_Section):
    """One parameter's significance: t, significant at 95 %, why it was dropped (null: kept), and where
    measured its held-out gain, calibrated t and the sigma of a nominal value held."""

    t: _number("a finite number", "write the t statistic (value / sigma)")
    significant: Annotated[bool, Strict(), Expect("true or false", "write true or false")]
    dropped: _text("a non-empty string or null", "write why the parameter was dropped, or null when it was kept") | None
    held_out_gain: _number("a finite number or null",
                           "write the relative held-out gain, or null when not measured") | None = None
    held_out_sigma: _number("a non-negative number or null", "write the held-out gain's standard error, or null",
                            ge=0.0) | None = None
    calibrated_t: _number("a finite number or null",
                          "write t over the square root of the block's overdispersion, or null") | None = None
    prior_sigma: _number("a non-negative number or null",
                         "write the standard deviation of the nominal value held, or null", ge=0.0) | None = None


_T0 = _number("a finite number", "write the reference temperature in degC")
_Slope = _number("a finite number", "write the slope in pixels per degC")


class LinearThermalSection(_Section):
    """``thermal`` of kind linear: T0 (degC), slopes of f, cx, cy (pixels per degC), valid range (degC)."""

    kind: Literal["linear"]
    t0: _T0
    df_dt: _Slope
    dcx_dt: _Slope
    dcy_dt: _Slope
    valid_range: _TemperatureRange | None
    sigmas: dict[Literal[THERMAL_SLOPE_NAMES], _Sigma]  # type: ignore[valid-type]


class SimilarityThermalSection(_Section):
    """``thermal`` of kind similarity: translation (pixels), scale, angle (radians) per tabulated temperature."""

    kind: Literal["similarity"]
    temperatures: _array(_Finite, minimum=1, expected="at least one temperature",
                         fix="list the tabulated temperatures")
    tx: _array(_Finite)
    ty: _array(_Finite)
    scale: _array(_Finite)
    theta: _array(_Finite)
    centre: _Pair
    valid_range: _TemperatureRange | None
    sigmas: dict[_Name, _Sigma]

    @model_validator(mode="after")
    def _one_value_per_temperature(self) -> SimilarityThermalSection:
        n = len(self.temperatures)
        for name in ("tx", "ty", "scale", "theta"):
            values = getattr(self, name)
            if len(values) != n:
                raise _refuse(name, f"an array of {n} elements", values, "write [...] here")
        return self


class PolynomialThermalSection(_Section):
    """``thermal`` of kind polynomial: ``coefficients[axis][power of dT - 1][i][j]`` (pixels), positions
    relative to ``centre`` divided by ``norm`` (pixels)."""

    kind: Literal["polynomial"]
    t0: _T0
    centre: _Pair
    norm: _number("a positive number", "write the normalisation in pixels", gt=0.0)
    coefficients: Any  # nested lists whose shape depends on the degree: checked below
    degree: _integer(0, "an integer >= 0")
    valid_range: _TemperatureRange | None
    sigmas: dict[_Name, _Sigma]

    @model_validator(mode="after")
    def _coefficient_shape(self) -> PolynomialThermalSection:
        shape = (2, 3, self.degree + 1, self.degree + 1)
        try:
            coef = np.asarray(self.coefficients, dtype=float)
        except (TypeError, ValueError, OverflowError):
            coef = None
        if coef is None or coef.shape != shape or not np.all(np.isfinite(coef)):
            raise _refuse("coefficients", f"finite numbers nested with shape {list(shape)}", self.coefficients,
                          "write coefficients[axis][power of dT - 1][i][j]")
        return self


ThermalSection = Annotated[
    LinearThermalSection | SimilarityThermalSection | PolynomialThermalSection,
    Field(discriminator="kind"),
]

#: the message of a thermal model of an unknown kind
THERMAL_KIND = Expect('"linear", "similarity" or "polynomial"',
                      "write one of the thermal model kinds of aerocal.camera")


class ConditionsSection(_Section):
    """``conditions``: what the calibration was made under; null where unknown."""

    date: Annotated[_text('a date "YYYY-MM-DD" or null', 'write e.g. "2024-05-17"') | None,
                    AfterValidator(_calendar_date)]
    temperature_range: _TemperatureRange | None
    n_images: _integer(0, "an integer >= 0 or null") | None
    strips: _integer(0, "an integer >= 0 or null") | None
    transversal_strip: Annotated[bool, Strict(), Expect("true or false or null", "write true or false")] | None
    n_gcp: _integer(0, "an integer >= 0 or null") | None
    priors: dict[_Name, _number("a positive number", "write the prior's sigma, its unit in the name (e.g. gnss_m)",
                                gt=0.0)]
    images: _array(_text())

    @model_validator(mode="after")
    def _counted_images(self) -> ConditionsSection:
        if self.images and self.n_images != len(self.images):
            raise _refuse("n_images", f"{len(self.images)} (the number of names in conditions.images)",
                          self.n_images, "make n_images equal the length of images")
        return self


class QualitySection(_Section):
    """``quality``: a-posteriori sigma0 (unitless), RMS reprojection error (pixels), degrees of freedom, and
    where measured the calibration block's overdispersion (``sigmas`` are then calibrated by its square root)."""

    sigma0: _number("a positive number or null", "write the a-posteriori sigma0 (unitless), or null when unknown",
                    gt=0.0) | None
    reprojection_rms_px: _number("a non-negative number or null",
                                 "write the RMS reprojection error in pixels, or null", ge=0.0) | None
    dof: _integer(0, "an integer >= 0 or null") | None
    overdispersion: _number("a positive number or null",
                            "write the calibration block's measured overdispersion (the sigmas are then calibrated "
                            "by its square root), or leave it out when the sigmas are formal", gt=0.0) | None = None


class ProvenanceSection(_Section):
    """``provenance``: the flow run, the code version and the sha256 (hex) of every input, by name."""

    flow_run: _text("a non-empty string or null") | None
    code_version: _text("a non-empty string", 'write the version, or "unknown"')
    inputs: dict[_Name, Annotated[str, Strict(), Field(pattern=_SHA256),
                                  Expect("a sha256 as 64 lowercase hex digits",
                                         "write hashlib.sha256(data).hexdigest()")]]


class ReviewSection(_Section):
    """``review``: the verdict of the calibration's review (:class:`aerocal.certificates.review.Review`)."""

    status: Annotated[Literal[STATUSES], Expect(" or ".join(f'"{x}"' for x in STATUSES),  # type: ignore[valid-type]
                                                "write the verdict of the calibration's review")]
    problems: _array(_text())
    checks: _array(_text())
    notes: _array(_text())

    @model_validator(mode="after")
    def _verdict_and_problems(self) -> ReviewSection:
        if self.status == ACCEPTED and self.problems:
            raise _refuse_text("problems", 'an accepted certificate lists problems; a problem rejects it (write '
                                           '"rejected") or remove the problems')
        if self.status == REJECTED and not self.problems:
            raise _refuse_text("problems", "a rejected certificate must say why; list the problems")
        return self


#: camera terms a diagnosis can certify (:mod:`aerocal.diagnose.extension`): the catalogue's interior effects
CAMERA_TERMS = ("rolling_shutter", "affinity_skew", "radial_k3", "thermal_focal", "thermal_principal_point",
                "thermal_rotation")
#: how a certified term reaches the measurements: through the camera model (``model.params`` b1, b2, k3; the
#: thermal model's slopes), or as a correction of the measurements at the adjusted geometry (a readout, a thermal
#: rotation: no Brown parameter holds them)
TERM_APPLIED = ("model", "measurements")


class EffectTermSection(_Section):
    """One entry of ``effects``: a camera term found by a flight's diagnosis and confirmed on data the fit did not
    use. ``values`` and ``sigmas`` in ``units`` (the catalogue's, :mod:`aerocal.effects`), how it is ``applied``,
    the ``flights`` whose diagnoses support it, and the ``evidence`` in words (held-out gain, check points)."""

    values: _array(_number(), minimum=1)
    sigmas: _array(_Sigma, minimum=1)
    units: _text()
    applied: Annotated[Literal[TERM_APPLIED], Expect(" or ".join(f'"{x}"' for x in TERM_APPLIED),  # type: ignore[valid-type]
                                                     "write how the term reaches the measurements")]
    flights: _array(_text(), minimum=1)
    evidence: _text()
    reference_temperature: _number("a finite number or null", "write the temperature (degC) a thermal term is "
                                   "relative to, or null for a term that does not depend on temperature") | None = None

    @model_validator(mode="after")
    def _same_length(self) -> EffectTermSection:
        if len(self.sigmas) != len(self.values):
            raise _refuse("sigmas", f"{len(self.values)} numbers (one per value)", self.sigmas,
                          "give one sigma per value")
        return self


class CameraSection(_Section):
    """``camera``: make, model, serial number and lens (``"unknown"`` where not recorded)."""

    make: _identity_part("make")
    model: _identity_part("model")
    serial: _identity_part("serial")
    lens: _identity_part("lens")


class CertificateDocument(_Section):
    """A certificate document of schema ``aerocal.certificate/1`` (see :mod:`aerocal.certificates.document`)."""

    schema_: Annotated[Literal[SCHEMA], Field(alias="schema"),  # type: ignore[valid-type]
                       Expect(f'"{SCHEMA}"', "this aerocal reads certificate schema 1 only; re-export the certificate "
                                             "or upgrade aerocal")]
    id: Annotated[str, Strict(), Field(pattern=_HEX32),
                  Expect("32 lowercase hex digits (uuid4().hex)", "write uuid.uuid4().hex")]
    camera: CameraSection
    version: _integer(1, "an integer >= 1 or null", "leave null; the certificate store numbers versions from 1") | None
    supersedes: Annotated[str, Strict(), Field(pattern=_HEX32),
                          Expect("the id (32 hex digits) of the superseded certificate, or null",
                                 "write the id of the certificate this one replaces")] | None
    issued: Annotated[dt.datetime, PlainValidator(_utc_time)]
    model: ModelSection
    sigmas: dict[Literal[PARAM_NAMES], _NonNegative]  # type: ignore[valid-type]
    estimated: _array(Annotated[Literal[PARAM_NAMES],  # type: ignore[valid-type]
                                Expect(f"one of {', '.join(PARAM_NAMES)}",
                                       "use the parameter names of aerocal.camera.PARAM_NAMES")])
    correlation: CorrelationSection
    significance: dict[Literal[PARAM_NAMES + THERMAL_SLOPE_NAMES], SignificanceEntry]  # type: ignore[valid-type]
    thermal: Annotated[ThermalSection | None,
                       Expect("an object or null", "write the thermal model object, or null when none")]
    conditions: ConditionsSection
    quality: QualitySection
    provenance: ProvenanceSection
    review: ReviewSection | None = None
    effects: dict[Annotated[Literal[CAMERA_TERMS],  # type: ignore[valid-type]
                            Expect(f"one of {', '.join(CAMERA_TERMS)}", "name a camera term of aerocal.effects")],
                  EffectTermSection] | None = None

    @model_validator(mode="after")
    def _consistent(self) -> CertificateDocument:
        estimated = self.estimated
        for i, name in enumerate(estimated):
            if estimated.index(name) != i:
                raise _refuse(f"estimated[{i}]", "each parameter once", name, "remove the duplicate")
        for name in self.sigmas:
            if name not in estimated:
                raise _refuse_text(f"sigmas.{name}", f"{name} has a sigma but is not in estimated; add {name} to "
                                                     "estimated or remove its sigma")
        thermal_names = set(THERMAL_SLOPE_NAMES) | set(self.thermal.sigmas) if self.thermal is not None else set()
        for i, name in enumerate(self.correlation.names):
            if name not in estimated and name not in thermal_names:
                raise _refuse(f"correlation.names[{i}]",
                              "an estimated parameter (listed in estimated) or a thermal slope", name,
                              "add it to estimated or remove its row and column")
        for name, entry in self.significance.items():
            if name in THERMAL_SLOPE_NAMES and self.thermal is None:
                raise _refuse_text(f"significance.{name}", "a thermal slope but thermal is null; add the thermal "
                                                           "model or remove this entry")
            if entry.dropped is not None and name in estimated:
                raise _refuse_text(f"significance.{name}.dropped", f"{name} is marked dropped but is listed in "
                                                                   "estimated; remove it from estimated or set dropped "
                                                                   "to null")
        return self


# =============================================================================== validation
def validate_document(doc: Any) -> CertificateDocument:
    """Validate a certificate document (parsed JSON); raise :class:`CertificateError` naming the first bad
    field, what was expected, what was found and the fix."""
    try:
        return CertificateDocument.model_validate(doc)
    except ValidationError as exc:
        raise CertificateError(_message(exc.errors(include_url=False)[0], doc)) from None


def parse_json(text: str | bytes) -> Any:
    """Parse strict JSON text (no NaN or Infinity); a syntax error names the line and column.

    Raises:
        CertificateError: ``text`` is not valid JSON (the message names the line and column), or it holds a NaN or
            Infinity constant.
    """
    try:
        return json.loads(text, parse_constant=_refuse_constant)
    except json.JSONDecodeError as e:
        raise CertificateError(f"line {e.lineno} column {e.colno}: invalid JSON ({e.msg}); fix the syntax there") \
            from None


def _refuse_constant(name: str) -> None:
    raise CertificateError(f"JSON constant {name} is not allowed (strict JSON); write a finite number or null")


# ------------------------------------------------------------------ locating a failure in the schema
@dataclass
class _Node:
    """Where a location of a validation error leads: the path as written in messages, the annotation there
    (``None`` past the schema), the :class:`Expect` attached to it, whether null is allowed."""

    path: str
    annotation: Any
    expect: Expect | None = None
    nullable: bool = False


def _unwrap(annotation: Any) -> tuple[Any, Expect | None, bool]:
    """Strip ``Annotated`` and ``| None``: the bare annotation, its :class:`Expect`, whether null is allowed."""
    expect, nullable = None, False
    while True:
        origin = get_origin(annotation)
        if origin is Annotated:
            args = get_args(annotation)
            annotation = args[0]
            expect = expect or next((m for m in args[1:] if isinstance(m, Expect)), None)
        elif origin in (Union, UnionType) and type(None) in get_args(annotation):
            arms = [a for a in get_args(annotation) if a is not type(None)]
            nullable = True
            annotation = arms[0] if len(arms) == 1 else Union[tuple(arms)]  # noqa: UP007
        else:
            return annotation, expect, nullable


def _model_arms(annotation: Any) -> list[type[BaseModel]]:
    if get_origin(annotation) in (Union, UnionType):
        return [a for a in get_args(annotation) if isinstance(a, type) and issubclass(a, BaseModel)]
    return []


def _join(path: str, key: Any) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


def _locate(loc: tuple[Any, ...]) -> tuple[_Node, _Node | None, bool]:
    """The node ``loc`` leads to, its parent node, and whether the error is about a dict key."""
    node, parent = _Node("", CertificateDocument), None
    items = list(loc)
    while items:
        key = items.pop(0)
        annotation, _, _ = _unwrap(node.annotation)
        if key == "[key]":
            return node, parent, True
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            field = {f.alias or n: f for n, f in annotation.model_fields.items()}.get(str(key))
            if field is None:
                child = _Node(_join(node.path, key), None)
            else:
                child = _Node(_join(node.path, key), Annotated[(field.annotation, *field.metadata)]
                              if field.metadata else field.annotation)
        elif (arms := _model_arms(annotation)) and isinstance(key, str):
            # a discriminated union: the location names the arm by its tag, not a field
            arm = next((a for a in arms if key in get_args(a.model_fields["kind"].annotation)), None)
            node = _Node(node.path, arm)
            continue
        elif get_origin(annotation) is dict:
            child = _Node(_join(node.path, key), get_args(annotation)[1])
            if items and items[0] == "[key]":
                child.annotation = get_args(annotation)[0]
                return child, node, True
        elif get_origin(annotation) is list:
            child = _Node(_join(node.path, key), get_args(annotation)[0])
        else:
            child = _Node(_join(node.path, key), None)
        parent, node = node, child
    return node, parent, False


_DEFAULTS: tuple[tuple[Any, Expect], ...] = (
    (BaseModel, Expect("a JSON object", "write an object {...} here")),
    (dict, Expect("a JSON object {name: value}", "write an object here ({} when empty)")),
    (list, Expect("a JSON array", "write [...] here")),
    (bool, Expect("true or false", "write true or false")),
    (int, Expect("an integer >= 0", "write a whole JSON number without a decimal point")),
    (float, Expect("a finite number", "write a finite JSON number")),
    (str, Expect("a non-empty string", "write a JSON string in double quotes")),
)


def _expectation(node: _Node) -> Expect:
    annotation, expect, nullable = _unwrap(node.annotation)
    if expect is not None:
        return expect
    kind = get_origin(annotation) or annotation
    if _model_arms(annotation):
        kind = BaseModel
    for base, default in _DEFAULTS:
        if isinstance(kind, type) and issubclass(kind, base):
            return Expect(default.expected + (" or null" if nullable else ""), default.fix)
    return Expect("a valid value", "see the certificate schema in aerocal.certificates.document")


def _message(error: Any, doc: Any) -> str:
    loc = tuple(error["loc"])
    node, parent, is_key = _locate(loc)
    kind = error["type"]
    where = node.path or "document"
    if kind == "certificate":
        ctx = error["ctx"]
        rel = ctx["path"]
        path = (f"{node.path}{rel}" if rel.startswith("[") else _join(node.path, rel)) if rel else where
        return f"{path}: {ctx['text']}"
    if is_key:
        names = get_args(_unwrap(node.annotation)[0])
        if names:
            return f"{where}: unknown name; valid names: {', '.join(names)}; remove or rename it"
        container = parent.path if parent is not None else "document"
        return f"{container}: expected non-empty string keys, got {show(error['input'])}; name each entry"
    if kind == "missing":
        return f"{where}: missing; add it (null where the value is unknown and null is allowed)"
    if kind == "extra_forbidden":
        model = _unwrap(parent.annotation)[0] if parent is not None else CertificateDocument
        fields = [f.alias or n for n, f in model.model_fields.items()] if isinstance(model, type) else []
        return (f"{where}: unknown field; valid fields of {parent.path if parent and parent.path else 'the document'}"
                f": {', '.join(fields)}; remove or rename it")
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        tag = error["ctx"].get("tag") if kind == "union_tag_invalid" else None
        return f"{_join(node.path, 'kind')}: expected {THERMAL_KIND.expected}, got {show(tag)}; {THERMAL_KIND.fix}"
    expect = _expectation(node)
    return f"{where}: expected {expect.expected}, got {show(error['input'])}; {expect.fix}"


__all__ = [
    "CORRELATION_TOLERANCE",
    "MAX_TERM_DISPLACEMENT",
    "MAX_FOCAL_IN_SIDES",
    "MAX_IMAGE_SIDE_PX",
    "MAX_PIXEL_SIZE_MM",
    "SCHEMA",
    "THERMAL_SLOPE_NAMES",
    "CertificateDocument",
    "CertificateError",
    "Expect",
    "camera_problem",
    "parse_json",
    "problem",
    "show",
    "validate_document",
]
