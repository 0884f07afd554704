"""Diagnosis: given a processed block, show what the model gets wrong, name the cause, extend the model
and measure the gain on data the fit did not use."""
