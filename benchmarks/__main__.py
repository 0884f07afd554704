"""Run every benchmark: `python -m benchmarks` (or `make bench`)."""

import importlib
import pkgutil
from pathlib import Path

for mod in sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)])):
    if mod.endswith("_bench"):
        print(f"== benchmarks.{mod}")
        importlib.import_module(f"benchmarks.{mod}").main()
