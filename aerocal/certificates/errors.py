"""The error of a malformed certificate, apart so that :mod:`identity` needs no schema to raise it."""


class CertificateError(ValueError):
    """A certificate document or object is malformed; the message names the field path and the fix."""
