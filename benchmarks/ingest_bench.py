"""Ingest of FLIR radiometric JPEGs: metadata of a whole flight and the raw-frame decode, per 1000 frames.

Writes N FLIR R-JPEGs of 640 x 512 as a DJI Zenmuse XT2 records them (the project's FFF writer: raw
counts, EXIF, GPS and DJI XMP), then times

* ``ingest_folder`` (every file's markers, EXIF, XMP and FFF headers; no pixel decode),
* ``read_raw`` of every frame (the 16-bit counts, what enhancement and the mosaic read),
* ``read_temperature_c`` of every frame (counts -> degC through the Planck constants),

and two baselines in the same run: ``tifffile`` reading the same counts written as 16-bit TIFFs (the
simulator's thermal format), and ``flyr`` 5.1, the reference FLIR reader, against aerocal's reader on the
same real file (``shared/data/flir_samples/fff_flir_t640.jpg``, 640 x 480 PNG payload: flyr cannot read
the little-endian Zenmuse layout, nor FFF files with fewer than three directory entries).
Target: ingest + raw decode <= 10 s per 1000 frames on 2 cores.

    python -m benchmarks.ingest_bench [--frames 1000] [--flyr-frames 20]
"""

from __future__ import annotations

import argparse
import io
import tempfile
import time
from pathlib import Path

import flyr
import numpy as np
import tifffile
from PIL import Image

from aerocal.ingest import ingest_folder, read_raw
from aerocal.ingest.metadata_writer import dji_xmp_packet, exif_block, fff_file, jpeg_with_flir, jpeg_with_metadata
from aerocal.ingest.pixels import read_temperature_c
from aerocal.simulate.image_files import zenmuse_xt2_camera_info
from benchmarks.common import peak_rss_mb, record

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "flir_samples" / "fff_flir_t640.jpg"


def _write_flight(folder: Path, n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    info = zenmuse_xt2_camera_info(60.0)
    images = folder / "images"
    images.mkdir(parents=True)
    base = rng.integers(3000, 7000, (512, 640)).astype(np.uint16)
    for k in range(n):
        raw = np.roll(base, k, axis=1)
        buf = io.BytesIO()
        Image.fromarray((raw >> 5).astype(np.uint8)).save(buf, "JPEG", quality=85)
        exif = exif_block(make="DJI", model="XT2", focal_mm=13.0, gps=(47.0 + k * 1e-5, 8.0, 620.0))
        xmp = dji_xmp_packet({"AbsoluteAltitude": 620.0, "RelativeAltitude": 60.0, "GimbalRollDegree": 0.0,
                              "GimbalPitchDegree": -90.0, "GimbalYawDegree": 90.0})
        (images / f"DJI_{k:04d}_R.jpg").write_bytes(
            jpeg_with_flir(jpeg_with_metadata(buf.getvalue(), exif, xmp), fff_file(raw, info)))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--flyr-frames", type=int, default=20)
    args = parser.parse_args(argv)

    n = args.frames
    with tempfile.TemporaryDirectory(prefix="aerocal-ingest-bench-") as tmp:
        folder = Path(tmp) / "flight"
        t0 = time.perf_counter()
        _write_flight(folder, n)
        t_write = time.perf_counter() - t0
        paths = sorted((folder / "images").iterdir())
        t0 = time.perf_counter()
        result = ingest_folder(folder)
        t_ingest = time.perf_counter() - t0
        assert result.images.num_rows == n and not result.errors, [str(p) for p in result.errors[:3]]
        t0 = time.perf_counter()
        for p in paths:
            read_raw(p)
        t_raw = time.perf_counter() - t0
        t0 = time.perf_counter()
        for p in paths:
            read_temperature_c(p)
        t_temp = time.perf_counter() - t0

        tiffs = Path(tmp) / "tiff"
        tiffs.mkdir()
        for k, p in enumerate(paths):
            tifffile.imwrite(tiffs / f"{k}.tif", read_raw(p))
        t0 = time.perf_counter()
        for q in sorted(tiffs.iterdir()):
            tifffile.imread(q)
        t_tiff = time.perf_counter() - t0

        sample = SAMPLE if SAMPLE.is_file() else None
        t_flyr_one = t_ours_one = float("nan")
        if sample is not None:
            t0 = time.perf_counter()
            for _ in range(args.flyr_frames):
                flyr.unpack(str(sample)).celsius  # noqa: B018  (the conversion is the work measured)
            t_flyr_one = (time.perf_counter() - t0) / args.flyr_frames
            t0 = time.perf_counter()
            for _ in range(args.flyr_frames):
                read_temperature_c(sample)
            t_ours_one = (time.perf_counter() - t0) / args.flyr_frames
        mb = sum(p.stat().st_size for p in paths) / 1e6
    per = 1000.0 / n
    record(
        f"Ingest of {n} FLIR radiometric JPEGs (640 x 512, {mb:.0f} MB)",
        [
            "| step | time | per 1000 frames |",
            "|---|---|---|",
            f"| write the flight (FFF writer, not ingest) | {t_write:.1f} s | {t_write * per:.1f} s |",
            f"| ingest_folder (metadata, FFF headers, checks) | {t_ingest:.2f} s | {t_ingest * per:.2f} s |",
            f"| read_raw (16-bit counts) | {t_raw:.2f} s | {t_raw * per:.2f} s |",
            f"| read_temperature_c (degC) | {t_temp:.2f} s | {t_temp * per:.2f} s |",
            f"| baseline: tifffile.imread of the same counts as 16-bit TIFF | {t_tiff:.2f} s | {t_tiff * per:.2f} s |",
            "",
            f"- ingest + raw decode: {(t_ingest + t_raw) * per:.2f} s per 1000 frames (target <= 10 s); raw decode "
            f"{t_raw / max(t_tiff, 1e-9):.2f}x the time of reading a plain TIFF",
            f"- one real FLIR T640 file to degC: aerocal {t_ours_one * 1000:.1f} ms, flyr {t_flyr_one * 1000:.1f} ms "
            f"({t_flyr_one / t_ours_one:.1f}x)",
            f"- peak memory {peak_rss_mb():.0f} MB",
        ],
    )


if __name__ == "__main__":
    main()
