"""Storage and provenance of aerocal: database, migrations, certificates, runs, artifacts, lineage.

Modules:

* :mod:`storage.database` -- database URL, engines and sessions (SQLite, PostgreSQL).
* :mod:`storage.migrations` -- Alembic migrations: ``upgrade``, ``downgrade``, ``current``.
* :mod:`storage.models` -- the tables (SQLAlchemy declarative models).
* :mod:`storage.cameras`, :mod:`storage.flights`, :mod:`storage.runs` -- repositories.
* :mod:`storage.certificates` -- issuing immutable certificates and selecting the one a flight uses.
* :mod:`storage.artifacts` -- the content-addressed artifact store.
* :mod:`storage.provenance` -- lineage between artifacts and the provenance of a run.
* :mod:`storage.errors` -- the errors (all :class:`~storage.errors.StorageError`).

The engine package ``aerocal`` never imports this package.
"""
