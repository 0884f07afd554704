"""Which physical camera a flight, an image or a certificate belongs to: make, model, serial number and lens.

One class, :class:`CameraIdentity`, serves ingest, certificates, the exchange formats and the database. A part
that was not recorded is :data:`UNKNOWN` (``"unknown"``) inside the class; surrounding whitespace is stripped
and an empty or ``None`` part becomes :data:`UNKNOWN` on construction.

Three textual forms are stored, and each has one conversion here:

* :attr:`CameraIdentity.key`, ``"make|model|serial|lens"`` with ``"unknown"`` for a missing part: the key
  certificates are grouped by, the four ``cameras`` columns of the database, the ``camera`` object of a
  certificate document (:meth:`CameraIdentity.as_dict`). :meth:`CameraIdentity.from_key` reads it back (the
  lens may be left out: ``"make|model|serial"``).
* :attr:`CameraIdentity.camera_id`, the ``camera_id`` column of the ``images`` table
  (:mod:`aerocal.tables`): ``"make|model|serial|lens"`` with an *empty* part where unknown and ``"|"`` inside
  a part written as ``"/"`` (e.g. ``"Canon|Canon PowerShot ELPH 300 HS||"``).
  :meth:`CameraIdentity.from_camera_id` reads it back.
* :attr:`CameraIdentity.label`, the text shown to people: ``"NEC TS9260 s/n 123"``.

A camera that records no serial number is identified by make, model, lens and frame size: its serial part is
``"no-serial WxH"`` (:data:`NO_SERIAL`, :meth:`CameraIdentity.serial_less`), and its certificates may be
shared by several bodies of that model (:attr:`CameraIdentity.shared_body`; the label says so).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from aerocal.certificates.errors import CertificateError

#: The value of an identity part that was not recorded.
UNKNOWN = "unknown"

#: Serial part of the identity of a camera whose images record no serial number: ``"no-serial WxH"`` (make,
#: model, lens and frame size identify it; several bodies may share its certificates).
NO_SERIAL = "no-serial"

#: The names of the parts, in key order.
IDENTITY_PARTS: tuple[str, ...] = ("make", "model", "serial", "lens")


def _part(value: object) -> str:
    text = "" if value is None else str(value).strip()
    return text or UNKNOWN


def is_unknown(part: str | None) -> bool:
    """True for a part that was not recorded: ``None``, empty, or ``"unknown"`` (any case)."""
    return part is None or str(part).strip().lower() in ("", UNKNOWN)


def is_shared_identity(serial: str | None) -> bool:
    """True for the serial part of a camera that records none (:data:`NO_SERIAL`)."""
    return bool(serial) and str(serial).startswith(NO_SERIAL)


@dataclass(frozen=True)
class CameraIdentity:
    """Make, model, serial number and lens of one camera; a part not recorded is :data:`UNKNOWN`.

    Parts are stripped of surrounding whitespace and an empty or ``None`` part becomes :data:`UNKNOWN`, so
    ``CameraIdentity("DJI", "XT2", "", " ")`` equals ``CameraIdentity("DJI", "XT2")``. ``str()`` of an
    identity is its :attr:`label`.
    """

    make: str = UNKNOWN
    model: str = UNKNOWN
    serial: str = UNKNOWN
    lens: str = UNKNOWN

    def __post_init__(self) -> None:
        for name in IDENTITY_PARTS:
            object.__setattr__(self, name, _part(getattr(self, name)))

    # ------------------------------------------------------------------ construction
    @classmethod
    def unknown(cls) -> CameraIdentity:
        """The identity of a camera nothing is known of (every part :data:`UNKNOWN`)."""
        return cls()

    @classmethod
    def from_parts(
        cls, make: str | None, model: str | None, serial: str | None, lens: str | None
    ) -> CameraIdentity:
        """From the four parts as metadata records them (``None`` or empty where not recorded)."""
        return cls(_part(make), _part(model), _part(serial), _part(lens))

    @classmethod
    def from_key(cls, key: str) -> CameraIdentity:
        """Inverse of :attr:`key` (and of :attr:`camera_id`): ``"make|model|serial|lens"``, or
        ``"make|model|serial"`` for an unknown lens; an empty part is unknown.

        Raises:
            CertificateError: ``key`` has not 3 or 4 ``|``-separated parts.
        """
        parts = str(key).split("|")
        if len(parts) not in (3, 4):
            raise CertificateError(
                f"camera key {key!r}: expected 4 parts 'make|model|serial|lens' (or 3, without the lens), got "
                f"{len(parts)}; write the key as make|model|serial|lens (use 'unknown' for a missing part)"
            )
        return cls(*parts)

    #: the ``images.camera_id`` form reads as a key does (an empty part is unknown)
    from_camera_id = from_key

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> CameraIdentity:
        """From ``{"make", "model", "serial", "lens"}`` (a certificate's ``camera``, a ``camera.json``'s
        ``identity``); a missing key is unknown. Raises :class:`CertificateError` for a part that is not text
        (a whole number is taken as text: serial numbers are written as numbers by hand)."""
        if not isinstance(mapping, Mapping):
            raise CertificateError(
                f"camera: expected an object with make, model, serial, lens, got {type(mapping).__name__}; "
                "write the camera identity as an object"
            )
        values = {}
        for name in IDENTITY_PARTS:
            value = mapping.get(name)
            if value is not None and not isinstance(value, str | int):
                raise CertificateError(
                    f"camera.{name}: expected text, got {type(value).__name__}; write the camera {name} as a string"
                )
            values[name] = value
        return cls(**values)

    @classmethod
    def coerce(cls, value: object) -> CameraIdentity:
        """An identity from an identity, a mapping (:meth:`from_mapping`), a key (:meth:`from_key`), or any
        object with ``make``, ``model``, ``serial`` and ``lens`` attributes (a database ``cameras`` row).

        Raises:
            TypeError: ``value`` is none of the accepted kinds.
            CertificateError: a malformed mapping or key (see :meth:`from_mapping` and :meth:`from_key`).
        """
        if isinstance(value, CameraIdentity):
            return value
        if isinstance(value, Mapping):
            return cls.from_mapping(value)
        if isinstance(value, str):
            return cls.from_key(value)
        if all(hasattr(value, name) for name in IDENTITY_PARTS):
            return cls(*(getattr(value, name) for name in IDENTITY_PARTS))
        raise TypeError(
            f"cannot read a camera identity from {type(value).__name__}; give a CameraIdentity, a mapping or "
            "'make|model|serial|lens'"
        )

    def serial_less(self, width: int, height: int) -> CameraIdentity:
        """This identity with the serial of a camera that records none: ``"no-serial WxH"`` (pixels)."""
        return CameraIdentity(self.make, self.model, f"{NO_SERIAL} {int(width)}x{int(height)}", self.lens)

    # ------------------------------------------------------------------ stored forms
    @property
    def key(self) -> str:
        """``"make|model|serial|lens"`` with ``"unknown"`` for a missing part: the key certificates are
        grouped by (the ``cameras`` columns of the database hold the same four parts)."""
        return "|".join((self.make, self.model, self.serial, self.lens))

    @property
    def camera_id(self) -> str:
        """The ``images.camera_id`` form: ``"make|model|serial|lens"`` with an empty part where unknown and
        ``"|"`` inside a part written as ``"/"``."""
        return "|".join("" if p == UNKNOWN else p.replace("|", "/") for p in self.parts)

    def as_dict(self) -> dict[str, str]:
        """``{"make", "model", "serial", "lens"}`` (a certificate document's ``camera`` object)."""
        return {name: getattr(self, name) for name in IDENTITY_PARTS}

    @property
    def parts(self) -> tuple[str, str, str, str]:
        """``(make, model, serial, lens)``."""
        return (self.make, self.model, self.serial, self.lens)

    # ------------------------------------------------------------------ what is known
    @property
    def is_known(self) -> bool:
        """True when make or model is recorded (an image whose identity says something)."""
        return not (is_unknown(self.make) and is_unknown(self.model))

    @property
    def missing(self) -> tuple[str, ...]:
        """Which of make, model and serial are unknown (a camera is only stored with all three)."""
        return tuple(name for name in IDENTITY_PARTS[:3] if is_unknown(getattr(self, name)))

    @property
    def has_serial(self) -> bool:
        return not is_unknown(self.serial)

    @property
    def has_lens(self) -> bool:
        return not is_unknown(self.lens)

    @property
    def shared_body(self) -> bool:
        """True for a camera that records no serial number, identified by make, model, lens and frame size
        (serial ``"no-serial WxH"``): its certificates may be shared by several bodies of that model."""
        return is_shared_identity(self.serial)

    # ------------------------------------------------------------------ text
    @property
    def label(self) -> str:
        """For people: ``"NEC TS9260 s/n 123"``, ``" lens 13 mm"`` added where known; a camera without a
        recorded serial says its certificates may serve any body of the model."""
        if self.shared_body:
            text = f"{self.make} {self.model} ({self.serial}: any body of this model, no serial recorded)"
        else:
            text = f"{self.make} {self.model} s/n {self.serial}"
        return f"{text} lens {self.lens}" if self.has_lens else text

    def __str__(self) -> str:
        return self.label


__all__ = [
    "IDENTITY_PARTS",
    "NO_SERIAL",
    "UNKNOWN",
    "CameraIdentity",
    "is_shared_identity",
    "is_unknown",
]
