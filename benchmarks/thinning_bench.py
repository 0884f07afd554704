"""Tie-point thinning, measured: the adjustments of a matched flight with every track and with the thinned ones.

On the rendered conte-city flight (or its ``--frames N`` central frames), matched once with the flow's
settings, both in this run and one after the other:

* the self-calibration of the calibration sub-block (the flow's: f, cx, cy, k1..k3, p1, p2 and df/dT free,
  adaptive selection, Huber screening), with every track and thinned;
* the fixed-IO block adjustment of the whole flight with the certificate from the thinned calibration,
  with every track and thinned (the left-out tracks intersected afterwards).

Printed: time, observations adjusted, sigma0, IO sigmas, check-point RMSE and rho, and the ratios.

Run: ``python -m benchmarks.thinning_bench [--frames N]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from aerocal.adjust import adjust, adjust_fixed_io, select_images
from aerocal.calibrate.subset import SubsetConfig, propose_subset
from aerocal.camera import LinearThermalModel
from aerocal.ingest import ingest_folder
from aerocal.pipeline.config import ProcessConfig, with_flight_sigmas
from aerocal.pipeline.match_step import match_images
from benchmarks.city_bench import rendered_flight, scratch_folder, subset_folder
from benchmarks.common import flight_document, record


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=None, help="only the N frames nearest the block centre")
    args = ap.parse_args(argv)

    with scratch_folder("work-thinning-") as work:
        full = rendered_flight()
        folder = subset_folder(full, args.frames, work) if args.frames else full
        res = ingest_folder(folder)
        images, gcps, gobs, camera = res.images, res.gcps, res.gcp_observations, res.camera
        flight = flight_document(folder)
        config = ProcessConfig()
        t0 = time.perf_counter()
        _, _, obs, _ = match_images(images, camera, gcps, flight, config.match)
        t_match = time.perf_counter() - t0
        cal_cfg = dataclasses.replace(with_flight_sigmas(config.calibration.adjust, flight),
                                      robust_loss=config.matched_robust_loss)
        blk_cfg = dataclasses.replace(with_flight_sigmas(config.block.adjust, flight),
                                      robust_loss=config.matched_robust_loss)
        thin = config.matched_tie_thinning
        if images.num_rows <= config.calibration.whole_flight_max_images:
            ids = images.column("image_id").to_pylist()
        else:
            scfg = dataclasses.replace(SubsetConfig(), height_agl_m=float(flight["height_agl_m"]))
            ids = propose_subset(images, camera, gcps, scfg).image_ids
        rows, cams = [], {}
        for label, th in (("every track", None), ("thinned", thin)):
            t0 = time.perf_counter()
            cal = adjust(select_images(images, ids), select_images(obs, ids), camera,
                         dataclasses.replace(cal_cfg, tie_thinning=th), gcps, select_images(gobs, ids))
            dt = time.perf_counter() - t0
            cams[label] = cal
            n = int(np.sum(np.isfinite(cal.obs_weight) & (cal.obs_weight > 0)))
            sig = ", ".join(f"{k} {v:.3g}" for k, v in cal.sigmas.items())
            rows.append(f"| self-calibration ({len(ids)} images) | {label} | {dt:.1f} s | {n} | {cal.sigma0:.3f} | "
                        f"f {cal.camera.f:.2f}; sigmas {sig} | {np.round(cal.check_rmse, 3).tolist()} | "
                        f"{np.round(cal.rho, 2).tolist()} |")
        cert = cams["thinned"]
        thermal = cert.thermal if isinstance(cert.thermal, LinearThermalModel) else None
        times = {}
        for label, th in (("every track", None), ("thinned", thin)):
            t0 = time.perf_counter()
            blk = adjust_fixed_io(images, obs, cert.camera, dataclasses.replace(blk_cfg, tie_thinning=th), gcps,
                                  gobs, thermal)
            times[label] = dt = time.perf_counter() - t0
            n = int(np.sum(np.isfinite(blk.obs_weight) & (blk.obs_weight > 0)))
            rows.append(f"| block, IO fixed ({images.num_rows} images) | {label} | {dt:.1f} s | {n} | "
                        f"{blk.sigma0:.3f} | {blk.iterations} iterations; {blk.points.num_rows} points | "
                        f"{np.round(blk.check_rmse, 3).tolist()} | {np.round(blk.rho, 2).tolist()} |")
        lines = [f"{full.name}: {images.num_rows} frames" + (f" ({args.frames} nearest the centre)" if args.frames
                                                               else "")
                 + f"; matched once ({t_match:.0f} s, {obs.num_rows} tie observations); thinning: {thin}", "",
                 "| adjustment | tracks | time | observations adjusted | sigma0 | estimates | check RMSE E/N/Up (m) "
                 "| rho |", "|---|---|---|---|---|---|---|---|", *rows, "",
                 f"- block adjustment time ratio, every track / thinned: "
                 f"{times['every track'] / times['thinned']:.2f}x", ""]
        record("Tie-point thinning: adjustments with every track and thinned, same run", lines)


if __name__ == "__main__":
    main()
