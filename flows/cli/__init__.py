"""The ``aerocal`` command line, one module per group of commands.

* :mod:`flows.cli.app` -- the command tree (``app``): every command and group and its help panel;
* :mod:`flows.cli.flights` -- ingest, match, process, calibrate, report;
* :mod:`flows.cli.campaigns` -- campaign (add, run, list), serve;
* :mod:`flows.cli.database` -- init, db (upgrade, downgrade, current);
* :mod:`flows.cli.certificates` -- certificates (list, show, export, import);
* :mod:`flows.cli.runs` -- runs (list, show);
* :mod:`flows.cli.simulation` -- simulate, demo; :mod:`flows.cli.diagnosis` -- diagnose;
* shared: :mod:`flows.cli.errors` (exit codes, the one error line, :func:`~flows.cli.errors.user_errors`),
  :mod:`flows.cli.console` (consoles, progress bar), :mod:`flows.cli.options` (``--database-url``,
  ``--artifacts``, ``--dask``), :mod:`flows.cli.help_text` (how a command's docstring becomes its help).

The console script ``aerocal`` is :data:`aerocal.cli.app`, which hands over :data:`flows.cli.app.app`.
Importing these modules never imports Prefect or SQLAlchemy: each command imports them when it runs.
"""
