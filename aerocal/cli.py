"""The entry point of the ``aerocal`` command line (the console script ``aerocal = "aerocal.cli:app"``).

The commands live in :mod:`flows.cli`, one module per group (:mod:`flows.cli.app` lists them). This is the
one engine module allowed to reach the platform package ``flows``, and only when :data:`app` is asked for:
importing the engine, this module included, imports neither ``flows`` nor Prefect nor SQLAlchemy. The
command modules themselves import Prefect, SQLAlchemy and the engine's heavy modules only inside the
commands that need them, so ``aerocal --help`` and ``aerocal simulate`` never import Prefect.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    """``app``: the command tree :data:`flows.cli.app.app`, imported on first use."""
    if name == "app":
        # lazy: the engine reaches the platform package only here, when the command tree is asked for
        from flows.cli.app import app

        return app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main() -> None:  # pragma: no cover - console entry point
    __getattr__("app")()


if __name__ == "__main__":  # pragma: no cover
    main()
