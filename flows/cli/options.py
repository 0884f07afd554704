"""Options several ``aerocal`` commands share, declared once so that their names and help read the same
everywhere (``--database-url``, ``--artifacts``, ``--dask``)."""

from __future__ import annotations

import typer

DATABASE_URL_OPTION = typer.Option(
    None, "--database-url", show_default=False,
    help="Database URL (default: $AEROCAL_DATABASE_URL, else ~/.local/share/aerocal/aerocal.db).",
)
ARTIFACT_ROOT_OPTION = typer.Option(
    None, "--artifacts", show_default=False,
    help="Artifact store folder (default: $AEROCAL_ARTIFACT_ROOT, else ~/.local/share/aerocal/artifacts).",
)
DASK_OPTION = typer.Option(
    None, "--dask", show_default=False,
    help="Address of a Dask scheduler (e.g. tcp://scheduler:8786); default: a local cluster per step.",
)
