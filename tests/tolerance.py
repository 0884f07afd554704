"""Tolerances taken from an estimator's own sigma, bounded.

"Within 3 sigma" alone passes any answer whose sigma has grown: a block that stopped determining a parameter
reports a wide sigma, and a wrong value then sits inside it. Each such assertion here also bounds the sigma by
what the estimate must achieve to be worth reporting, in the quantity's own units, and says which bound failed.
"""

from __future__ import annotations

import numpy as np


def assert_within_sigma(error, sigma, k: float, max_sigma: float, what: str) -> None:
    """``|error| < k * sigma`` with ``sigma <= max_sigma`` (arrays element by element); ``what`` names the
    quantity and the seed in the message."""
    err, sig = np.abs(np.asarray(error, dtype=float)), np.asarray(sigma, dtype=float)
    assert np.all(sig <= max_sigma), (f"{what}: sigma {np.round(sig, 6)} above {max_sigma:.3g}, too imprecise to "
                                      f"vouch for the value (error {np.round(err, 6)})")
    assert np.all(err < k * sig), f"{what}: off by {np.round(err, 6)}, beyond {k:g} sigma ({np.round(sig, 6)})"
