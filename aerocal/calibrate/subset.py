"""Choose a compact calibration sub-block by the predicted precision of the interior orientation.

Candidates are built from the flight's own recorded GNSS/IMU poses: ``k`` neighbouring parallel strips
around the block centre, the ``m`` exposures of each nearest the centre, with or without the
transversal strip, and the control GCPs the candidate sees. Each candidate is scored by the IO sigmas of a
simulated adjustment: synthetic tie points on a plane at the mean terrain height (no DSM, no truth)
projected with the nominal camera, the normal matrix of :mod:`aerocal.adjust.solver` at that noise-free
state, the points marginalised (Schur complement), GNSS and GCP sigmas as in the real adjustment.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.adjust.bundle import initial_state
from aerocal.adjust.problem import AdjustConfig, build_block
from aerocal.adjust.solver import BundleProblem, State, inverse_spd, schur_complement
from aerocal.camera import Camera


@dataclass(frozen=True)
class SubsetConfig:
    """Candidate sub-blocks and scoring (defaults after Conte 2018 and Mitishita).

    ``strip_counts``: numbers of neighbouring parallel strips tried (3, 4); ``images_per_strip``: exposures
    per strip tried (5, 8); ``transversal_images``: exposures of the transversal strip when used (12);
    ``terrain_height_m``: height of the synthetic tie plane (None = mean Z of the GCPs, else mean GNSS
    height minus ``height_agl_m``); ``tie_spacing_px``: grid spacing of the synthetic tie points in image
    pixels at the plane (40), coarsened on large frames to at most ``max_grid_per_side`` (48) points along
    the longer image side, with the sigma scaled so that the information per image area stays that of the
    40 px grid (a 17,310 px UltraCam frame asked for 122,000 synthetic points per frame and 13 GB for 72
    frames; on frames up to 1920 px the grid is unchanged); ``tie_sigma_px`` (0.5); ``adjust``: the
    adjustment configuration whose IO
    precision is predicted; ``max_images`` (44): larger candidates are not considered; ``score_params``
    (f, cx, cy): the score is the largest predicted sigma of these, pixels.
    """

    strip_counts: tuple[int, ...] = (3, 4)
    images_per_strip: tuple[int, ...] = (5, 8)
    transversal_images: int = 12
    terrain_height_m: float | None = None
    height_agl_m: float | None = None
    tie_spacing_px: float = 40.0
    max_grid_per_side: int = 48
    tie_sigma_px: float = 0.5
    adjust: AdjustConfig = field(default_factory=AdjustConfig)
    max_images: int = 44
    score_params: tuple[str, ...] = ("f", "cx", "cy")

    def __post_init__(self) -> None:
        if not self.strip_counts or min(self.strip_counts) < 1:
            raise ValueError(f"SubsetConfig.strip_counts must be counts of 1 or more, got {self.strip_counts}")
        if not self.images_per_strip or min(self.images_per_strip) < 2:
            raise ValueError(f"SubsetConfig.images_per_strip must be counts of 2 or more, got {self.images_per_strip}")
        if self.transversal_images < 0 or self.max_grid_per_side < 1 or self.max_images < 1:
            raise ValueError("SubsetConfig: transversal_images must be 0 or more, max_grid_per_side and max_images 1 "
                             f"or more (got {self.transversal_images}, {self.max_grid_per_side}, {self.max_images})")
        if not (self.tie_spacing_px > 0 and self.tie_sigma_px > 0):
            raise ValueError("SubsetConfig: tie_spacing_px and tie_sigma_px must be positive pixels, got "
                             f"{self.tie_spacing_px}, {self.tie_sigma_px}")
        if self.height_agl_m is not None and not self.height_agl_m > 0:
            raise ValueError(f"SubsetConfig.height_agl_m must be positive metres or None, got {self.height_agl_m}")
        if not self.score_params:
            raise ValueError("SubsetConfig.score_params is empty; give the parameters the sub-block is chosen for")


@dataclass
class SubsetProposal:
    """The chosen sub-block: image ids, strips, GCP ids, predicted IO sigmas (pixels), score and why."""

    image_ids: list[int]
    strips: list[int]
    transversal: bool
    gcp_ids: list[str]
    predicted_sigmas: dict[str, float]
    score: float
    reasons: list[str]
    candidates: list[dict] = field(default_factory=list)


def _strip_axes(C: np.ndarray, strip: np.ndarray) -> tuple[dict[int, np.ndarray], np.ndarray]:
    dirs = {}
    for s in np.unique(strip):
        c = C[strip == s, :2]
        d = c[-1] - c[0] if len(c) > 1 else np.array([1.0, 0.0])
        dirs[int(s)] = d / max(np.linalg.norm(d), 1e-9)
    main = max(dirs.values(), key=lambda d: sum(abs(float(d @ e)) > 0.7 for e in dirs.values()))
    return dirs, main


def _predict(
    images: pa.Table, camera: Camera, ids: list[int], gcps: pa.Table | None, cfg: SubsetConfig, z_plane: float
) -> tuple[dict[str, float], list[str]]:
    im = images.filter(pa.compute.is_in(images.column("image_id"), value_set=pa.array(ids, pa.int32())))
    blk0 = build_block(im, _empty_obs(), None, None, cfg.adjust)
    # synthetic tie grid on the plane, projected with the recorded poses and the camera
    gsd = float(np.mean(blk0.gnss[:, 2] + blk0.origin[2] - z_plane)) / camera.f
    lo = blk0.gnss[:, :2].min(axis=0) - 0.6 * max(camera.width, camera.height) * gsd
    hi = blk0.gnss[:, :2].max(axis=0) + 0.6 * max(camera.width, camera.height) * gsd
    spacing_px = max(cfg.tie_spacing_px, max(camera.width, camera.height) / cfg.max_grid_per_side)
    tie_sigma = cfg.tie_sigma_px * cfg.tie_spacing_px / spacing_px  # one point stands for (ratio)^2 of them
    step = spacing_px * gsd
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], step), np.arange(lo[1], hi[1], step))
    P = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z_plane - blk0.origin[2])])
    rows_i, rows_p, uv = [], [], []
    for i in range(blk0.n_images):
        p = (P - blk0.gnss[i]) @ blk0.R_rec[i].T
        ok = p[:, 2] > 0
        px = camera.project(p[ok])
        inside = camera.in_image(px, margin=2.0)
        rows_i.append(np.full(int(inside.sum()), i))
        rows_p.append(np.flatnonzero(ok)[inside])
        uv.append(px[inside])
    ri, rp, uvs = np.concatenate(rows_i), np.concatenate(rows_p), np.vstack(uv)
    counts = np.bincount(rp, minlength=len(P))
    keep = counts[rp] >= 2
    ri, rp, uvs = ri[keep], rp[keep], uvs[keep]
    used, rp = np.unique(rp, return_inverse=True)
    obs = pa.table(
        {
            "image_id": pa.array(blk0.image_ids[ri], pa.int32()),
            "track_id": pa.array(used[rp], pa.int64()),
            "x": uvs[:, 0],
            "y": uvs[:, 1],
            "sigma": pa.array(np.full(len(ri), tie_sigma), pa.float32()),
        }
    )
    gobs = None
    gids: list[str] = []
    if gcps is not None and gcps.num_rows:
        g = np.column_stack([gcps.column(n).to_numpy() for n in ("X", "Y", "Z")]) - blk0.origin
        names = gcps.column("gcp_id").to_pylist()
        role = gcps.column("role").to_pylist()
        gi, gn, guv = [], [], []
        for i in range(blk0.n_images):
            p = (g - blk0.gnss[i]) @ blk0.R_rec[i].T
            px = camera.project(p)
            inside = np.isfinite(px).all(axis=1) & camera.in_image(np.nan_to_num(px, nan=-1.0), margin=5.0)
            for k in np.flatnonzero(inside):
                if role[k] == "control":
                    gi.append(int(blk0.image_ids[i]))
                    gn.append(names[k])
                    guv.append(px[k])
        gids = sorted(set(gn))
        if gi:
            guv_a = np.asarray(guv)
            gobs = pa.table(
                {
                    "gcp_id": gn,
                    "image_id": pa.array(gi, pa.int32()),
                    "x": guv_a[:, 0],
                    "y": guv_a[:, 1],
                    "sigma": pa.array(np.full(len(gi), cfg.tie_sigma_px), pa.float32()),
                }
            )
    blk = build_block(im, obs, gcps if gobs is not None else None, gobs, cfg.adjust)
    blk, st = initial_state(blk, camera)
    # the noise-free state: the synthetic points where they were placed, GCPs at their coordinates
    state = State(io=st.io, slopes=st.slopes, R=st.R, C=st.C, X=st.X)
    prob = BundleProblem(blk, cfg.adjust, t0=float(np.nanmedian(blk.temperature)) if cfg.adjust.thermal else 0.0)
    _, _, _, r, Jc, Jp, Hpp = prob.residuals(state, jac=True)
    S, *_ = schur_complement(Jc, Jp, Hpp, np.zeros_like(r), 0.0)
    cov = inverse_spd(S.toarray())  # a calibration sub-block: tens of images
    ng = prob.layout.n_global
    names = list(cfg.adjust.free) + [f"d{n}/dT" for n in cfg.adjust.thermal]
    return dict(zip(names, np.sqrt(np.maximum(np.diag(cov)[:ng], 0.0)).tolist(), strict=True)), gids


def terrain_plane(images: pa.Table, gcps: pa.Table | None, cfg: SubsetConfig) -> float | None:
    """Height (world metres) of the synthetic tie plane: ``cfg.terrain_height_m``, else the mean Z of the
    GCPs, else the mean GNSS height minus ``cfg.height_agl_m``; ``None`` when none of them is known."""
    if cfg.terrain_height_m is not None:
        return float(cfg.terrain_height_m)
    if gcps is not None and gcps.num_rows:
        return float(np.mean(gcps.column("Z").to_numpy()))
    if cfg.height_agl_m is not None:
        z = images.column("gnss_z").to_numpy(zero_copy_only=False).astype(float)
        if np.isfinite(z).any():
            return float(np.nanmean(z)) - float(cfg.height_agl_m)
    return None


def predict_io_sigmas(
    images: pa.Table, camera: Camera, gcps: pa.Table | None = None, config: SubsetConfig | None = None,
    image_ids: list[int] | None = None,
) -> dict[str, float] | None:
    """Predicted standard deviations (pixels; slopes pixels per degC) of the self-calibration's global
    parameters on a block of ``image_ids`` (default every image), from its geometry alone: the recorded
    poses, a synthetic tie grid on the terrain plane seen with ``camera``, the GNSS and GCP weights of
    ``config.adjust`` (see the module docstring). ``None`` when the terrain height is unknown."""
    cfg = config or SubsetConfig()
    z_plane = terrain_plane(images, gcps, cfg)
    if z_plane is None:
        return None
    ids = [int(i) for i in (image_ids if image_ids is not None else images.column("image_id").to_pylist())]
    sig, _ = _predict(images, camera, ids, gcps, cfg, z_plane)
    return sig


def _empty_obs() -> pa.Table:
    return tables.empty("observations")


def propose_subset(
    images: pa.Table, camera: Camera, gcps: pa.Table | None = None, config: SubsetConfig | None = None
) -> SubsetProposal:
    """Propose the calibration sub-block with the best predicted IO precision (see the module docstring).

    Raises:
        ValueError: the terrain height is unknown (give ``gcps``, ``SubsetConfig.terrain_height_m`` or
            ``SubsetConfig.height_agl_m``), or no candidate sub-block has at most ``SubsetConfig.max_images`` images
            (lower ``SubsetConfig.strip_counts``).
    """
    cfg = config or SubsetConfig()
    ids = images.column("image_id").to_numpy().astype(int)
    strip = images.column("strip").to_numpy().astype(int)
    C = np.column_stack([images.column(n).to_numpy() for n in ("gnss_x", "gnss_y", "gnss_z")])
    dirs, main = _strip_axes(C, strip)
    centre = np.median(C[:, :2], axis=0)
    across = np.array([-main[1], main[0]])
    parallel = [s for s, d in dirs.items() if abs(float(d @ main)) > 0.7]
    transv = [s for s in dirs if s not in parallel]
    offset = {s: float(np.median(C[strip == s, :2] - centre, axis=0) @ across) for s in parallel}
    parallel.sort(key=lambda s: offset[s])
    z_plane = terrain_plane(images, gcps, cfg)
    if z_plane is None:
        raise ValueError(
            "propose_subset needs the terrain height: give gcps, SubsetConfig.terrain_height_m "
            "or SubsetConfig.height_agl_m"
        )

    def nearest(s: int, m: int) -> list[int]:
        sel = np.flatnonzero(strip == s)
        d = np.linalg.norm(C[sel, :2] - centre, axis=1)
        return sorted(int(ids[k]) for k in sel[np.argsort(d, kind="stable")[:m]])

    candidates = []
    for k, m, use_t in itertools.product(cfg.strip_counts, cfg.images_per_strip, (False, True)):
        if k > len(parallel) or (use_t and not transv):
            continue
        mid = int(np.argmin([abs(offset[s]) for s in parallel]))
        start = min(max(0, mid - (k - 1) // 2), len(parallel) - k)
        strips = parallel[start : start + k]
        chosen = [i for s in strips for i in nearest(s, m)]
        if use_t:
            tsel = transv[0]
            chosen += nearest(tsel, cfg.transversal_images)
            strips = [*strips, tsel]
        if len(chosen) > cfg.max_images:
            continue
        sig, gids = _predict(images, camera, chosen, gcps, cfg, z_plane)
        score = max(sig[p] for p in cfg.score_params if p in sig)
        candidates.append(
            {
                "image_ids": chosen,
                "strips": strips,
                "transversal": use_t,
                "gcp_ids": gids,
                "sigmas": sig,
                "score": score,
                "n_images": len(chosen),
            }
        )
    if not candidates:
        raise ValueError(
            f"no candidate sub-block of at most {cfg.max_images} images: the flight has "
            f"{len(parallel)} parallel strips; lower SubsetConfig.strip_counts"
        )
    best = min(candidates, key=lambda c: (c["score"], c["n_images"]))
    ranked = sorted(candidates, key=lambda c: (c["score"], c["n_images"]))
    reasons = [
        f"{len(candidates)} candidates scored by the largest predicted sigma of {', '.join(cfg.score_params)}"
    ]
    for c in ranked[:4]:
        reasons.append(
            f"{c['n_images']} images, strips {c['strips']}, transversal {c['transversal']}, "
            f"{len(c['gcp_ids'])} GCPs: score {c['score']:.3f} px "
            f"(f {c['sigmas'].get('f', float('nan')):.3f} px)"
        )
    reasons.append(f"chosen: the lowest score ({best['score']:.3f} px) with {best['n_images']} images")
    return SubsetProposal(
        image_ids=best["image_ids"],
        strips=best["strips"],
        transversal=best["transversal"],
        gcp_ids=best["gcp_ids"],
        predicted_sigmas=best["sigmas"],
        score=best["score"],
        reasons=reasons,
        candidates=candidates,
    )
