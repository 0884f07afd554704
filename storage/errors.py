"""Errors of the storage layer.

Every error a user can meet is one line that names the thing at fault (database URL with the password
masked, certificate id, artifact URI, document field) and says how to fix it.
"""

from __future__ import annotations

from aerocal.certificates.selection import NoCertificateError as NoApplicableCertificateError


class StorageError(Exception):
    """Base class of every storage error; ``str(err)`` is a single line meant for the user."""


class DatabaseURLError(StorageError):
    """The database URL cannot be used (unparseable, unknown database kind, missing driver)."""


class DatabaseUnreachableError(StorageError):
    """The database server does not answer or refuses the connection."""


class DatabaseBusyError(StorageError):
    """A SQLite store stayed locked by another process for longer than the busy timeout: SQLite lets one
    process write at a time, so flights processed at once belong on PostgreSQL."""


class SchemaOutOfDateError(StorageError):
    """The database schema is not at the revision this code expects; run ``aerocal db upgrade``."""


class NotFoundError(StorageError, LookupError):
    """A certificate, run, camera or artifact asked for by id does not exist."""


class CertificateDocumentError(StorageError, ValueError):
    """A certificate document lacks a field the store indexes, or a field has the wrong type."""


class ImmutableCertificateError(StorageError):
    """Something tried to change or delete a stored certificate; issue a new one that supersedes it."""


class NoStoredCertificateError(StorageError, NoApplicableCertificateError):
    """No stored certificate applies to a flight; the message says what is missing. Raised by the database store;
    a subclass of the engine's :class:`aerocal.certificates.selection.NoCertificateError`, which callers catch."""


class CorruptArtifactError(StorageError):
    """An artifact file is missing or its content no longer matches its sha256; the message names the URI."""
