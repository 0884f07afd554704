"""Adaptive selection of the self-calibration parameters by significance and correlation.

After each adjustment one parameter at most is dropped, then the block is adjusted again:

1. a near-singular pair (|correlation| > ``corr_limit``) with a member that is not significant
   (t < ``t_limit``): that member is dropped (never one of ``always_keep`` unless both are); of two radial
   terms, the higher order. A pair whose members are both significant stays unless it is singular
   (|correlation| > ``singular_corr``): their t values, from the full covariance, already pay for the
   correlation;
2. otherwise the least significant parameter with t < ``t_limit`` (not one of ``always_keep``, and not a
   radial term while a higher-order one is still free).

Radial terms go from the highest order down (:data:`RADIAL_ORDER`): k3 r^6 is a correction to k2 r^4,
not a substitute. In a narrow field the two are nearly collinear, and dropping the less significant of
the pair removed k2 and kept k3 (a rendered conte-city calibration sub-block, true k2 0.12: 0.16 px at
the corners). There k2 alone is not determinable either (t 0.54, correlation 0.954 with k1) and goes
next, so the certificate lacks it and the full block's diagnosis names the radial signal.

It stops when every remaining parameter is significant and no pair is near-singular. Every decision is
recorded as one sentence naming the parameters and the numbers.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from aerocal.adjust.problem import AdjustConfig

#: Radial distortion terms, lowest order first.
RADIAL_ORDER = ("k1", "k2", "k3")


def _higher_radial_free(name: str, names: list[str]) -> bool:
    """True when ``name`` is a radial term and a higher-order one is among ``names``."""
    if name not in RADIAL_ORDER:
        return False
    return any(n in names for n in RADIAL_ORDER[RADIAL_ORDER.index(name) + 1 :])


def _drop(config: AdjustConfig, name: str) -> AdjustConfig:
    if name.startswith("d") and name.endswith("/dT"):
        base = name[1:-3]
        return dataclasses.replace(config, thermal=tuple(n for n in config.thermal if n != base))
    return dataclasses.replace(config, free=tuple(n for n in config.free if n != name))


def choose_drop(
    names: list[str], corr: np.ndarray, t: np.ndarray, config: AdjustConfig
) -> tuple[str | None, str]:
    """The parameter to drop next and why (``None`` and a summary when every parameter stays)."""
    keep = set(config.always_keep)
    n = len(names)
    if n >= 2:
        c = np.abs(np.asarray(corr, dtype=float)).copy()
        np.fill_diagonal(c, 0.0)
        while True:
            a, b = np.unravel_index(int(np.argmax(c)), c.shape)
            if c[a, b] <= config.corr_limit:
                break
            options = [k for k in (a, b) if names[k] not in keep]
            if c[a, b] <= config.singular_corr:
                # a correlation alone never drops a parameter the block determines: t comes from the full
                # covariance, so a significant t holds despite the correlation (conte-calibration and
                # daakir-calibration lost a true k2 of 0.12 / 0.01 at |corr(k1, k2)| 0.96, their certificates
                # then biased f by 2-8 sigma and the diagnosis named the missing radial term)
                options = [k for k in options if t[k] < config.t_limit]
            if options:
                k = min(options, key=lambda q: t[q])
                if names[a] in RADIAL_ORDER and names[b] in RADIAL_ORDER and len(options) == 2:
                    k = max(options, key=lambda q: RADIAL_ORDER.index(names[q]))
                other = b if k == a else a
                return names[k], (
                    f"dropped {names[k]}: |corr({names[a]}, {names[b]})| = {c[a, b]:.3f} "
                    f"> {config.corr_limit} "
                    f"(t({names[k]}) = {t[k]:.2f}, t({names[other]}) = {t[other]:.2f})"
                )
            c[a, b] = c[b, a] = 0.0  # both must stay: leave the pair and look at the next one
    cand = [k for k in range(n) if names[k] not in keep and t[k] < config.t_limit
            and not _higher_radial_free(names[k], names)]
    if cand:
        k = min(cand, key=lambda q: t[q])
        level = "at 95 %" if config.t_limit <= 1.96 else "against the null measured on the block"
        return names[k], f"dropped {names[k]}: t = {t[k]:.2f} < {config.t_limit:.3g} (not significant {level})"
    summary = ", ".join(f"{nm} t={tv:.1f}" for nm, tv in zip(names, t, strict=True))
    c = np.abs(np.asarray(corr, dtype=float)) - np.eye(n) if n else np.zeros((0, 0))
    pairs = [f"|corr({names[a]}, {names[b]})| = {c[a, b]:.3f}" for a in range(n) for b in range(a + 1, n)
             if c[a, b] > config.corr_limit]
    if pairs:
        return None, (f"kept {summary}: all significant; {', '.join(pairs)} above {config.corr_limit} kept, "
                      "both members significant")
    return None, f"kept {summary}: all significant, no |correlation| above {config.corr_limit}"


def select_parameters(run: Callable[[AdjustConfig], object], config: AdjustConfig):
    """Adjust with ``run(config)`` repeatedly, dropping parameters; returns the last result, the reasons
    and the last configuration. The result's ``dropped`` maps each dropped parameter to (why, its t value
    when it was dropped).

    ``run`` returns an object with ``names`` (free parameter names), ``correlation`` and ``t_values``.
    """
    reasons: list[str] = []
    dropped: dict[str, tuple[str, float]] = {}
    cfg = config
    for _ in range(len(config.free) + len(config.thermal) + 1):
        result = run(cfg)
        names = list(result.names)
        name, why = choose_drop(names, result.correlation, np.asarray(result.t_values), cfg)
        reasons.append(why)
        if name is None:
            break
        dropped[name] = (why.partition(": ")[2], float(np.asarray(result.t_values)[names.index(name)]))
        cfg = _drop(cfg, name)
    result.dropped = dropped
    return result, reasons, cfg
