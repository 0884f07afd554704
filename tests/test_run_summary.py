"""The run summary is a typed record: what ``run.json`` holds reads back into the same fields, and a summary that
could not be right is refused where it is made."""

import json

import pytest

from aerocal.pipeline import RunSummary, StepRecord, StepStatus
from aerocal.pipeline.findings import Finding
from aerocal.pipeline.summary import GroundControlSummary


def _summary() -> RunSummary:
    return RunSummary(
        run_id="r1", flight="demo", mode="observations", certificate_id="cert-2",
        certificate_reason="extended by this flight's diagnosis",
        steps={"match": StepRecord(StepStatus.SKIPPED, reason="observations mode"),
               "adjust": StepRecord(StepStatus.COMPUTED, seconds=1.23456, computed_by="r1", key="k",
                                    outputs={"poses": "sha"}, extra={"method": "gnss"})},
        images_skipped_at_ingest=("IMG_0446.JPG",), ingest_problems=("eo.csv:3: alt [error]",),
        flight_facts={"height_agl_m": "70 m (senseFly XMP Height)"},
        ground_control=GroundControlSummary("3 control points", ("gcp04",), ("gcp04 double-labelled",)),
        findings=(Finding("rolling_shutter", (0.01,), (0.0003,), "s", "diagnosis", "the block adjusted again with it",
                          "held-out gain +14.8 +- 1.6 %"),),
        diagnosis="rolling_shutter = 0.01 s", diagnosis_after_extension="no systematic effect found",
        recorded_eo_corrections=("time lag 0.05 s removed",), accuracy={"rho": {"E": 1.1}},
        adjustment_converged=True, adjustment_iterations=7, files={"report": "/tmp/report.html"})


def test_the_summary_reads_back_from_its_json_as_it_was_written():
    summary = _summary()
    back = RunSummary.from_json(json.loads(json.dumps(summary.to_json())))
    assert back.steps["adjust"].seconds == pytest.approx(1.235)  # rounded to the millisecond on disk
    assert back.steps["adjust"].status is StepStatus.COMPUTED and back.steps["match"].reason == "observations mode"
    assert back.finding("rolling_shutter") == summary.finding("rolling_shutter")
    assert back.ground_control == summary.ground_control and back.flight_facts == summary.flight_facts
    assert back.to_json() == RunSummary.from_json(back.to_json()).to_json()
    # what a reader of run.json sees: plain values, the statuses as words
    doc = json.loads(json.dumps(summary.to_json()))
    assert doc["steps"]["match"] == {"status": "skipped", "reason": "observations mode"}
    assert doc["findings"][0]["values"] == [0.01] and doc["certificate_id"] == "cert-2"


def test_a_run_json_of_an_earlier_version_still_reads():
    """Keys a newer summary dropped are ignored and the ones an older one lacked take their defaults."""
    doc = {"run_id": "r0", "flight": "f", "mode": "images", "certificate_id": None, "certificate_reason": "nominal",
           "steps": {"ingest": {"status": "reused", "seconds": 2.0, "computed_by": "r-1"}}, "retired_field": 1}
    back = RunSummary.from_json(doc)
    assert back.steps["ingest"].status is StepStatus.REUSED and back.findings == () and back.accuracy is None


@pytest.mark.parametrize("bad, message", [
    (lambda: StepRecord(StepStatus.SKIPPED), "reason"),
    (lambda: StepRecord("finished"), "finished"),
    (lambda: StepRecord(StepStatus.COMPUTED, seconds=-1.0), "seconds"),
    (lambda: RunSummary("", "f", "images", None, "x"), "run id"),
    (lambda: RunSummary("r", "f", "images", None, "x", steps={"ingest": {"status": "computed"}}), "StepRecord"),
])
def test_a_summary_that_could_not_be_right_is_refused_where_it_is_made(bad, message):
    with pytest.raises((ValueError, TypeError), match=message):
        bad()


def test_a_step_makes_only_the_figures_its_type_declares():
    """A step's small figures (``run.json``'s ``steps.<name>.extra``) are checked against the step's type when the
    step makes them: an undeclared name, a missing one or a value of another type is refused there, not found
    missing by a reader later."""
    from aerocal.pipeline.figures import step_figures

    made = step_figures("match", pairs=3, observations=120, pairs_from="footprints")
    assert made.value == {"pairs": 3, "observations": 120, "pairs_from": "footprints"}
    assert step_figures("orient", method="priors", images=2, observations=9, tracks=4,
                        images_without_observations=0).value["method"] == "priors"
    with pytest.raises(TypeError, match="undeclared \\['pair'\\]"):
        step_figures("match", pair=3, pairs=3, observations=120, pairs_from="footprints")
    with pytest.raises(TypeError, match="missing \\['review'\\]"):
        step_figures("calibrate", certificate_id="c1")
    with pytest.raises(TypeError, match="pairs must be int"):
        step_figures("match", pairs=True, observations=1, pairs_from="footprints")
    with pytest.raises(TypeError, match="datum must be str"):
        step_figures("control", datum=None, demoted=[], lines=[])
