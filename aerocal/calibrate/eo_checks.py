"""Recorded exterior orientation checked, and corrected where the decision rule allows, before it is trusted.

Small drones' recorded EO carries gross systematic errors: a height read against another reference (take-off,
geoid or ellipsoid), a constant GNSS offset. Used as a prior in a self-calibration, such an offset is absorbed
by the interior orientation, and the certificate is then confidently wrong while the check points still pass
(``benchmarks/history/engine_measurements.md``).

:func:`correct_gnss_offset` adjusts the block with the calibration's own model and estimates the
``gnss_bias`` hypothesis of :mod:`aerocal.diagnose` against it (sigmas calibrated by the block's
overdispersion, determinability and physical size checked: :func:`aerocal.diagnose.engine.recorded_eo_checks`).
Each horizontal component beyond ``MIN_Z`` of its sigmas is subtracted from the recorded positions. The
vertical one is reported, not corrected: with f free it is the focal length's twin at a constant flying
height. It needs control GCPs (without them the offset is the datum itself and is not testable); every
outcome is a sentence with its numbers.

The GNSS time lag (camera clock against the receiver's) is tested in the same adjustment and needs no control:
it moves each position along its own track, so strips flown in opposite directions determine it. A lag beyond
``MIN_Z`` of its calibrated sigmas, and within its physical size, is removed from the recorded positions
(``position - velocity x lag``, the velocity from the recorded track, :func:`track_velocities`). Unmodelled,
a lag sits in the calibration's GNSS residuals.
The image-side effects that mimic a lag (:data:`TIME_LAG_RIVALS`: a rolling-shutter readout) are tested beside
it; a lag the diagnosis cannot tell apart from one of them is reported and not removed. So is the principal point
of IO held fixed: its error moves each footprint along the track as a lag does, so the fixed IO's uncertainty (a
certificate's covariance, a nominal camera's tolerances) is taken into the test (held exact, a nominal camera's
small cy error was removed as a significant lag: ``benchmarks/history/engine_measurements.md``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from aerocal.adjust import AdjustConfig, AdjustmentError, select_images
from aerocal.adjust.strategy import central_images
from aerocal.camera import Camera
from aerocal.diagnose.attitude import AttitudeOffset, mean_rotation_covariance, offset_statistics
from aerocal.diagnose.engine import DiagnoseConfig, diagnose
from aerocal.diagnose.extension import turn_recorded_attitudes
from aerocal.diagnose.hypotheses import velocities
from aerocal.diagnose.io_uncertainty import IOUncertainty
from aerocal.diagnose.model import Baseline, fit_baseline, image_strips, image_times_s
from aerocal.geometry import small_rotation

#: control GCPs the offset needs in the block (a translation of the datum is determined by three points)
MIN_CONTROL = 3
#: a component of the offset is subtracted when it exceeds this many of its calibrated sigmas
MIN_Z = 3.0
#: image-side effects tested beside the time lag, which they mimic: a frame read out row by row while the
#: aircraft moves displaces its rows along the track, in the opposite sense on strips flown the other way. A
#: simulated conte-calibration flight (33 ms readout, no lag) had a lag of +51 +- 14 ms "removed" (3 m along
#: each track) when the lag was tested alone
TIME_LAG_RIVALS = ("rolling_shutter",)


@dataclass
class GnssCorrection:
    """The recorded positions as corrected (``images``), the offset subtracted (metres E, N, Up; ``None``
    when none was), its sigma, and what was decided, in words."""

    images: pa.Table
    offset_m: list[float] | None = None
    sigma_m: list[float] | None = None
    notes: list[str] = field(default_factory=list)
    time_offset_s: float | None = None  # the GNSS time lag removed (seconds), None when none was
    time_sigma_s: float | None = None
    # the evidence of each correction made on data the fit did not use, in words (by name: gnss_bias, gnss_time_offset)
    evidence: dict[str, str] = field(default_factory=dict)


def shift_gnss(images: pa.Table, offset: np.ndarray) -> pa.Table:
    """``images`` with ``offset`` (metres E, N, Up in the flight's CRS) subtracted from gnss_x/y/z."""
    return shift_gnss_each(images, np.broadcast_to(np.asarray(offset, dtype=float), (images.num_rows, 3)))


def track_velocities(images: pa.Table) -> np.ndarray:
    """Velocity (m/s, E N Up of the flight's CRS) of each recorded position from its neighbours in time within
    its strip (:func:`aerocal.diagnose.hypotheses.velocities`); zero where the image has no neighbour."""
    C = np.column_stack([images.column(c).to_numpy(zero_copy_only=False).astype(float)
                         for c in ("gnss_x", "gnss_y", "gnss_z")])
    secs = image_times_s(images)
    if secs is None:
        return np.zeros_like(C)
    return np.nan_to_num(velocities(np.nan_to_num(C), secs, image_strips(images)))


def shift_gnss_in_time(images: pa.Table, lag_s: float) -> pa.Table:
    """``images`` with each recorded position moved back along its track by ``lag_s`` seconds."""
    return shift_gnss_each(images, track_velocities(images) * float(lag_s))


def shift_gnss_each(images: pa.Table, offsets: np.ndarray) -> pa.Table:
    """``images`` with ``offsets`` ((N, 3) metres, one row per image) subtracted from gnss_x/y/z."""
    out = images
    for k, name in enumerate(("gnss_x", "gnss_y", "gnss_z")):
        i = out.schema.get_field_index(name)
        col = out.column(name).to_numpy(zero_copy_only=False).astype(float) - offsets[:, k]
        out = out.set_column(i, out.schema.field(i), pa.array(col, pa.float64()))
    return out


def correct_gnss_offset(
    images: pa.Table,
    observations: pa.Table,
    camera: Camera,
    config: AdjustConfig,
    gcps: pa.Table | None,
    gcp_observations: pa.Table | None,
    max_images: int | None = None,
    io: IOUncertainty | None = None,
    block: str | None = None,
) -> GnssCorrection:
    """Test the recorded positions for a constant offset against the control GCPs and for a GNSS time lag, and
    remove what passes (see the module docstring). ``config`` is the adjustment the positions are for (a
    self-calibration's free IO is free here too, so that the offset is not mistaken for an IO error, nor the
    other way round). ``max_images``: estimate on that many images nearest the block centre (None: all); the
    correction applies to every image. ``io``: the uncertainty of the IO held fixed (a certificate's, or a
    nominal camera's tolerances), taken into every statistic: a principal-point error moves each image's
    footprint along its own track as a lag does, in opposite senses on strips flown the other way.
    ``block``: which block this is, in words ("the 33-image calibration block"), added to every note: a flight
    tests its positions on its calibration block and again on the whole block, and the two results differ."""
    out = _correct_gnss_offset(images, observations, camera, config, gcps, gcp_observations, max_images, io)
    for _ in range(REFINE_ROUNDS):
        if out.offset_m is None and out.time_offset_s is None:
            break
        again = _correct_gnss_offset(out.images, observations, camera, config, gcps, gcp_observations, max_images,
                                     io, refining=out.time_offset_s is not None)
        if again.offset_m is None and again.time_offset_s is None:
            break
        out = _refined(out, again)
    if block:
        out.notes = [f"{n} (tested on {block})" for n in out.notes]
    return out


#: rounds of the GNSS tests on the positions they corrected: each is a linearised estimate, and a large lag is
#: underestimated by one (its rest then found by the diagnosis afterwards: ``benchmarks/history/
#: engine_measurements.md``). A lag the first round removed is refined by what the next round estimates beyond
#: :data:`MIN_Z` of its sigma, named again or not: the decision that the lag exists was the first round's (with its
#: held-out gain), and a remainder the size of the estimate's own error has a held-out gain of half its z, which
#: left part of a rendered lag in the records, where the attitude check took its tilt for a boresight
#: (benchmarks/RESULTS.md, "Every catalogue effect hidden in rendered conte-calibration frames")
REFINE_ROUNDS = 2


def _refined(first: GnssCorrection, again: GnssCorrection) -> GnssCorrection:
    """The corrections of ``first`` and of ``again`` (the tests repeated on the positions ``first`` corrected), in
    all; the sigmas are the last round's."""
    def total(a, b):
        if a is None or b is None:
            return b if a is None else a
        return (np.asarray(a, dtype=float) + np.asarray(b, dtype=float)).tolist()

    lag = total(first.time_offset_s, again.time_offset_s)
    return GnssCorrection(
        again.images, total(first.offset_m, again.offset_m), again.sigma_m if again.offset_m is not None
        else first.sigma_m, first.notes + [f"again, on the positions so corrected: {n}" for n in again.notes
                                           if "removed" in n or "subtracted" in n],
        float(lag) if lag is not None else None,
        again.time_sigma_s if again.time_offset_s is not None else first.time_sigma_s,
        {**again.evidence, **first.evidence})


def _correct_gnss_offset(images: pa.Table, observations: pa.Table, camera: Camera, config: AdjustConfig,
                         gcps: pa.Table | None, gcp_observations: pa.Table | None, max_images: int | None,
                         io: IOUncertainty | None, refining: bool = False) -> GnssCorrection:
    """One round of :func:`correct_gnss_offset`; ``refining``: a lag was removed by an earlier round, and what is
    left of it is removed when beyond :data:`MIN_Z` of its sigma whether or not the diagnosis names it again."""
    if config.gnss_sigma_m is None:
        return GnssCorrection(images, notes=["GNSS offset not tested: the adjustment does not use GNSS"])
    n_control = 0
    if gcps is not None and gcp_observations is not None and gcps.num_rows:
        roles = dict(zip(gcps.column("gcp_id").to_pylist(), gcps.column("role").to_pylist(), strict=True))
        seen = set(gcp_observations.column("gcp_id").to_pylist())
        n_control = sum(1 for g in seen if roles.get(g) == "control")
    offset_testable = n_control >= MIN_CONTROL and config.use_gcps
    tested = ("gnss_bias", "gnss_time_offset") if offset_testable else ("gnss_time_offset",)
    cfg = dataclasses.replace(config, thermal=(), adaptive=False, tie_thinning=None)
    try:
        d = diagnose(images, observations, camera, cfg, gcps, gcp_observations,
                     DiagnoseConfig(hypotheses=tested + TIME_LAG_RIVALS, max_effects=len(tested + TIME_LAG_RIVALS),
                                    max_images=max_images, twins=0), io)
    except (AdjustmentError, np.linalg.LinAlgError, ValueError) as exc:
        return GnssCorrection(images, notes=[f"GNSS offset and time lag not tested: the block could not be adjusted "
                                             f"({exc})"])
    # what is removed is what the diagnosis names, each estimated given the other (a lag on a block flown
    # mostly one way is partly a constant offset: both estimated on their own and both subtracted put a
    # rendered block's check points far off: benchmarks/history/engine_measurements.md)
    named = {e.name: e for e in d.effects}
    out = GnssCorrection(images)
    if offset_testable:
        _offset(out, named.get("gnss_bias"), d.recorded_eo.get("gnss_bias", {}), n_control)
    else:
        out.notes.append(f"GNSS offset not testable: {n_control} control GCPs in the block (at least {MIN_CONTROL} "
                         "are needed; without them a constant offset is the datum itself)")
    rivals = [named[n] for n in TIME_LAG_RIVALS if n in named]
    lag_check = d.recorded_eo.get("gnss_time_offset", {})
    if refining and "gnss_time_offset" not in named and not rivals:
        _lag_remainder(out, lag_check)
    else:
        _time_lag(out, named.get("gnss_time_offset"), lag_check, rivals)
    return out


def _lag_remainder(out: GnssCorrection, check: dict) -> None:
    """What is left of a lag an earlier round removed, estimated on the positions so corrected (``check``: its
    recorded-EO check, estimated alone): removed when determined, within its physical size and beyond
    :data:`MIN_Z` of its sigma."""
    if "estimate" not in check or check.get("status") in ("not determined", "beyond physical size", "not testable"):
        out.notes.append(f"GNSS time lag left after its removal: {_unnamed(check, 's')}")
        return
    lag, sig = float(check["estimate"][0]), float(check["sigma"][0])
    if abs(lag) <= MIN_Z * sig:
        out.notes.append(f"GNSS time lag left after its removal {lag:+.3g} +- {sig:.2g} s: not beyond {MIN_Z:g} sigma")
        return
    out.images = shift_gnss_in_time(out.images, lag)
    out.time_offset_s, out.time_sigma_s = lag, sig
    out.notes.append(f"GNSS time lag left after its removal {lag:+.3g} +- {sig:.2g} s: removed too (a refinement "
                     "of the lag found, not a new finding)")


@dataclass
class AttitudeCorrection:
    """The recorded attitudes as corrected (``images``), the offset removed (degrees about the camera axes x, y, z;
    ``None`` when none was), the check itself (:class:`aerocal.diagnose.attitude.AttitudeOffset`, None where it
    could not be made) and what was decided, in words."""

    images: pa.Table
    offset_deg: list[float] | None = None
    check: AttitudeOffset | None = None
    notes: list[str] = field(default_factory=list)
    #: the GNSS time lag (s) a tilt held back as a just-removed lag's remainder stands for (``lag_sigma_s`` of
    #: :func:`correct_attitude_offset`), to be removed from the positions with that lag; None where there is none
    lag_remainder_s: float | None = None


def correct_attitude_offset(images: pa.Table, observations: pa.Table, camera: Camera, config: AdjustConfig,
                            gcps: pa.Table | None, gcp_observations: pa.Table | None,
                            max_images: int | None = None, block: str | None = None,
                            lag_sigma_s: float | None = None) -> AttitudeCorrection:
    """Measure how the recorded attitudes are turned from the orientation the images and the recorded positions
    (and control points) give without them, and remove the offset from the records where it is beyond its sigma
    about an axis and predicts the images it was not estimated on (:mod:`aerocal.diagnose.attitude`), as a
    boresight. Only where ``config`` observes the attitudes: otherwise they do not reach the block, and the
    diagnosis reports their offset. ``max_images``: measure on that many images nearest the block centre (the
    correction applies to every image); ``block``: which block this is, in words, added to every note.
    ``lag_sigma_s``: the sigma (s) of a GNSS time lag just removed from the positions; a tilt that moves the
    footprints along their tracks as a lag within :data:`MIN_Z` of that sigma would is what is left of the lag as
    far as this block can tell (:func:`lag_equivalent_s`): it is not removed from the attitudes, and the lag it
    stands for is returned in ``lag_remainder_s`` for the caller to remove from the positions with the lag."""
    out = AttitudeCorrection(images)
    if config.attitude_sigma_deg is None or config.gnss_sigma_m is None:
        return out
    cfg = dataclasses.replace(config, attitude_sigma_deg=None, free=(), thermal=(), adaptive=False, tie_thinning=None)
    sub_images, sub_obs, sub_gobs = _central(images, observations, gcp_observations, max_images)
    where = f" (tested on {block})" if block else ""
    try:
        base = fit_baseline(sub_images, sub_obs, camera, cfg, gcps, sub_gobs)
    except (AdjustmentError, np.linalg.LinAlgError, ValueError) as exc:
        out.notes.append(f"recorded attitudes not checked: the block could not be adjusted without them ({exc})"
                         + where)
        return out
    check = offset_statistics(base.state.R, base.block.R_rec,
                              mean_rotation_covariance(base.solution, base.block.n_images))
    out.check = check
    if check is None:
        return out
    if not check.significant:
        out.notes.append(f"recorded attitudes: {check.text()}, against the orientation the images and positions give "
                         f"without them: no offset; used as recorded{where}")
        return out
    offset = check.applied()
    if lag_sigma_s is not None:
        lag_like = lag_equivalent_s(base, sub_images, offset)
        within = np.isfinite(lag_like) & (np.abs(lag_like) <= MIN_Z * lag_sigma_s) & (offset != 0)
        if within.any():
            axes = ", ".join("xyz"[k] for k in np.flatnonzero(within))
            out.lag_remainder_s = float(np.sum(lag_like[within]))
            out.notes.append(
                f"recorded attitudes: the offset about the camera's {axes} axis moves the footprints along their "
                f"tracks as a GNSS time lag of {out.lag_remainder_s:+.3g} s would, within {MIN_Z:g} sigma "
                f"({lag_sigma_s:.2g} s) of the lag just removed: taken for what is left of that lag, and removed with "
                f"it from the positions, not from the attitudes{where}")
            offset = np.where(within, 0.0, offset)
            if not offset.any():
                out.notes.append(f"recorded attitudes: {check.text()}; used as recorded{where}")
                return out
    out.images = turn_recorded_attitudes(images, small_rotation(np.radians(offset)))
    out.offset_deg = [float(v) for v in offset]
    out.notes.append(f"recorded attitudes: {check.text()}, against the orientation the images and positions give "
                     f"without them: an offset about the camera's {', '.join(check.axes)} axis (a gimbal's yaw for the "
                     f"camera's, a mounting tilt, another angle convention), removed from every recorded attitude as a "
                     f"boresight before the adjustment{where}")
    return out


def lag_equivalent_s(base: Baseline, images: pa.Table, offset_deg: np.ndarray) -> np.ndarray:
    """Per camera axis, the GNSS time lag (s) whose shift moves the footprints as the attitude offset about that
    axis does, where that axis's tilt moves them along their tracks; NaN for an axis whose tilt moves them across
    the tracks or not at all (about the optical axis), and for a block without times.

    ``base``: the block adjusted without attitudes (its cameras' rotations world-to-camera, centres and points,
    metres); ``images``: its images in the block's order (the recorded track gives each image's velocity);
    ``offset_deg``: the offset about the camera axes x, y, z (``log(R_adjusted R_recorded^T)``), degrees. Per image
    the footprint of the optical axis moves by the flying height above the points' median height times the turn of
    the axis; its component along the track over the ground speed is a lag. The median over the images moving
    faster than 1 m/s; an axis counts as along the track where the median of that component is more than 0.7 of the
    whole shift (a lag moves nothing across the track)."""
    v = track_velocities(images)
    speed = np.linalg.norm(v[:, :2], axis=1)
    moving = speed > 1.0
    out = np.full(3, np.nan)
    if moving.sum() < 3:
        return out
    R, C, X = base.state.R[moving], base.state.C[moving], base.state.X
    height = C[:, 2] - float(np.median(X[:, 2])) if len(X) else None
    if height is None:
        return out
    along = v[moving, :2] / speed[moving, None]
    e_z = np.array([0.0, 0.0, 1.0])
    for k in range(3):
        if offset_deg[k] == 0:
            continue
        w = np.zeros(3)
        w[k] = np.radians(offset_deg[k])
        turn = -np.einsum("nji,j->ni", R, np.cross(w, e_z))  # the optical axis's turn in the world, R^T (w x e_z)
        shift = height[:, None] * turn[:, :2]
        a = np.einsum("ni,ni->n", shift, along)
        whole = np.linalg.norm(shift, axis=1)
        if np.median(np.abs(a)) > 0.7 * np.median(whole):
            out[k] = -float(np.median(a / speed[moving]))
    return out


#: the chi-square (in the better block's sigma0 squared) by which the records corrected one way must fit worse than
#: corrected the other way for a GNSS error and an attitude offset to be told apart: 3 sigma of one degree of freedom
SEPARATES_CHI2 = 9.0


def correct_recorded_eo(images: pa.Table, observations: pa.Table, camera: Camera, config: AdjustConfig,
                        gcps: pa.Table | None, gcp_observations: pa.Table | None, max_images: int | None = None,
                        io: IOUncertainty | None = None,
                        block: str | None = None) -> tuple[AttitudeCorrection, GnssCorrection]:
    """The recorded attitudes (:func:`correct_attitude_offset`) and positions (:func:`correct_gnss_offset`)
    checked together; the GNSS correction's ``images`` carry both corrections.

    Each check looks at the block through the other's records: an attitude offset, observed, turns the block the
    GNSS tests see, and a GNSS error turns the orientation the attitudes are checked against (a lag tilts the
    cameras about their x axis, the same in every strip since the camera turns with the heading: checked in one
    order only, a rendered lag passed as a boresight, and the lag then as a GNSS offset:
    ``benchmarks/history/engine_measurements.md``).
    So where either check corrects something the records are checked in both orders (attitudes first, positions
    first); when the two orders decide alike the first is kept, otherwise the block is adjusted on the records
    corrected each way and the one that fits better by :data:`SEPARATES_CHI2` wins (the lag's shift grows with
    the ground speed, which differs between strips in a wind; a boresight's tilt does not). A block that fits
    both alike cannot tell the two causes apart: the records are used as they are, and the diagnosis reports
    them as a group."""
    check = (observations, camera, config, gcps, gcp_observations, max_images)

    def positions_first(eo: GnssCorrection) -> tuple[AttitudeCorrection, GnssCorrection]:
        positioned = eo.images
        for c in ("roll", "pitch", "yaw"):  # the corrected positions with the attitudes as recorded
            positioned = positioned.set_column(positioned.schema.get_field_index(c), c, images.column(c))
        att = correct_attitude_offset(positioned, *check, block,
                                      lag_sigma_s=eo.time_sigma_s if eo.time_offset_s is not None else None)
        if att.lag_remainder_s is not None and eo.time_offset_s is not None:
            att.images = shift_gnss_in_time(att.images, att.lag_remainder_s)
            return att, dataclasses.replace(eo, images=att.images,
                                            time_offset_s=eo.time_offset_s + att.lag_remainder_s)
        return att, dataclasses.replace(eo, images=att.images)

    att = correct_attitude_offset(images, *check, block)
    eo = correct_gnss_offset(att.images, *check, io, block)
    corrected_gnss = eo.offset_m is not None or eo.time_offset_s is not None
    if att.offset_deg is None and not corrected_gnss:
        return att, eo
    # the other order: without an attitude correction the GNSS tests saw the records as they are; with one, the
    # positions are tested on the images alone, the attitudes not observed (observed, a lag's tilt
    # of the cameras would conflict with them and hold the lag back, and a rendered lag then passed as a
    # boresight in both orders); the attitudes are then checked against the positions so corrected
    free = dataclasses.replace(config, attitude_sigma_deg=None)
    other = positions_first(eo if att.offset_deg is None else correct_gnss_offset(
        images, observations, camera, free, gcps, gcp_observations, max_images, io, block))
    if _decisions(att, eo) == _decisions(*other):
        return att, eo
    fits, dofs = zip(*[_records_chi2(e.images, *check) for _, e in ((att, eo), other)], strict=True)
    orders = ("attitudes first", "positions first")
    said = [f"{orders[k]}: {'; '.join(a.notes + e.notes)} (chi2 {fits[k]:.1f})"
            for k, (a, e) in enumerate(((att, eo), other))]
    better = int(np.argmin(fits))
    scale = min(fits) / max(min(dofs), 1)  # the better block's sigma0 squared
    if abs(fits[0] - fits[1]) < SEPARATES_CHI2 * max(scale, 1e-12):
        # what both orders found: an attitude offset about the same axis, of the same sign
        a = np.asarray(att.offset_deg or [0.0] * 3, dtype=float)
        b = np.asarray(other[0].offset_deg or [0.0] * 3, dtype=float)
        common = np.where((a != 0) & (np.sign(a) == np.sign(b)), a, 0.0)
        note = ("recorded attitudes and positions: corrected in either order the block fits alike, so an attitude "
                "offset and a GNSS error are not told apart here; "
                + (f"the offset about the camera's {', '.join('xyz'[k] for k in np.flatnonzero(common))} axis "
                   f"both found ({', '.join(f'{v:+.3g}' for v in common)} deg) removed from the recorded attitudes, "
                   "the rest used as recorded" if common.any() else "records used as they are")
                + " (" + " | ".join(said) + ")")
        if not common.any():
            return AttitudeCorrection(images, check=att.check, notes=[note]), GnssCorrection(images)
        turned = turn_recorded_attitudes(images, small_rotation(np.radians(common)))
        return (AttitudeCorrection(turned, [float(v) for v in common], att.check, [note]),
                GnssCorrection(turned))
    chosen = (att, eo) if better == 0 else other
    chosen[0].notes.insert(0, f"recorded attitudes and positions checked in both orders; {orders[better]} fits the "
                              f"block better by chi2 {abs(fits[0] - fits[1]):.1f} (the other: "
                              f"{said[1 - better]})")
    return chosen


def _decisions(att: AttitudeCorrection, eo: GnssCorrection) -> tuple[bool, bool, bool]:
    """Which recorded-EO corrections were made: an attitude offset, a GNSS offset, a GNSS time lag."""
    return att.offset_deg is not None, eo.offset_m is not None, eo.time_offset_s is not None


def _central(images: pa.Table, observations: pa.Table, gcp_observations: pa.Table | None,
             max_images: int | None) -> tuple[pa.Table, pa.Table, pa.Table | None]:
    """The ``max_images`` images nearest the block's centre, with their measurements (all where None)."""
    if max_images is None or images.num_rows <= max_images:
        return images, observations, gcp_observations
    keep = central_images(images, max_images)
    return (select_images(images, keep), select_images(observations, keep),
            select_images(gcp_observations, keep) if gcp_observations is not None else None)


def _records_chi2(images, observations, camera, config, gcps, gcp_observations,
                  max_images) -> tuple[float, int]:
    """Chi-square and degrees of freedom of the block (its central ``max_images``) adjusted on ``images``' records
    with ``config``."""
    sub_images, sub_obs, sub_gobs = _central(images, observations, gcp_observations, max_images)
    cfg = dataclasses.replace(config, free=(), thermal=(), adaptive=False, tie_thinning=None)
    try:
        sol = fit_baseline(sub_images, sub_obs, camera, cfg, gcps, sub_gobs).solution
    except (AdjustmentError, np.linalg.LinAlgError, ValueError):
        return float("inf"), 1
    return 2.0 * float(sol.cost), int(sol.dof)


def held_out_text(effect) -> str:
    """The evidence on data the fit did not use of a named effect (:class:`aerocal.diagnose.engine.NamedEffect`),
    in words."""
    parts = []
    held, check = effect.held_out or {}, effect.check_points or {}
    if held.get("gain") is not None:
        parts.append(f"held-out gain {100 * held['gain']:+.2f} +- {100 * (held.get('sigma') or 0):.2f} % on "
                     f"{held.get('n_images')} images ({held.get('units')})")
    if check.get("gain") is not None:
        parts.append(f"check points {100 * check['gain']:+.1f} +- {100 * (check.get('sigma') or 0):.1f} %")
    return "; ".join(parts) or "named by the diagnosis"


def _unnamed(check: dict, units: str) -> str:
    """Why a recorded-EO term is not removed, from its check (estimated alone, in ``units``)."""
    if "estimate" not in check or check.get("status") in ("not determined", "beyond physical size", "not testable"):
        return f"{check.get('reason') or check.get('status', 'not tested')}"
    est = ", ".join(f"{v:+.3g}" for v in check["estimate"])
    sig = ", ".join(f"{v:.2g}" for v in check["sigma"])
    return f"{est} +- {sig} {units} when estimated alone, not named by the diagnosis ({check.get('status')})"


def _offset(out: GnssCorrection, effect, check: dict, n_control: int) -> None:
    if effect is None:
        out.notes.append(f"GNSS offset tested against {n_control} control GCPs: {_unnamed(check, 'm')}; "
                         "positions used as recorded")
        return
    est, sig = np.asarray(effect.magnitude, dtype=float), np.asarray(effect.sigma, dtype=float)
    z = np.abs(est) / np.maximum(sig, 1e-300)
    text = (f"{', '.join(f'{v:+.3g}' for v in est)} +- {', '.join(f'{v:.2g}' for v in sig)} m E/N/Up against "
            f"{n_control} control GCPs")
    if not np.any(z > MIN_Z):
        out.notes.append(f"GNSS offset {text}: no component beyond {MIN_Z:g} sigma; positions used as recorded")
        return
    # each horizontal component on its own. The vertical one is not corrected: with f free it is the focal
    # length's twin at a constant flying height (sigma 5 m on conte-calibration) and its linearised estimate
    # is biased there (+15 m on an effect-free block, +17 m with 2 m hidden); subtracting it moved f by 30 px
    use = (z > MIN_Z) & np.array([True, True, False])
    if not use.any():
        out.notes.append(f"GNSS offset {text}: no horizontal component beyond {MIN_Z:g} sigma (the vertical one is "
                         "not corrected: with f free it is f's twin); positions used as recorded")
        return
    offset = np.where(use, est, 0.0)
    axes = ", ".join(a for a, k in zip(("E", "N", "Up"), use, strict=True) if k)
    out.notes.append(f"GNSS offset {text}: the {axes} component(s) beyond {MIN_Z:g} sigma subtracted from the "
                     "recorded positions before the adjustment")
    out.images = shift_gnss(out.images, offset)
    out.offset_m, out.sigma_m = [float(v) for v in offset], [float(v) for v in sig]
    out.evidence["gnss_bias"] = held_out_text(effect)


def _time_lag(out: GnssCorrection, effect, check: dict, rivals: list) -> None:
    rival = "; ".join(f"{r.name} {r.magnitude[0]:.3g} +- {r.sigma[0]:.2g} {r.units} named in the same test"
                      for r in rivals)
    if effect is None:
        out.notes.append(f"GNSS time lag: {_unnamed(check, 's')}; positions used as recorded"
                         + (f" ({rival})" if rival else ""))
        return
    lag, sig = float(effect.magnitude[0]), float(effect.sigma[0])
    text = f"GNSS time lag {lag:+.3g} +- {sig:.2g} s" + (f" ({rival})" if rival else "")
    confused = [a for a in effect.alternatives if a in TIME_LAG_RIVALS]
    if confused:
        out.notes.append(f"{text}: not told apart from {', '.join(confused)} on this block, so not removed; "
                         "positions used as recorded")
        return
    if abs(lag) <= MIN_Z * sig:
        out.notes.append(f"{text}: not beyond {MIN_Z:g} sigma; positions used as recorded")
        return
    out.images = shift_gnss_in_time(out.images, lag)
    out.time_offset_s, out.time_sigma_s = lag, sig
    out.evidence["gnss_time_offset"] = held_out_text(effect)
    out.notes.append(f"{text}: removed from the recorded positions (each moved back along its track by its velocity "
                     "x the lag) before the adjustment")
