"""The diagnosis of the whole real seneca flight, timed on the diagnose step's own inputs.

``--capture DIR`` runs the whole seneca flight (166 frames, ``benchmarks.seneca_bench.build_flight``) through
:func:`aerocal.pipeline.process` with its default configuration, as ``benchmarks.loop_bench --seneca-full`` does,
and stops when the diagnose step calls the engine: that call's arguments (the block adjustment's observations
after its screening, the certificate's camera, the run's adjustment configuration, its poses and points) are
written to ``DIR/diagnosis_inputs.pickle``. About 16 minutes on 2 cores (matching and calibration).

``DIR`` alone times :func:`aerocal.diagnose.engine.diagnose` on those inputs with this code, twice in one
run: with the default :class:`~aerocal.diagnose.engine.DiagnoseConfig` (blocks past
``two_ray_tracks_up_to`` tie measurements diagnosed on their tracks of three rays or more) and with every track
(the baseline), each in a fresh process (its own peak memory). Printed and recorded: time, peak memory, the
per-image null's overdispersion, the verdict and what each candidate's decision was, and the time ratio.
Target: <= 60 s on 2 cores (issue: the loop's benchmarks).

Run: ``python -m benchmarks.diagnosis_bench --capture /tmp/aerocal-diagnosis`` once, then
``python -m benchmarks.diagnosis_bench /tmp/aerocal-diagnosis``. The inputs are a pickle of this code's own
types: capture them again after a change of those types.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pickle
import time
from pathlib import Path

from benchmarks.common import in_fresh_process, peak_rss_mb, record

INPUTS = "diagnosis_inputs.pickle"
TARGET_S = 60.0


def capture(work: Path) -> None:
    """Process the whole seneca flight up to its diagnosis; write the engine call's arguments to ``work``."""
    import aerocal.pipeline.diagnose_step as step
    from aerocal.pipeline import ProcessConfig, process
    from benchmarks.seneca_bench import build_flight

    class Captured(Exception):
        pass

    def keep(*args, **kwargs):
        with open(work / f"{INPUTS}.part", "wb") as f:
            pickle.dump((args, kwargs), f)
        os.replace(work / f"{INPUTS}.part", work / INPUTS)
        raise Captured

    work.mkdir(parents=True, exist_ok=True)
    folder, built = build_flight(work, quick=False)
    step.diagnose = keep
    t0 = time.perf_counter()
    try:
        process(folder, ProcessConfig(), out_dir=work / "run")
    except Captured:
        pass
    if not (work / INPUTS).is_file():
        raise SystemExit("the run ended without calling the diagnosis: see its run folder " + str(work / "run"))
    print(f"{built['images']} images processed up to the diagnosis in {time.perf_counter() - t0:.0f} s; "
          f"inputs in {work / INPUTS}")


def _diagnose(path: str, every_track: bool, queue) -> None:
    from aerocal.diagnose.engine import DiagnoseConfig, diagnose

    with open(path, "rb") as f:
        args, kwargs = pickle.load(f)
    config = args[6] if len(args) > 6 else kwargs.get("config")
    config = config or DiagnoseConfig()
    if every_track:
        config = dataclasses.replace(config, two_ray_tracks_up_to=None)
    args = (*args[:6], config, *args[7:])
    t0 = time.perf_counter()
    result = diagnose(*args, **kwargs)
    seconds = time.perf_counter() - t0
    decisions = [n for n in result.notes if n.split(" ")[0].rstrip(":") in set(config.hypotheses)
                 and ("held-out" in n or "calibrated" in n)]
    queue.put({"seconds": seconds, "peak_mb": peak_rss_mb(), "observations": args[1].num_rows,
               "summary": result.summary(), "overdispersion": result.overdispersion,
               "named": [e.name for e in result.effects], "decisions": decisions})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--capture", action="store_true", help="process the flight and keep the inputs first")
    args = parser.parse_args()
    if args.capture:
        capture(args.work)
        return
    path = args.work / INPUTS
    if not path.is_file():
        raise SystemExit(f"{path} not found: run with --capture {args.work} first")
    runs = {label: in_fresh_process(_diagnose, str(path), every) for label, every in
            (("every track (baseline)", True), ("default (three rays or more past the limit)", False))}
    base, new = runs["every track (baseline)"], runs["default (three rays or more past the limit)"]
    lines = [f"- inputs: the diagnose step's engine call of `aerocal process` on the whole seneca flight "
             f"({base['observations']} tie measurements after the block adjustment's screening)", "",
             "| diagnosis | time | peak memory | overdispersion | named |", "|---|---|---|---|---|"]
    for label, r in runs.items():
        lines.append(f"| {label} | {r['seconds']:.1f} s | {r['peak_mb']:.0f} MB | {r['overdispersion']:.1f} | "
                     f"{', '.join(r['named']) or 'nothing'} |")
    met = "met" if new["seconds"] <= TARGET_S else "not met"
    lines += ["", f"- time, default / every track: {new['seconds'] / base['seconds']:.2f}; target <= {TARGET_S:g} s: "
              f"{met} ({new['seconds']:.1f} s)", f"- verdict (default): {new['summary']}"]
    lines += [f"  - {d}" for d in new["decisions"]]
    lines += [f"- verdict (every track): {base['summary']}"]
    lines += [f"  - {d}" for d in base["decisions"]]
    print("\n".join(lines))
    record("Diagnosis of the whole seneca flight", lines)


if __name__ == "__main__":
    main()
