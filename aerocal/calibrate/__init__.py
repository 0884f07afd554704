"""Calibration of a camera from a flight: the subset, the self-calibration and the checks of its result.

:mod:`subset` chooses the images that determine the interior orientation and predicts each parameter's
precision from the block's geometry before anything is estimated; :mod:`self_calibration` adjusts that subset
with the IO (and its thermal slopes) free and writes a certificate; :mod:`heldout` asks whether a thermal
model predicts strips the fit did not use; :mod:`eo_checks` compares the adjusted exterior orientation with
the recorded GNSS/IMU (lever arm, boresight, time lag). The acceptance rule for the result is
:mod:`aerocal.certificates.review`.

Tests: tests/test_calibration.py, tests/test_subset.py, tests/test_eo_checks.py, tests/test_config_validation.py.
"""
