"""The uncertainty of the interior orientation a diagnosis holds fixed.

A diagnosis adjusts the block with IO fixed from a certificate and asks what the residuals still hold. The
certificate's IO is an estimate: an error within its own sigmas leaves a residual pattern (J_io delta_io)
that hypotheses sharing its signature pick up. On a rendered, effect-free 640 x 480 block calibrated on its
own images (k1, k2 and k3 correlated with |r| 0.92 to 0.99 on a 22 degree field) the fixed-IO block named
``radial_k3 = 1.13 +- 0.23``, well inside the certificate's own k3 sigma of 3.2: the diagnosis saw the
certificate's error, not an effect.

So each hypothesis's estimate is given the certificate's covariance propagated to it,
``A Sigma_io A^T`` with ``A = I^-1 C`` (``I`` the hypothesis's conditional information, ``C`` its
conditional cross-information with the IO columns), beside the block's own ``I^-1 sigma0^2``. For a
certificate made from the same images this is conservative (its errors are partly fitted away already);
for a certificate from another flight it is the uncertainty that flight left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aerocal.camera import PARAM_NAMES


@dataclass(frozen=True)
class IOUncertainty:
    """Covariance of the fixed IO parameters ``names`` (units of :data:`aerocal.camera.PARAM_UNITS`)."""

    names: tuple[str, ...]
    covariance: np.ndarray  # (k, k)

    def __post_init__(self) -> None:
        unknown = [n for n in self.names if n not in PARAM_NAMES]
        if unknown:
            raise ValueError(f"IOUncertainty: unknown IO parameter(s) {unknown}; valid: {', '.join(PARAM_NAMES)}")
        cov = np.asarray(self.covariance, dtype=float)
        if cov.shape != (len(self.names), len(self.names)) or not np.all(np.isfinite(cov)):
            raise ValueError(f"IOUncertainty: covariance must be a finite {len(self.names)}-square matrix")

    @property
    def columns(self) -> list[int]:
        """Indices of ``names`` in :data:`aerocal.camera.PARAM_NAMES`."""
        return [PARAM_NAMES.index(n) for n in self.names]

    def without(self, names) -> IOUncertainty | None:
        """The marginal uncertainty of the parameters other than ``names`` (e.g. those a diagnosis frees), or None
        when none is left."""
        keep = [k for k, n in enumerate(self.names) if n not in set(names)]
        if not keep:
            return None
        cov = np.asarray(self.covariance, dtype=float)[np.ix_(keep, keep)]
        return IOUncertainty(tuple(self.names[k] for k in keep), cov)

    @classmethod
    def from_certificate(cls, cert) -> IOUncertainty | None:
        """The estimated IO of ``cert`` (:class:`aerocal.certificates.document.Certificate`) with its covariance from
        its sigmas and correlation matrix: calibrated sigmas where ``quality.overdispersion`` is recorded, else
        the formal ones inflated by the overdispersion its calibration measured (squared ratio of formal to
        calibrated t, where recorded), plus the nominal values it holds because
        the block could not determine them, with their recorded ``prior_sigma`` (uncorrelated). None when
        there is neither."""
        names = [n for n in cert.estimated if n in PARAM_NAMES and n in cert.sigmas
                 and np.isfinite(cert.sigmas[n]) and cert.sigmas[n] > 0]
        s = np.array([float(cert.sigmas[n]) for n in names])
        corr = np.eye(len(names))
        cnames = list(cert.correlation.names)
        if cnames:
            R = np.asarray(cert.correlation.matrix, dtype=float)
            for a, na in enumerate(names):
                for b, nb in enumerate(names):
                    if na in cnames and nb in cnames:
                        corr[a, b] = R[cnames.index(na), cnames.index(nb)]
        phi = []
        if cert.quality.overdispersion is None:  # formal sigmas (a document written before it was recorded)
            for n in names:
                sig = cert.significance.get(n)
                if sig is not None and sig.calibrated_t and sig.t and np.isfinite(sig.calibrated_t):
                    phi.append((float(sig.t) / float(sig.calibrated_t)) ** 2)
        inflate = max(1.0, float(np.median(phi))) if phi else 1.0
        cov = corr * np.outer(s, s) * inflate
        # nominal values held because the block could not determine them: their own uncertainty, uncorrelated
        held = [(n, float(sig.prior_sigma)) for n, sig in cert.significance.items()
                if n in PARAM_NAMES and n not in names and getattr(sig, "prior_sigma", None)]
        if held:
            k = len(names)
            full = np.zeros((k + len(held), k + len(held)))
            full[:k, :k] = cov
            for i, (_, sd) in enumerate(held):
                full[k + i, k + i] = sd**2
            names, cov = names + [n for n, _ in held], full
        if not names:
            return None
        return cls(tuple(names), cov)


__all__ = ["IOUncertainty"]
