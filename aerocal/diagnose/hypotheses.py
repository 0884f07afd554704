"""Hypotheses: each catalogue effect as columns of the block's Jacobian, and as a correction of the data.

For an effect with parameters theta, :func:`columns` gives d(whitened residuals)/d(theta) at theta = 0:
its *signature*, how the image measurements, GNSS positions or IMU attitudes would move. The image
signatures are exactly linear in theta for the interior effects (the pixel is linear in f, cx, cy, b1,
b2 and k3) and to first order in the readout time and the refraction constant, so :func:`correct`
removes an estimated effect by subtracting ``signature * theta`` from the measurements: Daakir 2019's
workflow (correct tie points and GCP measurements, not pixels), which is how the model is extended.

Signs and units follow :mod:`aerocal.effects` (the simulator's conventions), so an estimate is directly
the effect's magnitude. The diagnosis never imports the simulator.

What a block can and cannot separate (say so when reporting): with IO free, a focal length constant in
time absorbs the mean of a thermal drift, and refraction (``K (r + r^3/f^2)``) is absorbed by f and k1
unless the flying height varies; the vertical lever arm is a vertical GNSS bias for a nadir block; at a
constant speed an along-track lever arm and a GNSS time offset have the same signature.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from aerocal.adjust.problem import Block
from aerocal.camera import PARAM_NAMES
from aerocal.diagnose.model import Baseline, Linear, point_geometry, triangulate_checks
from aerocal.effects import CATALOGUE, bertram_refraction_k, plausible_size, thermal_rotation_angle
from aerocal.geometry import small_rotation

PER_STRIP = "per_strip_io"
#: hypotheses the diagnosis tests: the effect catalogue plus per-strip interior orientation
HYPOTHESES: tuple[str, ...] = (*CATALOGUE, PER_STRIP)
UNITS = {**{k: v.units for k, v in CATALOGUE.items()}, PER_STRIP: "px"}
IMAGE_EFFECTS = ("thermal_focal", "thermal_principal_point", "thermal_rotation", "affinity_skew", "radial_k3",
                 "rolling_shutter", "refraction", PER_STRIP)


@dataclass(frozen=True)
class Context:
    """Per-image covariates of the signatures, from the measurements and the baseline solution."""

    dT: np.ndarray  # (N,) temperature minus the reference temperature (0 where unknown)
    t_ref: float
    velocity: np.ndarray  # (N, 3) m/s, from the adjusted centres and the image times
    refraction_k: np.ndarray  # (N,) Bertram's K for each image's height above the block's median ground
    strips: np.ndarray  # strip numbers that get their own IO offsets (all but the first)


def make_context(base: Baseline, reference_temperature: float | None = None) -> Context:
    b, st = base.block, base.state
    T = b.temperature
    if reference_temperature is not None:
        t_ref = float(reference_temperature)
    else:
        t_ref = float(np.nanmean(T)) if np.isfinite(T).any() else 0.0
    dT = np.where(np.isfinite(T), T - t_ref, 0.0)
    V = velocities(st.C, base.covariates.time_s, base.covariates.strip)
    ground = float(np.nanmedian(st.X[: b.n_tie, 2])) + b.origin[2]
    K = np.array([bertram_refraction_k(float(c + b.origin[2]), ground) for c in st.C[:, 2]])
    strips = np.unique(base.covariates.strip[base.covariates.strip >= 0])
    return Context(dT=dT, t_ref=t_ref, velocity=V, refraction_k=K, strips=strips[1:])


def sub_context(ctx: Context, keep: np.ndarray) -> Context:
    """``ctx`` for the images where ``keep`` is True (a sub-block of :func:`aerocal.diagnose.prediction.sub_block`)."""
    return dataclasses.replace(ctx, dT=ctx.dT[keep], velocity=ctx.velocity[keep], refraction_k=ctx.refraction_k[keep])


def velocities(C: np.ndarray, t: np.ndarray, strip: np.ndarray, max_gap_s: float = 30.0,
               unassigned_gap: float = 1.5) -> np.ndarray:
    """Velocity (m/s) of each station (``C``, metres; ``t``, seconds) from its neighbours in time within the same
    strip (``strip``, -1 for none) at most ``max_gap_s`` apart. A frame with no neighbour in a strip of its own (the
    first frame of a strip ingest left out of it, its course from noisy GNSS not yet settled) takes its neighbours in
    time at most ``unassigned_gap`` times the neighbour's strip's median exposure interval apart (the flight's, for
    a neighbour in no strip), whatever their strip: the aircraft has not turned between them. Frames without either
    (a hover, a turn) get zero. Without this, the first frame of a rendered XT2 survey got zero velocity and no
    readout signature while its pixels carried 2.8 px of it, and an affinity was named for the readout."""
    t = np.asarray(t, dtype=float)
    order = np.argsort(t, kind="stable")
    ts, ss = t[order], np.asarray(strip)[order]
    steps = np.diff(ts)

    def interval(same: np.ndarray) -> float:
        ok = same & (steps > 0)
        return float(np.median(steps[ok])) if ok.any() else 0.0

    flight = interval(np.ones(len(steps), dtype=bool))
    per_strip = {int(k): interval((ss[1:] == k) & (ss[:-1] == k)) or flight for k in np.unique(ss[ss >= 0])}
    V = np.zeros_like(C)
    for a, i in enumerate(order):
        near = [order[b] for b in (a - 1, a + 1) if 0 <= b < len(order)]
        nb = [j for j in near if strip[i] >= 0 and strip[j] == strip[i] and 0 < abs(t[j] - t[i]) < max_gap_s]
        if not nb:
            nb = [j for j in near
                  if 0 < abs(t[j] - t[i]) <= unassigned_gap * per_strip.get(int(strip[j]), flight)]
        if len(nb) == 2:
            V[i] = (C[nb[1]] - C[nb[0]]) / (t[nb[1]] - t[nb[0]])
        elif len(nb) == 1:
            V[i] = (C[nb[0]] - C[i]) / (t[nb[0]] - t[i])
    return V


#: plausible per-strip IO offsets (f, cx, cy): 1 % of the focal length, a lens refocused or a sensor shifted
#: between strips by more than that is a different camera
PER_STRIP_PLAUSIBLE = 0.01


def plausible(name: str, camera, ctx: Context) -> np.ndarray:
    """The largest plausible magnitude of each parameter of hypothesis ``name`` (its units) for ``camera``
    (:func:`aerocal.effects.plausible_size`)."""
    f_px = float(camera.f)
    if name == PER_STRIP:
        return np.full(size(name, ctx), PER_STRIP_PLAUSIBLE * f_px)
    return np.full(size(name, ctx), plausible_size(name, f_px, camera.corner_radius))


def size(name: str, ctx: Context) -> int:
    return 3 * len(ctx.strips) if name == PER_STRIP else CATALOGUE[name].size


def image_signature(name: str, base: Baseline, ctx: Context, img: np.ndarray, uv: np.ndarray, xn: np.ndarray,
                    pc: np.ndarray, duv_dpc: np.ndarray) -> np.ndarray:
    """d(pixels)/d(theta) of image measurements (M, 2, k) for an image-space hypothesis, on the baseline's camera,
    attitudes and strips (:func:`signature`)."""
    return signature(name, base.camera, base.state.R, base.covariates.strip, ctx, img, xn, pc, duv_dpc)


def signature(name: str, cam, R: np.ndarray, strip: np.ndarray, ctx: Context, img: np.ndarray, xn: np.ndarray,
              pc: np.ndarray, duv_dpc: np.ndarray) -> np.ndarray:
    """d(pixels)/d(theta) (M, 2, k) of the image measurements of images ``img`` (indices into ``R``, ``strip`` and
    ``ctx``'s arrays) for image-space hypothesis ``name``, at zero effect.

    ``cam``: the :class:`~aerocal.camera.Camera` at the reference temperature; ``R`` (N, 3, 3) world-to-camera;
    ``xn`` (M, 2), ``pc`` (M, 3) and ``duv_dpc`` (M, 2, 3): each measured point's undistorted normalised
    coordinates, its camera-frame position and d(pixels)/d(camera-frame point) at the adjusted geometry
    (:func:`aerocal.diagnose.model.observation_geometry`). Every covariate is taken from the adjusted geometry,
    never from the measurement itself: its noise would correlate with the residuals.

    Raises:
        KeyError: ``name`` is not an image-space hypothesis.
    """
    col = PARAM_NAMES.index
    if name in ("thermal_focal", "thermal_principal_point", "affinity_skew", "radial_k3", PER_STRIP):
        Jio = cam.param_jacobian(xn)
        dT = ctx.dT[img][:, None, None]
        if name == "thermal_focal":
            return Jio[:, :, [col("f")]] * dT
        if name == "thermal_principal_point":
            return Jio[:, :, [col("cx"), col("cy")]] * dT
        if name == "affinity_skew":
            return Jio[:, :, [col("b1"), col("b2")]]
        if name == "radial_k3":
            return Jio[:, :, [col("k3")]]
        sub = Jio[:, :, [col("f"), col("cx"), col("cy")]]
        blocks = [sub * (strip[img] == s)[:, None, None] for s in ctx.strips]
        return np.concatenate(blocks, axis=2) if blocks else np.zeros((len(img), 2, 0))
    if name == "rolling_shutter":
        # the row the point is imaged on, from its adjusted position (xn), not the measured row: the measurement's
        # noise in the row would enter the signature and correlate with the residual, a bias of order
        # sigma_px^2 / height in the gradient that the poses do not absorb (an effect-free xt2-survey block named a
        # readout from the measured rows and none from the adjusted ones: benchmarks/history/engine_measurements.md)
        frac = cam.normalised_to_pixels(cam.distort(xn))[:, 1] / cam.height - 0.5
        dC = np.einsum("mab,mb->ma", R[img], ctx.velocity[img])  # camera motion in its frame
        return (-np.einsum("mab,mb->ma", duv_dpc, dC) * frac[:, None])[:, :, None]
    if name == "thermal_rotation":  # normalised coordinates turned by dT / r_corner per px/degC
        duv_dxn = duv_dpc[:, :, :2] * pc[:, 2][:, None, None]
        theta = thermal_rotation_angle(1.0, ctx.dT[img], cam.corner_radius)  # radians per px/degC at the corner
        dxn = np.column_stack([-xn[:, 1], xn[:, 0]]) * theta[:, None]
        return np.einsum("mab,mb->ma", duv_dxn, dxn)[:, :, None]
    if name == "refraction":
        duv_dxn = duv_dpc[:, :, :2] * pc[:, 2][:, None, None]
        r2 = np.sum(xn**2, axis=1)
        dxn = xn * (ctx.refraction_k[img] * (1.0 + r2))[:, None]
        return np.einsum("mab,mb->ma", duv_dxn, dxn)[:, :, None]
    raise KeyError(name)


def columns(name: str, lin: Linear, base: Baseline, ctx: Context) -> np.ndarray:
    """d(whitened residuals)/d(effect parameters) at zero effect: (rows, k).

    Raises:
        KeyError: ``name`` is not a hypothesis of :data:`HYPOTHESES`.
    """
    b, st = base.block, base.state
    k = size(name, ctx)
    out = np.zeros((len(lin.r), k))
    if name in IMAGE_EFFECTS:
        J = image_signature(name, base, ctx, b.obs_image, b.obs_uv, lin.xn, lin.pc, lin.duv_dpc)
        M = len(b.obs_image)
        out[: 2 * M] = (J / b.obs_sigma[:, None, None]).reshape(2 * M, k)
        return out
    if name in ("gnss_bias", "gnss_time_offset", "lever_arm"):
        g = lin.groups.get("gnss")
        if g is None:
            return out
        inv = 1.0 / np.asarray(base.config.gnss_sigma_m, dtype=float)
        N = b.n_images
        if name == "gnss_bias":
            blk = np.broadcast_to(np.diag(inv), (N, 3, 3))
        elif name == "gnss_time_offset":
            blk = (ctx.velocity * inv)[:, :, None]
        else:  # lever arm in the camera frame: antenna = C + R^T l
            blk = np.transpose(st.R, (0, 2, 1)) * inv[None, :, None]
        out[g] = blk.reshape(3 * N, k)
        return out
    if name == "boresight":
        g = lin.groups.get("imu")
        if g is None:
            return out
        sig = np.radians(np.asarray(base.config.attitude_sigma_deg, dtype=float))
        out[g] = np.tile(-np.diag(np.radians(1.0) / sig), (b.n_images, 1))
        return out
    raise KeyError(f"unknown hypothesis {name!r}; valid: {', '.join(HYPOTHESES)}")


def _check_geometry(base: Baseline, block: Block):
    """xn, pc, duv_dpc of the check-point measurements at their triangulated positions."""
    st = base.state
    X = triangulate_checks(base, block)
    return point_geometry(st.io, st.slopes, st.R, st.C, block.check_image, np.nan_to_num(X[block.check_point]))


def correct(name: str, theta: np.ndarray, base: Baseline, lin: Linear, ctx: Context) -> Block:
    """The block's measurements with an estimated effect removed (the extended model's data)."""
    check = _check_geometry(base, base.block) if len(base.block.check_image) else None
    return correct_block(name, theta, base.block, base.camera, base.state.R, base.covariates.strip, ctx,
                         (lin.xn, lin.pc, lin.duv_dpc), check)


def correct_block(name: str, theta: np.ndarray, b: Block, camera, R: np.ndarray, strip: np.ndarray, ctx: Context,
                  geometry: tuple[np.ndarray, np.ndarray, np.ndarray],
                  check_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> Block:
    """Block ``b`` with effect ``name`` of size ``theta`` removed from what it acts on: the image measurements
    (``obs_uv``, and ``check_uv`` where ``check_geometry`` is given), the recorded positions (``gnss``) or the
    recorded attitudes (``R_rec``). ``camera``, ``R`` (adjusted world-to-camera, one per image), ``strip`` and
    ``geometry`` (xn, pc, duv_dpc of every image measurement, :func:`aerocal.diagnose.model.observation_geometry`)
    describe the adjusted block the signatures are taken at; ``ctx`` its per-image covariates.

    Raises:
        KeyError: ``name`` is not a hypothesis of :data:`HYPOTHESES`.
    """
    theta = np.asarray(theta, dtype=float)
    if name in IMAGE_EFFECTS:
        J = signature(name, camera, R, strip, ctx, b.obs_image, *geometry)
        new = dataclasses.replace(b, obs_uv=b.obs_uv - J @ theta)
        if len(b.check_image) and check_geometry is not None:
            Jk = signature(name, camera, R, strip, ctx, b.check_image, *check_geometry)
            new = dataclasses.replace(new, check_uv=b.check_uv - np.nan_to_num(Jk @ theta))
        return new
    if name == "gnss_bias":
        return dataclasses.replace(b, gnss=b.gnss - theta)
    if name == "gnss_time_offset":
        return dataclasses.replace(b, gnss=b.gnss - ctx.velocity * theta[0])
    if name == "lever_arm":
        return dataclasses.replace(b, gnss=b.gnss - np.einsum("nji,j->ni", R, theta))
    if name == "boresight":
        B = small_rotation(np.radians(theta))
        return dataclasses.replace(b, R_rec=np.einsum("ab,nbc->nac", B, b.R_rec))
    raise KeyError(f"unknown hypothesis {name!r}; valid: {', '.join(HYPOTHESES)}")
