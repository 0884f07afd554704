"""A step's small figures (:attr:`StepResult.extra`, ``run.json``'s ``steps.<name>.extra``), one typed dictionary
per step that has any, with the names its readers use.

They travel as JSON (a step record in the store holds them, a reused step reads them back), so they are typed
dictionaries rather than dataclasses; :func:`step_figures` is the one way a step makes them, and checks them
against its type: a figure a step does not declare, or one it leaves out, is a programming error caught when the
step runs, not a key a reader later misses.
"""

from __future__ import annotations

from typing import Any, Literal, TypedDict, get_type_hints

from aerocal.pipeline.runner import JsonOutput


class MatchFigures(TypedDict):
    """The match step's: candidate ``pairs`` tried, tie-point ``observations`` kept and where the pairs came
    from (``pairs_from``, words)."""

    pairs: int
    observations: int
    pairs_from: str


class OrientFigures(TypedDict, total=False):
    """The orient step's: the ``method`` (``"priors"``: the recorded GNSS/IMU; ``"incremental"``: SfM), the
    block's ``images``, ``observations``, ``tracks`` and ``images_without_observations``; after SfM also the
    images ``registered``, those ``not_registered`` (names) and the ``georeference_scale`` of the similarity
    onto the control (dimensionless)."""

    method: Literal["priors", "incremental"]
    images: int
    observations: int
    tracks: int
    images_without_observations: int
    registered: int
    not_registered: list[str]
    georeference_scale: float


class ControlFigures(TypedDict):
    """The control step's: the ``datum`` the screened control gives the block (``"gnss"``, ``"control"`` or
    ``"none"``), the GCP ids ``demoted`` and one line per point of the screening."""

    datum: str
    demoted: list[str]
    lines: list[str]


class CalibrateFigures(TypedDict):
    """The calibrate step's: the ``certificate_id`` it issued and its review's status."""

    certificate_id: str
    review: str


class SkippedFigures(TypedDict):
    """A skipped step's: why it did not run."""

    skipped: str


#: every step's figures' type, by step name (a step not listed has none)
FIGURES: dict[str, type] = {"match": MatchFigures, "orient": OrientFigures, "control": ControlFigures,
                            "calibrate": CalibrateFigures, "recalibrate": CalibrateFigures}

StepFigures = MatchFigures | OrientFigures | ControlFigures | CalibrateFigures | SkippedFigures

#: the Python types a declared figure may hold, by annotation (JSON's: ``int`` accepts no ``bool``)
_JSON_TYPES = {int: (int,), float: (float, int), str: (str,)}


def step_figures(step: str, **values: Any) -> JsonOutput:
    """The ``_extra`` output of ``step`` holding ``values``, checked against the step's type in :data:`FIGURES`.

    Raises:
        KeyError: ``step`` declares no figures.
        TypeError: a figure the type does not declare, a required one missing, or a value of another type.
    """
    kind = FIGURES[step]
    hints = get_type_hints(kind)
    unknown = sorted(set(values) - set(hints))
    missing = sorted(set(kind.__required_keys__) - set(values))
    if unknown or missing:
        raise TypeError(f"{kind.__name__} of step {step!r}: undeclared {unknown}, missing {missing}")
    for name, value in values.items():
        allowed = _JSON_TYPES.get(hints[name])
        if allowed is not None and (isinstance(value, bool) or not isinstance(value, allowed)):
            raise TypeError(f"{kind.__name__}.{name} must be {hints[name].__name__}, got {value!r}")
    return JsonOutput(dict(values), "extra")
