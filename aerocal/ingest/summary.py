"""A short human-readable summary of an ingest result, as rows of (item, value) for a CLI table."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pyarrow.compute as pc

from aerocal.ingest.folder import IngestResult


def summary_rows(result: IngestResult) -> list[tuple[str, str]]:
    """A short human-readable summary of an ingest result, as rows for a CLI table.

    Args:
        result: what :func:`aerocal.ingest.folder.ingest_folder` returned.

    Returns:
        Rows ``(item, value)``, both text, in this order: images (ingested, skipped), cameras, bit depth, time
        span (UTC), GNSS positions, attitude, camera temperature (degC), strips (and frames in no strip), CRS,
        ground control, the nominal camera and the certificate identity (each when known), flying height (m),
        GNSS sigma (m), and the problems found (errors, those that stop processing, warnings).
    """
    img = result.images
    n = img.num_rows
    rows: list[tuple[str, str]] = []
    skipped = len(result.skipped_images)
    rows.append(("images", f"{n} ingested" + (f", {skipped} skipped" if skipped else "")))
    cams = Counter(img.column("camera_id").to_pylist())
    rows.append(("cameras", "; ".join(f"{c} ({k})" for c, k in cams.most_common()) or "none"))
    depths = Counter(img.column("bit_depth").to_pylist())
    rows.append(("bit depth", ", ".join(f"{d}-bit ({k})" for d, k in sorted(depths.items(), key=str)) or "-"))
    times = [t for t in img.column("time").to_pylist() if t is not None]
    if times:
        t0, t1 = min(times), max(times)
        rows.append(
            (
                "time (UTC)",
                f"{t0:%Y-%m-%d %H:%M:%S} -> {t1:%H:%M:%S} ({(t1 - t0).total_seconds() / 60:.1f} min)",
            )
        )
    else:
        rows.append(("time (UTC)", "unknown"))
    n_pos = n - img.column("gnss_x").null_count
    rows.append(("GNSS positions", f"{n_pos}/{n}"))
    conv = Counter(c for c in img.column("attitude_convention").to_pylist() if c)
    rows.append(("attitude", f"{sum(conv.values())}/{n}" + (f" ({', '.join(conv)})" if conv else "")))
    temps = np.array([t for t in img.column("temperature_c").to_pylist() if t is not None], dtype=float)
    if temps.size:
        first = next(t for t in img.column("temperature_c").to_pylist() if t is not None)
        last = [t for t in img.column("temperature_c").to_pylist() if t is not None][-1]
        rows.append(
            (
                "camera temperature",
                f"{temps.min():.1f} .. {temps.max():.1f} degC "
                f"(first {first:.1f}, last {last:.1f}; {temps.size}/{n})",
            )
        )
    else:
        rows.append(("camera temperature", "not recorded"))
    strips = [s for s in img.column("strip").to_pylist() if s is not None]
    if strips:
        n_strips = len({s for s in strips if s >= 0})
        rows.append(("strips", f"{n_strips} ({sum(1 for s in strips if s < 0)} frames in turns)"))
    else:
        rows.append(("strips", "none (no positions)"))
    rows.append(("CRS", result.crs or "none"))
    if result.gcps.num_rows:
        roles = Counter(result.gcps.column("role").to_pylist())
        observed = (
            pc.count_distinct(result.gcp_observations.column("gcp_id")).as_py()
            if (result.gcp_observations.num_rows)
            else 0
        )
        rows.append(
            (
                "ground control",
                f"{result.gcps.num_rows} GCPs ({', '.join(f'{k} {r}' for r, k in roles.items())}), "
                f"{result.gcp_observations.num_rows} image measurements of {observed}",
            )
        )
    else:
        rows.append(("ground control", "none"))
    if result.camera is not None:
        cam = result.camera
        rows.append(("nominal camera", f"{cam.width}x{cam.height}, f {cam.f:.1f} px ({result.camera_source})"))
    if result.camera_identity is not None:
        rows.append(("certificate identity", result.camera_identity.camera_id.replace("|", " | ")))
    for key, label in (("height_agl_m", "flying height"), ("gnss_sigma_m", "GNSS sigma")):
        value = getattr(result, key)
        text = "unknown" if value is None else (
            f"{value:.1f} m" if key == "height_agl_m" else f"{value[0]:g} m horizontal, {value[1]:g} m vertical"
        )
        source = result.flight_facts.get(key)
        rows.append((label, f"{text} ({source})" if source and value is not None else text))
    errors, warnings, blocking = len(result.errors), len(result.warnings), len(result.blocking)
    stop = f" ({blocking} stop processing)" if blocking else ""
    rows.append(("problems", f"{errors} error(s){stop}, {warnings} warning(s)"))
    return rows
