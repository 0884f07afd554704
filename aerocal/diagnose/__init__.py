"""Diagnosis: given a processed block, show what the model gets wrong, name the cause, extend the model
and measure the gain on data the fit did not use.

:mod:`model` fits the baseline (the block as processed, with the effects it already models) and its
covariates per image (time, temperature, velocity, strip); :mod:`hypotheses` lists the candidate causes
(camera terms, readout, GNSS lag and offsets, lever arm, boresight, attitude offsets) as columns of a
linearised design; :mod:`engine` tests them against the block's residuals with the decision rule (determined,
plausible, better on held-out data) and names what passes; :mod:`prediction` is the held-out test (k-fold
over strips or time blocks); :mod:`extension` corrects the block's data for a named effect and adjusts again;
:mod:`twin` makes the adjusted block again with the simulation's noise model and names where the real block's
residuals depart from it; :mod:`attitude`
and :mod:`io_uncertainty` hold the recorded-attitude offset and the propagation of the interior orientation's
uncertainty. Nothing here reads the simulator or its truth.

Tests: tests/test_diagnose.py, tests/test_twin.py, tests/test_model_loop.py.
"""
