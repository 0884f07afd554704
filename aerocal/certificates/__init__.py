"""Calibration certificates: what a camera is, what was measured of it, and which measurement a flight uses.

A certificate is the interior orientation of one physical camera (its :mod:`identity`: make, model, serial,
lens) as a self-calibration measured it, with its covariance, thermal slopes, quality and provenance. This
package owns the document and its JSON form (:mod:`document`), the validation of every field of a stored or
hand-written one (:mod:`schema`, errors in :mod:`errors`), the decision rule that accepts or rejects a finished
self-calibration before it is stored (:mod:`review`), and the choice of the certificate a flight uses among
those on record (:mod:`selection`). It holds no database code: :mod:`storage.certificates` persists documents,
:mod:`aerocal.pipeline.certificates` runs the choice as a step of a flight.

Tests: tests/test_certificate.py, tests/test_camera_identity.py, tests/test_certificate_selection.py.
"""
