"""A catalogue of input faults: what goes wrong with flight folders in the field, applied to a copy.

Each kind mutates one file of an image-mode flight folder as ``aerocal simulate --mode images`` writes it
(``images/``, ``eo.csv``, ``gcps.csv``, ``gcp_list.txt``, ``camera.json``, ``flight.json``), seeded, and
says what a user must then see from ``aerocal process``:

* ``"stop"``: exit code 2 (bad input), the message names the file; nothing stored.
* ``"said"``: the run may go on (exit 0) or stop (exit 2), but the output names what is wrong (the file,
  or the GCP that was demoted).
* ``"quiet"``: a fault that may be harmless (a bit flip inside pixel data, a stray file): exit 0 or 2,
  nothing else required.

Every kind: no traceback, never exit code 1 (a bad input is not a failure of the program), and no stored
certificate or artifact changed unless the run succeeded. The process-level corpus
(``benchmarks/fuzz_process_bench.py``, a fast subset in ``tests/test_fuzz_process.py``) checks this.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Tokens a spreadsheet, a script or a hand edit puts where a number belongs.
BAD_NUMBERS = ("abc", "", "nan", "inf", "-inf", "1e400", "--", "1,5", "0x1F", "12.3.4", "NULL", "N/A", "1e-400x")


@dataclass(frozen=True)
class AppliedFault:
    """One fault applied to a folder: its kind, the file it touched (relative to the folder), what a user
    must see (``expect``), the words the output must contain for a ``said`` fault (``names``), and what
    was done (``detail``)."""

    kind: str
    target: str
    expect: str
    names: tuple[str, ...]
    detail: str

    def to_dict(self) -> dict:
        return {"kind": self.kind, "target": self.target, "expect": self.expect, "names": list(self.names),
                "detail": self.detail}


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in (folder / "images").iterdir() if p.is_file())


def _table_lines(path: Path) -> tuple[list[str], int]:
    """Lines of a delimited text file and the index of its header (the first line that is no comment)."""
    lines = path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if line.strip() and not line.startswith("#"))
    return lines, header


def _write_lines(path: Path, lines: list[str]) -> None:
    path.write_text("\n".join(lines) + "\n")


# ------------------------------------------------------------------------------------------ images
def image_truncated(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = _images(folder)[int(rng.integers(len(_images(folder))))]
    data = path.read_bytes()
    keep = int(len(data) * rng.uniform(0.02, 0.95))
    path.write_bytes(data[:keep])
    return AppliedFault("image-truncated", f"images/{path.name}", "said", (path.name,),
                        f"cut to {keep} of {len(data)} bytes")


def image_empty(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = _images(folder)[int(rng.integers(len(_images(folder))))]
    path.write_bytes(b"")
    return AppliedFault("image-empty", f"images/{path.name}", "said", (path.name,), "0 bytes")


def image_foreign(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = _images(folder)[int(rng.integers(len(_images(folder))))]
    choices = [b"<html><body>404 Not Found</body></html>\n", b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n" + bytes(200),
               b"\x89PNG\r\n\x1a\n" + bytes(100), rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()]
    pick = int(rng.integers(len(choices)))
    path.write_bytes(choices[pick])
    return AppliedFault("image-foreign", f"images/{path.name}", "said", (path.name,),
                        ["an HTML page", "a PDF", "a PNG header", "random bytes"][pick] + " under an image name")


def image_header_bitflip(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = _images(folder)[int(rng.integers(len(_images(folder))))]
    data = bytearray(path.read_bytes())
    n = int(rng.integers(1, 9))
    for pos in rng.integers(0, min(len(data), 1024), n):
        data[int(pos)] ^= 1 << int(rng.integers(8))
    path.write_bytes(bytes(data))
    return AppliedFault("image-header-bitflip", f"images/{path.name}", "quiet", (path.name,),
                        f"{n} bit(s) flipped in the first 1024 bytes")


def image_stray_file(folder: Path, rng: np.random.Generator) -> AppliedFault:
    name = ["Thumbs.db", ".DS_Store", "notes.txt", "IMG_9999.tif.part", "desktop.ini"][int(rng.integers(5))]
    (folder / "images" / name).write_bytes(rng.integers(0, 256, 512, dtype=np.uint8).tobytes())
    return AppliedFault("image-stray-file", f"images/{name}", "quiet", (name,), "a stray file in images/")


def image_duplicate_name_case(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = _images(folder)[int(rng.integers(len(_images(folder))))]
    copy = path.with_name(path.stem + " (1)" + path.suffix)
    copy.write_bytes(path.read_bytes())
    return AppliedFault("image-duplicate", f"images/{copy.name}", "said", (copy.name,),
                        f"a second copy of {path.name}")


# ------------------------------------------------------------------------------------------ eo.csv
def eo_cell(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "eo.csv"
    lines, h = _table_lines(path)
    columns = lines[h].split(",")
    row = int(rng.integers(h + 1, len(lines)))
    col = int(rng.integers(1, len(columns)))
    cells = lines[row].split(",")
    token = BAD_NUMBERS[int(rng.integers(len(BAD_NUMBERS)))]
    cells[col] = token
    lines[row] = ",".join(cells)
    _write_lines(path, lines)
    return AppliedFault("eo-cell", "eo.csv", "said", ("eo.csv",),
                        f"line {row + 1} column {columns[col]} = {token!r}")


def eo_row_missing(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "eo.csv"
    lines, h = _table_lines(path)
    row = int(rng.integers(h + 1, len(lines)))
    gone = lines.pop(row).split(",")[0]
    _write_lines(path, lines)
    return AppliedFault("eo-row-missing", "eo.csv", "said", (gone,), f"the row of {gone} deleted")


def eo_row_duplicated(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "eo.csv"
    lines, h = _table_lines(path)
    row = int(rng.integers(h + 1, len(lines)))
    cells = lines[row].split(",")
    cells[1] = f"{float(cells[1]) + rng.uniform(1e-4, 1e-3):.9f}"  # the same image, elsewhere
    lines.insert(row + 1, ",".join(cells))
    _write_lines(path, lines)
    return AppliedFault("eo-row-duplicated", "eo.csv", "said", ("eo.csv",),
                        f"{cells[0]} given twice with different positions")


def eo_truncated(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "eo.csv"
    data = path.read_bytes()
    _, h = _table_lines(path)
    start = len("\n".join(path.read_text().splitlines()[: h + 2]))
    cut = int(rng.integers(start, len(data) - 2))
    path.write_bytes(data[:cut])
    return AppliedFault("eo-truncated", "eo.csv", "said", ("eo.csv",), f"cut at byte {cut} of {len(data)}")


def eo_header(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "eo.csv"
    lines, h = _table_lines(path)
    columns = lines[h].split(",")
    col = int(rng.integers(1, len(columns)))
    old = columns[col]
    columns[col] = ["", old.upper() + "_m", "value", old + old, "col" + str(col)][int(rng.integers(5))]
    lines[h] = ",".join(columns)
    _write_lines(path, lines)
    return AppliedFault("eo-header", "eo.csv", "said", ("eo.csv",), f"column {old!r} renamed {columns[col]!r}")


def eo_bytes(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "eo.csv"
    data = bytearray(path.read_bytes())
    junk = [b"\x00", b"\xff\xfe", b"\xe9", b"\r", b"\x1a"][int(rng.integers(5))]
    pos = int(rng.integers(len(data) // 3, len(data)))
    data[pos:pos] = junk
    path.write_bytes(bytes(data))
    return AppliedFault("eo-bytes", "eo.csv", "said", ("eo.csv",), f"bytes {junk!r} inserted at {pos}")


# ------------------------------------------------------------------------------------ ground control
def _gcp_rows(folder: Path) -> tuple[Path, list[str], int]:
    path = folder / "gcps.csv"
    lines, h = _table_lines(path)
    return path, lines, h


def gcp_displaced(folder: Path, rng: np.random.Generator) -> AppliedFault:
    """The same wrong coordinates in both GCP files (so they agree, and only the block can tell)."""
    path, lines, h = _gcp_rows(folder)
    row = int(rng.integers(h + 1, len(lines)))
    cells = lines[row].split(",")
    gid, axis = cells[0], int(rng.integers(1, 4))
    metres = float(rng.choice([-1, 1]) * rng.uniform(30.0, 1000.0))
    old = cells[axis]
    cells[axis] = f"{float(old) + metres:.4f}"
    lines[row] = ",".join(cells)
    _write_lines(path, lines)
    odm = folder / "gcp_list.txt"
    out = []
    for line in odm.read_text().splitlines():
        parts = line.split()
        if len(parts) >= 7 and parts[-1] == gid:
            parts[axis - 1] = cells[axis]
            line = " ".join(parts)
        out.append(line)
    _write_lines(odm, out)
    return AppliedFault("gcp-displaced", "gcps.csv", "said", (gid,),
                        f"{gid} moved {metres:+.1f} m along {'XYZ'[axis - 1]} in gcps.csv and gcp_list.txt")


def gcp_conflict(folder: Path, rng: np.random.Generator) -> AppliedFault:
    odm = folder / "gcp_list.txt"
    lines = odm.read_text().splitlines()
    row = int(rng.integers(1, len(lines)))
    parts = lines[row].split()
    gid = parts[-1]
    metres = float(rng.uniform(5.0, 500.0))
    for k, line in enumerate(lines[1:], 1):
        p = line.split()
        if p and p[-1] == gid:
            p[0] = f"{float(p[0]) + metres:.4f}"
            lines[k] = " ".join(p)
    _write_lines(odm, lines)
    return AppliedFault("gcp-conflict", "gcp_list.txt", "stop", ("gcp_list.txt",),
                        f"{gid} {metres:.1f} m east in gcp_list.txt only")


def gcp_measurement(folder: Path, rng: np.random.Generator) -> AppliedFault:
    odm = folder / "gcp_list.txt"
    lines = odm.read_text().splitlines()
    row = int(rng.integers(1, len(lines)))
    parts = lines[row].split()
    what = int(rng.integers(4))
    if what == 0:
        parts[3], detail = f"{-50.0 - rng.uniform(0, 500):.3f}", "pixel x outside the image"
    elif what == 1:
        parts[5], detail = "IMG_0999.tif", "an image that is not in the folder"
    elif what == 2:
        parts[4], detail = BAD_NUMBERS[int(rng.integers(len(BAD_NUMBERS)))] or "?", "pixel y not a number"
    else:
        parts, detail = parts[:4], "a line cut short"
    lines[row] = " ".join(parts)
    _write_lines(odm, lines)
    return AppliedFault("gcp-measurement", "gcp_list.txt", "said", ("gcp_list.txt",), f"line {row + 1}: {detail}")


def gcp_cell(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path, lines, h = _gcp_rows(folder)
    row = int(rng.integers(h + 1, len(lines)))
    cells = lines[row].split(",")
    col = int(rng.integers(1, len(cells)))
    token = BAD_NUMBERS[int(rng.integers(len(BAD_NUMBERS)))] if col < 6 else ["", "controll", "both"][
        int(rng.integers(3))]
    cells[col] = token
    lines[row] = ",".join(cells)
    _write_lines(path, lines)
    return AppliedFault("gcp-cell", "gcps.csv", "said", ("gcps.csv",), f"line {row + 1} column {col} = {token!r}")


# --------------------------------------------------------------------------- camera.json, flight.json
def camera_json(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "camera.json"
    doc = json.loads(path.read_text())
    what = int(rng.integers(8))
    cam = doc["camera"]
    if what == 0:
        path.write_text(path.read_text()[: int(rng.integers(5, 60))])
        return AppliedFault("camera-json", "camera.json", "stop", ("camera.json",), "cut short")
    changes = [None, ("f", -cam["f"]), ("f", 1e308), ("k1", 1e300), ("width", cam["width"] + 1),
               ("f", float("nan")), ("cx", None), ("f", "1668 px")][what]
    key, value = changes
    if value is None:
        del cam[key]
    else:
        cam[key] = value
    path.write_text(json.dumps(doc))
    return AppliedFault("camera-json", "camera.json", "stop", ("camera.json",), f"camera.{key} = {value!r}")


def flight_json(folder: Path, rng: np.random.Generator) -> AppliedFault:
    path = folder / "flight.json"
    doc = json.loads(path.read_text())
    what = int(rng.integers(6))
    if what == 0:
        path.write_text(path.read_text().replace(",", ";", 1))
        return AppliedFault("flight-json", "flight.json", "stop", ("flight.json",), "a comma made a semicolon")
    key, value = [None, ("height_agl_m", -60.0), ("crs", "EPSG:999999"), ("gnss_sigma_m", "two metres"),
                  ("imu_sigma_deg", [-1, 1, 1]), ("height_agl_m", "high")][what]
    doc[key] = value
    path.write_text(json.dumps(doc))
    return AppliedFault("flight-json", "flight.json", "stop", ("flight.json",), f"{key} = {value!r}")


#: kind -> mutation. Each takes the folder (modified in place) and a seeded generator.
FAULTS: dict[str, Callable[[Path, np.random.Generator], AppliedFault]] = {
    "image-truncated": image_truncated,
    "image-empty": image_empty,
    "image-foreign": image_foreign,
    "image-header-bitflip": image_header_bitflip,
    "image-stray-file": image_stray_file,
    "image-duplicate": image_duplicate_name_case,
    "eo-cell": eo_cell,
    "eo-row-missing": eo_row_missing,
    "eo-row-duplicated": eo_row_duplicated,
    "eo-truncated": eo_truncated,
    "eo-header": eo_header,
    "eo-bytes": eo_bytes,
    "gcp-displaced": gcp_displaced,
    "gcp-conflict": gcp_conflict,
    "gcp-measurement": gcp_measurement,
    "gcp-cell": gcp_cell,
    "camera-json": camera_json,
    "flight-json": flight_json,
}


def apply_fault(kind: str, folder: str | Path, seed: int) -> AppliedFault:
    """Apply fault ``kind`` to ``folder`` (in place) with generator seed ``seed``.

    Raises:
        ValueError: ``kind`` is not a key of :data:`FAULTS` (the message lists the known ones).
    """
    if kind not in FAULTS:
        raise ValueError(f"unknown fault {kind!r}; known: {', '.join(FAULTS)}")
    return FAULTS[kind](Path(folder), np.random.default_rng(seed))
