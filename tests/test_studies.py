"""The studies in their quick mode: each writes its Markdown tables (with every row) and its figures."""

from __future__ import annotations

import importlib
import json
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


def test_paper_setups_puts_each_papers_section_in_one_report(tmp_path):
    """The aggregator runs the papers' studies (here Mitishita's, the quickest; each study is tested in full in
    its own test) and writes their sections, figures and numbers."""
    md = _study("paper_setups").main(["--quick", "--papers", "mitishita", "--out", str(tmp_path)])
    text = md.read_text()
    assert text.startswith("# The seed papers' set-ups, simulated (quick mode)"), text[:200]
    assert "Mitishita" in text and "nominal" in text, text[:2000]
    assert (tmp_path / "mitishita_quick.png").stat().st_size > 10_000, "figure missing or empty"
    result = json.loads((tmp_path / "mitishita_quick.json").read_text())
    assert result, "the study's numbers are written beside its section"
