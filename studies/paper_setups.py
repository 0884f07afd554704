"""The seed papers' set-ups as simulations, each against its paper's measured numbers: one report.

Each paper is a study of its own, run through the engine's adjustment, certificates and diagnosis; this
script runs them and puts their sections into one report, *paper | our simulation, today's model | our
simulation, extended model*, every row's difference explained:

* :mod:`studies.daakir2019`: Daakir et al. 2019, the UAV corridor and its thermal correction;
* :mod:`studies.mitishita`: Mitishita et al., direct georeferencing with nominal / in-situ IOP;
* :mod:`studies.conte2018`: Conte et al. 2018, calibration strategies STR1/STR2/STR3 on a GNSS-only
  thermal city block.

Run: ``python -m studies.paper_setups`` (``--quick``: each study's reduced set-up; ``--papers daakir,conte``:
some of them). Writes ``studies/output/paper_setups.md`` (``paper_setups_quick.md``) and each study's figure
and JSON beside it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the project's packages
    sys.path.insert(0, str(ROOT))

from aerocal.io import write_text_atomic  # noqa: E402
from studies.papers import OUT, write_study  # noqa: E402

#: the papers: name -> module of its study
PAPERS = {"daakir": "studies.daakir2019", "mitishita": "studies.mitishita", "conte": "studies.conte2018"}


def run_paper(name: str, quick: bool, out: Path, saved: bool = False) -> str:
    """Run one paper's study (``saved``: take the numbers its last run wrote to ``out`` instead), write its own
    report, figure and numbers to ``out``; its Markdown section."""
    module = importlib.import_module(PAPERS[name])
    stem = module.__name__.rsplit(".", 1)[-1]
    if saved:
        path = out / f"{stem}{'_quick' if quick else ''}.json"
        if not path.is_file():
            raise SystemExit(f"{path} not found: run the study first (python -m {module.__name__})")
        result = json.loads(path.read_text())
    else:
        result = module.run(quick=quick)
    return write_study(stem, result, module.markdown, module.figure, out, quick).read_text()


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="each study's reduced set-up")
    ap.add_argument("--papers", default=",".join(PAPERS), help=f"comma-separated, of {', '.join(PAPERS)}")
    ap.add_argument("--out", type=Path, default=OUT, help=f"output folder (default {OUT})")
    ap.add_argument("--saved", action="store_true",
                    help="write the report from the numbers each study's last run saved in --out (no run)")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.papers.split(",") if n.strip()]
    unknown = [n for n in names if n not in PAPERS]
    if unknown:
        ap.error(f"unknown paper(s) {', '.join(unknown)}; choose from {', '.join(PAPERS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sections = []
    for name in names:
        print(name, flush=True)
        sections.append(run_paper(name, args.quick, args.out, args.saved).strip())
    title = "# The seed papers' set-ups, simulated" + (" (quick mode)" if args.quick else "")
    text = "\n\n".join([title, f"Written by `python -m studies.paper_setups{' --quick' if args.quick else ''}` in "
                        f"{time.perf_counter() - t0:.0f} s; each section is also its study's own report.",
                        *sections]) + "\n"
    md = args.out / ("paper_setups_quick.md" if args.quick else "paper_setups.md")
    write_text_atomic(md, text)
    print(f"wrote {md}")
    return md


if __name__ == "__main__":
    main()
