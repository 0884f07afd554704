"""The studies in their quick mode: each writes its Markdown tables (with every row) and its figures."""

from __future__ import annotations

import importlib
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def _study(name: str):
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return importlib.import_module(f"studies.{name}")


def _table_rows(text: str, header_start: str) -> list[list[str]]:
    """Cells of the Markdown table whose header row starts with ``header_start``."""
    lines = text.splitlines()
    start = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def test_paper_setups_quick_writes_every_table(tmp_path):
    md = _study("paper_setups").main(["--quick", "--out", str(tmp_path)])
    text = md.read_text()
    assert (tmp_path / "paper_setups_quick.png").stat().st_size > 10_000, "figure missing or empty"

    daakir = _table_rows(text, "| metric | measured (paper)")
    assert [r[0] for r in daakir] == ["residual mean (mm)", "residual std (mm)", "residual min (mm)",
                                      "residual max (mm)", "gain in the mean"], text
    nominal_mean = float(daakir[0][2])
    assert 1.0 < nominal_mean < 100.0, f"Daakir residual mean {nominal_mean} mm is not a corridor's figure"

    mitishita = _table_rows(text, "| IOP |")
    assert [r[0] for r in mitishita] == ["nominal", "in situ", "in situ + angular"], text
    dz = [float(re.split(r"[,/]", r[3])[2]) for r in mitishita]
    # the nominal focal (100.500 vs 100.534 mm) at 2500 m moves heights by ~85 cm; the in-situ IOP removes it
    assert abs(dz[0]) > 50 and abs(dz[1]) < 0.5 * abs(dz[0]), f"Mitishita DZ means {dz} cm"
    focal = float(re.search(r"In-situ focal length per seed: ([0-9.]+) mm", text).group(1))
    assert abs(focal - 100.534) < 0.005, f"in-situ focal {focal} mm (true 100.534)"

    conte = _table_rows(text, "| strategy |")
    assert [r[0] for r in conte] == ["STR1", "STR2", "STR3"], text
    for r in conte:
        assert re.match(r"-?[0-9.]+ \+- [0-9.]+, [+-][0-9.]+", r[2]), f"Conte row {r}"
