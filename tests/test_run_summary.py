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
