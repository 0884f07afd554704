"""Bad input never stops ingest: corrupted, truncated, mislabelled and absurd files are reported by name.

The fuzz test builds a seeded corpus of more than 200 mutated files from small copies of the measured
cameras' metadata (Canon PowerShot with senseFly XMP, Canon EOS, DJI H20T R-JPEG) and a simulated TIFF,
plus mutated GCP and EO text files, and checks that every file or line that is bad is reported.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from aerocal import tables
from aerocal.ingest import IngestOutputError, ingest_folder, read_ingest, read_raw, write_ingest
from aerocal.ingest.delimited import read_text_lines
from aerocal.ingest.eo_csv import read_eo_csv
from aerocal.ingest.gcp_odm import read_odm_gcp_list
from aerocal.ingest.metadata_writer import dji_xmp_packet, jpeg_without_metadata, write_tiff_with_metadata
from aerocal.ingest.problems import ProblemLog

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SHARED_MISSING = f"measured data not found at {DATA} (a clone without ../shared/data)"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=SHARED_MISSING)  # only without ../shared/data
FUZZ_SEED = int(os.environ.get("AEROCAL_FUZZ_SEED", "20240611"))


def _segments(data: bytes) -> list[tuple[int, int, int]]:
    """(marker, payload offset, payload length) of the segments before SOS."""
    out, i = [], 2
    while i + 4 <= len(data) and data[i] == 0xFF and data[i + 1] != 0xDA:
        length = struct.unpack_from(">H", data, i + 2)[0]
        out.append((data[i + 1], i + 4, length - 2))
        i += 2 + length
    return out


def _graft(real: bytes, app3: bytes = b"", app4: bool = False, width: int = 64, height: int = 48) -> bytes:
    """A small JPEG (width x height) carrying the real file's APP1 segments (EXIF, XMP), optionally a raw
    frame in APP3 segments and the real file's APP4 block, in DJI's order."""
    ok, buf = cv2.imencode(".jpg", np.full((height, width, 3), 90, np.uint8))
    body = jpeg_without_metadata(buf.tobytes())
    segs = b"".join(real[o - 4 : o + n] for m, o, n in _segments(real) if m == 0xE1)
    for k in range(0, len(app3), 65530):
        chunk = app3[k : k + 65530]
        segs += b"\xff\xe3" + struct.pack(">H", len(chunk) + 2) + chunk
    if app4:
        segs += b"".join(real[o - 4 : o + n] for m, o, n in _segments(real) if m == 0xE4)
    return body[:2] + segs + body[2:]


def _entry(data: bytes, ifd_offset: int, tag: int) -> int:
    """Byte offset in ``data`` (a little-endian TIFF block) of the 12-byte entry of ``tag`` in the IFD there."""
    count = struct.unpack_from("<H", data, ifd_offset)[0]
    for k in range(count):
        pos = ifd_offset + 2 + 12 * k
        if struct.unpack_from("<H", data, pos)[0] == tag:
            return pos
    raise KeyError(tag)


def _exif_block(data: bytes) -> tuple[int, Image.Exif]:
    """(offset of the TIFF header, Pillow's reading) of the APP1 EXIF block of a JPEG."""
    for m, o, n in _segments(data):
        if m == 0xE1 and data[o : o + 6] == b"Exif\x00\x00":
            exif = Image.Exif()
            exif.load(data[o + 6 : o + n])
            return o + 6, exif
    raise KeyError("EXIF")


def _exif_entry_offset(data: bytes, tag: int, ifd: str = "ifd0") -> int:
    """Byte offset in ``data`` of the 12-byte IFD entry of ``tag`` (IFD0, EXIF or GPS IFD of APP1)."""
    base, exif = _exif_block(data)
    offset = struct.unpack_from("<I", data, base + 4)[0] if ifd == "ifd0" else exif[{"exif": 34665, "gps": 34853}[ifd]]
    return base + _entry(data[base:], offset, tag)


def _canon_camera_info_temperature_offset(data: bytes) -> int:
    """Byte offset in ``data`` of the CameraInfo value (third from the end) Canon compacts keep degC in."""
    base, exif = _exif_block(data)
    block = data[base:]
    maker_note = block.find(exif.get_ifd(34665)[0x927C])
    entry = _entry(block, maker_note, 0x000D)
    count, values = struct.unpack_from("<II", block, entry + 4)
    return base + values + 4 * (count - 3)


def _seeds(tmp: Path) -> dict[str, bytes]:
    seneca = (DATA / "seneca" / "images" / "IMG_0500.jpg").read_bytes()
    copr = (DATA / "copr" / "images" / "IMG_0046.jpg").read_bytes()
    dji = (DATA / "h20t_forest" / "images" / "DJI_20220602143546_0199_T.JPG").read_bytes()
    raw = np.arange(64 * 48, dtype="<u2").tobytes()
    sim = tmp / "seed.tif"
    xmp = dji_xmp_packet(
        {
            "GpsLatitude": 46.9,
            "GpsLongitude": 9.0,
            "AbsoluteAltitude": 900.0,
            "GimbalRollDegree": 0.0,
            "GimbalPitchDegree": -90.0,
            "GimbalYawDegree": 10.0,
        }
    )
    write_tiff_with_metadata(sim, np.full((48, 64), 30000, np.uint16), "aerocal", "SimTherm", "S1", xmp=xmp)
    return {
        "seneca": _graft(seneca),
        "copr": _graft(copr),
        "dji": _graft(dji, app3=raw, app4=True),
        "sim": sim.read_bytes(),
    }


def _mutations(seeds: dict[str, bytes], rng: np.random.Generator):
    """Yield (name, bytes, expected field or "error" or None): what ingest must report for the file."""
    for kind, data in seeds.items():
        ext = ".tif" if kind == "sim" else ".jpg"
        yield f"{kind}_intact{ext}", data, None
        for k in range(18):
            cut = int(rng.integers(2, len(data) - 2))
            yield f"{kind}_trunc{k}{ext}", data[:cut], "error"
        for k in range(18):
            b = bytearray(data)
            limit = min(len(b), 3000 if kind != "sim" else 1000)
            for _ in range(int(rng.integers(1, 20))):
                pos = int(rng.integers(0, limit))
                b[pos] ^= 1 << int(rng.integers(0, 8))
            yield f"{kind}_flip{k}{ext}", bytes(b), None  # anything may happen; nothing may crash
        for k in range(5):
            yield f"{kind}_garbage{k}{ext}", rng.bytes(int(rng.integers(1, 5000))), "error"
    ok, png = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    yield "png_named.jpg", png.tobytes(), "error"
    yield "empty.jpg", b"", "error"
    yield "jpeg_named.tif", seeds["copr"] + b"\x00", "extension"  # one byte after EOI: not a duplicate
    # absurd values, same byte length so segment lengths stay valid
    s = seeds["seneca"]
    lat = s.find(b"<sensefly:Latitude>") + len(b"<sensefly:Latitude>")
    end = s.find(b"<", lat)
    yield "seneca_lat400.jpg", s[:lat] + (b"400." + b"0" * 40)[: end - lat] + s[end:], "lat/lon"
    d = seeds["dji"]
    i = d.find(b'GpsLatitude="') + len(b'GpsLatitude="')
    yield "dji_lat400.jpg", d[:i] + b"+400.000000" + d[i + 11 :], "lat/lon"
    app4 = [o for m, o, n in _segments(d) if m == 0xE4][0]
    nan = bytearray(d)
    nan[app4 + 132 : app4 + 136] = struct.pack("<f", math.nan)
    yield "dji_app4_nan.jpg", bytes(nan), "dji_app4_f132_undocumented"
    hot = bytearray(s)
    struct.pack_into("<i", hot, _canon_camera_info_temperature_offset(s), 500)
    yield "seneca_temp500.jpg", bytes(hot), "temperature_c"
    # wrong metadata types: Make stored as SHORT, GPSLatitude stored as ASCII
    for name, seed, tag, ifd, typ, field in (
        ("copr_make_short.jpg", seeds["copr"], 271, "ifd0", 3, "Make"),
        ("seneca_gpslat_ascii.jpg", s, 2, "gps", 2, "GPSLatitude"),
        ("dji_gpslat_ascii.jpg", d, 2, "gps", 2, "GPSLatitude"),
    ):
        b = bytearray(seed)
        struct.pack_into("<H", b, _exif_entry_offset(seed, tag, ifd) + 2, typ)
        yield name, bytes(b), field
    broken = s.replace(b"</rdf:Description>", b"<!rdf:Description>", 1)
    yield "seneca_xmp_broken.jpg", broken, "XMP"
    sim = bytearray(seeds["sim"])
    struct.pack_into("<I", sim, _tiff_entry(seeds["sim"], 256) + 8, 0xFFFFFFFB)  # width -5 as LONG
    yield "sim_negative_width.tif", bytes(sim), "error"


def _tiff_entry(data: bytes, tag: int) -> int:
    return _entry(data, struct.unpack_from("<I", data, 4)[0], tag)


def _assert_table_sane(images) -> None:
    img = tables.validate(images, "images")
    for col, lo, hi in (
        ("lat", -90, 90),
        ("lon", -180, 180),
        ("temperature_c", -60, 120),
        ("roll", -180, 180),
    ):
        values = np.array([v for v in img.column(col).to_pylist() if v is not None], dtype=float)
        assert np.all(np.isfinite(values)) and np.all((values >= lo) & (values <= hi)), col
    assert all(w > 0 for w in img.column("width").to_pylist())


# ---------------------------------------------------------------------------- hand-made bad folder
@needs_data
def test_truncated_and_stripped_images_are_named_and_the_rest_ingests(tmp_path):
    src = DATA / "seneca" / "images"
    shutil.copy(src / "IMG_0500.jpg", tmp_path / "IMG_0500.jpg")
    data = (src / "IMG_0501.jpg").read_bytes()
    (tmp_path / "IMG_0501.jpg").write_bytes(data[: len(data) * 6 // 10])
    (tmp_path / "IMG_0502.jpg").write_bytes(jpeg_without_metadata((src / "IMG_0502.jpg").read_bytes()))
    r = ingest_folder(tmp_path)
    assert r.images.column("name").to_pylist() == ["IMG_0500.jpg", "IMG_0502.jpg"]
    assert r.skipped_images == ["IMG_0501.jpg"]
    trunc = [p for p in r.errors if p.file == str(tmp_path / "IMG_0501.jpg")]
    assert len(trunc) == 1 and "truncated" in trunc[0].message
    stripped = [p for p in r.problems if p.file == str(tmp_path / "IMG_0502.jpg")]
    assert any("no EXIF or XMP metadata" in p.message for p in stripped)
    assert all(p.severity == "warning" for p in stripped)
    rows = r.images.to_pylist()
    assert rows[0]["lat"] is not None and rows[0]["temperature_c"] is not None
    assert rows[1]["lat"] is None and rows[1]["camera_id"] == rows[0]["camera_id"], "same size: same camera"


@needs_data
def test_ifd_entries_pillow_cannot_read_are_reported_not_silent(tmp_path):
    """Pillow skips an entry of unknown type without a word and stops an IFD at a value outside the block:
    both are reported against the file, and the rest of the image ingests."""
    copr = _graft((DATA / "copr" / "images" / "IMG_0046.jpg").read_bytes())
    unknown = bytearray(copr)
    struct.pack_into("<H", unknown, _exif_entry_offset(copr, 272) + 2, 2050)  # Model: type 2050 does not exist
    (tmp_path / "model_unknown_type.jpg").write_bytes(bytes(unknown))
    outside = bytearray(copr)
    struct.pack_into("<I", outside, _exif_entry_offset(copr, 271) + 8, 0xFFFFFF)  # Make's text beyond the block
    (tmp_path / "make_outside.jpg").write_bytes(bytes(outside))
    r = ingest_folder(tmp_path)
    rows = {row["name"]: row for row in r.images.to_pylist()}
    assert set(rows) == {"model_unknown_type.jpg", "make_outside.jpg"}
    assert not [p for p in r.errors if p.file.endswith(".jpg")], [str(p) for p in r.errors]
    by_file = {name: [p for p in r.problems if p.file == str(tmp_path / name)] for name in rows}
    skipped = [p for p in by_file["model_unknown_type.jpg"] if p.field == "EXIF"]
    assert len(skipped) == 1 and "IFD0 at byte 8 declares 9 entries, Pillow read 8" in skipped[0].message
    assert rows["model_unknown_type.jpg"]["camera_id"].startswith("Canon||")
    messages = [p.message for p in by_file["make_outside.jpg"] if p.field == "EXIF"]
    assert any(m.startswith("Pillow: Truncated File Read") for m in messages), messages
    assert any("declares 9 entries" in m for m in messages), messages
    assert rows["make_outside.jpg"]["temperature_c"] is None, "no make: the Canon maker note is not read"


def test_bigtiff_is_read_little_endian_and_named_big_endian(tmp_path):
    import tifffile

    pixels = np.arange(20 * 30, dtype=np.uint16).reshape(20, 30)
    tags = [(271, "s", 0, "aerocal", True), (272, "s", 0, "BigSim", True)]
    tifffile.imwrite(tmp_path / "little.tif", pixels, bigtiff=True, extratags=tags)
    tifffile.imwrite(tmp_path / "big.tif", pixels, bigtiff=True, byteorder=">", extratags=tags)
    r = ingest_folder(tmp_path)
    row = r.images.to_pylist()[0]
    assert (row["name"], row["width"], row["height"], row["bit_depth"]) == ("little.tif", 30, 20, 16)
    assert row["camera_id"].startswith("aerocal|BigSim|")
    assert r.skipped_images == ["big.tif"]
    (big,) = [p for p in r.errors if p.file.endswith("big.tif")]
    assert "big-endian BigTIFF" in big.message
    assert np.array_equal(read_raw(tmp_path / "little.tif"), pixels)


# ---------------------------------------------------------------------------- fuzz corpus
@needs_data
@pytest.mark.timeout(120)
def test_fuzz_corpus_never_raises_and_reports_every_bad_file(tmp_path):
    rng = np.random.default_rng(FUZZ_SEED)
    folder = tmp_path / "images"
    folder.mkdir()
    expected: dict[str, str | None] = {}
    for name, data, expect in _mutations(_seeds(tmp_path), rng):
        (folder / name).write_bytes(data)
        expected[name] = expect
    n_images = len(expected)
    result = ingest_folder(folder)  # must not raise
    crashes = [str(p) for p in result.problems if "unexpected failure" in p.message]
    assert not crashes, f"seed={FUZZ_SEED}: a reader raised instead of reporting: {crashes}"
    by_file: dict[str, list] = {}
    for p in result.problems:
        by_file.setdefault(Path(p.file).name, []).append(p)
    ingested = set(result.images.column("name").to_pylist())
    for name, expect in expected.items():
        found = by_file.get(name, [])
        where = f"seed={FUZZ_SEED} file={name} problems={[str(p) for p in found]}"
        if expect == "error":
            assert any(p.severity == "error" for p in found) and name not in ingested, where
        elif expect == "extension":
            assert name in ingested and any("extension" in p.message for p in found), where
        elif expect is not None:
            assert name in ingested and any(p.field == expect for p in found), where
        elif "intact" in name:
            assert name in ingested and not [p for p in found if p.severity == "error"], where
        else:  # bit flips: either ingested or reported as an error
            assert name in ingested or any(p.severity == "error" for p in found), where
    _assert_table_sane(result.images)

    # text sidecars: every mutated line is reported with its line number
    text_files = _fuzz_text_files(tmp_path / "text", rng)
    for path, bad_lines, reader in text_files:
        problems = ProblemLog()
        reader(path, problems)  # must not raise
        reported = {p.line for p in problems if p.severity == "error"}
        missing = sorted(set(bad_lines) - reported)
        assert not missing, f"seed={FUZZ_SEED} {path.name}: bad lines {missing} not reported"
    assert n_images + len(text_files) >= 200, "the corpus must hold at least 200 mutated files"

    # the tables written from such a flight read back; nothing partial is left on failure
    out = tmp_path / "out"
    write_ingest(result, out)
    back = read_ingest(out)
    assert back["images"].num_rows == result.images.num_rows
    assert len(back["problems"]) == len(result.problems)


def _fuzz_text_files(folder: Path, rng: np.random.Generator) -> list[tuple[Path, list[int], object]]:
    folder.mkdir()
    out = []
    base_gcp = (DATA / "copr" / "gcp_list.txt").read_text().splitlines()
    for k in range(25):
        lines = list(base_gcp)
        bad = sorted(
            rng.choice(np.arange(1, len(lines)), size=int(rng.integers(1, 5)), replace=False).tolist()
        )
        for i in bad:
            fields = lines[i].split()
            how = int(rng.integers(0, 3))
            if how == 0:
                fields = fields[: int(rng.integers(1, 5))]  # wrong column count
            elif how == 1:
                fields[int(rng.integers(0, 5))] = "x1"  # non-numeric
            else:
                fields[int(rng.integers(0, 5))] = "nan"  # not finite
            lines[i] = " ".join(fields)
        path = folder / f"gcp_{k}.txt"
        path.write_text("\n".join(lines) + "\n")
        out.append((path, [i + 1 for i in bad], lambda p, pr: read_odm_gcp_list(p, pr)))
    crs_bad = folder / "gcp_badcrs.txt"
    crs_bad.write_text("\n".join(["NOT A CRS 99", *base_gcp[1:]]) + "\n")
    out.append((crs_bad, [1], lambda p, pr: read_odm_gcp_list(p, pr)))
    header = "image,lat,lon,alt,roll,pitch,yaw,temperature"
    good = [f"IMG_{i:04d}.tif,46.9,9.0,900,0,-90,{i},25" for i in range(12)]
    for k in range(15):
        lines = list(good)
        bad = sorted(rng.choice(np.arange(len(lines)), size=int(rng.integers(1, 4)), replace=False).tolist())
        for i in bad:
            f = lines[i].split(",")
            how = int(rng.integers(0, 4))
            if how == 0:
                f = f[:-2]
            elif how == 1:
                f[1] = "400"
            elif how == 2:
                f[7] = "nan"
            else:
                f[int(rng.integers(1, 8))] = "abc"
            lines[i] = ",".join(f)
        path = folder / f"eo_{k}.csv"
        path.write_text(
            "# crs: EPSG:4326\n# attitude: dji_gimbal\n" + header + "\n" + "\n".join(lines) + "\n"
        )
        out.append((path, [i + 4 for i in bad], lambda p, pr: read_eo_csv(p, pr)))
    return out


def test_text_lines_are_counted_like_grep(tmp_path):
    p = tmp_path / "a.txt"
    p.write_bytes(b"EPSG:32611\r\r\n1 2 3 4 5 a.jpg\r\r\n\r\r\n1 2 3 4 x a.jpg\r\n")
    lines = read_text_lines(p, ProblemLog())
    assert [n for n, _ in lines.lines] == [1, 2, 4]
    problems = ProblemLog()
    read_odm_gcp_list(p, problems)
    assert [pr.line for pr in problems if pr.severity == "error"] == [4]


# ---------------------------------------------------------------------------- nothing partial on disk
def test_write_ingest_leaves_nothing_trusted_when_interrupted(tmp_path, monkeypatch):
    folder = tmp_path / "imgs"
    for k in range(3):
        write_tiff_with_metadata(folder / f"IMG_{k}.tif", np.full((8, 8), k, np.uint16), "aerocal", "T")
    result = ingest_folder(folder)
    out = tmp_path / "out"
    write_ingest(result, out)
    assert read_ingest(out)["images"].num_rows == 3

    import pyarrow.parquet as pq

    real = pq.write_table
    calls = {"n": 0}

    def failing(table, where, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError("disk full")
        return real(table, where, *args, **kwargs)

    monkeypatch.setattr(pq, "write_table", failing)
    with pytest.raises(OSError, match="disk full"):
        write_ingest(result, out)
    monkeypatch.undo()
    with pytest.raises(IngestOutputError, match="ingest.json"):
        read_ingest(out)
    assert not list(out.glob(".tmp-*")), "no temporary file is left behind"
    tables.read(out / "images.parquet", "images")  # what was written is whole
