"""The Arrow schemas every step of aerocal exchanges.

Steps hand each other Arrow tables (persisted as Parquet), never Python objects. This module is the
single definition of those tables; every reader calls :func:`validate` before it trusts one.

Conventions that hold for every table:

* Image coordinates ``x``, ``y`` are pixels with the origin at the top-left *corner* of the top-left
  pixel, x to the right, y down (the centre of the first pixel is (0.5, 0.5), as in COLMAP).
* World coordinates ``X``, ``Y``, ``Z`` are metres in the flight's projected CRS (easting, northing,
  ellipsoidal or orthometric height as the flight states); the CRS is stored in the table metadata
  under ``aerocal.crs``.
* Rotations are world-to-camera (``cam_from_world``, as in COLMAP) unit quaternions, scalar first
  (``qw, qx, qy, qz``). The camera frame is x right, y down, z along the viewing direction.
* Angles recorded by a sensor (roll/pitch/yaw) are degrees and keep the sensor's own convention,
  named in ``attitude_convention`` (see :mod:`aerocal.geometry`).
* Temperatures are degrees Celsius; times are UTC.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from aerocal.io import atomic_path

CRS_KEY = b"aerocal.crs"
KIND_KEY = b"aerocal.kind"

IMAGES = pa.schema(
    [
        pa.field("image_id", pa.int32(), nullable=False),
        pa.field("name", pa.string(), nullable=False),
        pa.field("path", pa.string()),
        pa.field("sha256", pa.string()),
        pa.field("time", pa.timestamp("us", tz="UTC")),
        pa.field("camera_id", pa.string(), nullable=False),  # "make|model|serial|lens"
        pa.field("width", pa.int32(), nullable=False),
        pa.field("height", pa.int32(), nullable=False),
        pa.field("bit_depth", pa.int8()),
        # GNSS antenna (or recorded camera) position: WGS84 and the flight's projected CRS
        pa.field("lat", pa.float64()),
        pa.field("lon", pa.float64()),
        pa.field("alt", pa.float64()),
        pa.field("gnss_x", pa.float64()),
        pa.field("gnss_y", pa.float64()),
        pa.field("gnss_z", pa.float64()),
        # recorded attitude (degrees) in the convention named by attitude_convention
        pa.field("roll", pa.float64()),
        pa.field("pitch", pa.float64()),
        pa.field("yaw", pa.float64()),
        pa.field("attitude_convention", pa.string()),
        pa.field("temperature_c", pa.float64()),
        pa.field("strip", pa.int32()),
        # the range a laser range finder on the camera's axis measured (metres; DJI XMP LRFTargetDistance)
        pa.field("laser_range_m", pa.float64()),
    ]
)

KEYPOINTS = pa.schema(
    [
        pa.field("image_id", pa.int32(), nullable=False),
        pa.field("keypoint_id", pa.int32(), nullable=False),
        pa.field("x", pa.float32(), nullable=False),
        pa.field("y", pa.float32(), nullable=False),
        pa.field("scale", pa.float32()),
        pa.field("orientation", pa.float32()),  # radians
        pa.field("descriptor", pa.list_(pa.uint8(), 128)),
    ]
)

MATCHES = pa.schema(
    [
        pa.field("image_id1", pa.int32(), nullable=False),
        pa.field("image_id2", pa.int32(), nullable=False),
        pa.field("keypoint_id1", pa.int32(), nullable=False),
        pa.field("keypoint_id2", pa.int32(), nullable=False),
    ]
)

OBSERVATIONS = pa.schema(
    [
        pa.field("image_id", pa.int32(), nullable=False),
        pa.field("track_id", pa.int64(), nullable=False),
        pa.field("x", pa.float64(), nullable=False),
        pa.field("y", pa.float64(), nullable=False),
        pa.field("sigma", pa.float32(), nullable=False),  # a-priori std of x and y, pixels
    ]
)

GCPS = pa.schema(
    [
        pa.field("gcp_id", pa.string(), nullable=False),
        pa.field("X", pa.float64(), nullable=False),
        pa.field("Y", pa.float64(), nullable=False),
        pa.field("Z", pa.float64(), nullable=False),
        pa.field("sigma_x", pa.float64(), nullable=False),
        pa.field("sigma_y", pa.float64(), nullable=False),
        pa.field("sigma_z", pa.float64(), nullable=False),
        pa.field("role", pa.string(), nullable=False),  # "control" or "check"
    ]
)

GCP_OBSERVATIONS = pa.schema(
    [
        pa.field("gcp_id", pa.string(), nullable=False),
        pa.field("image_id", pa.int32(), nullable=False),
        pa.field("x", pa.float64(), nullable=False),
        pa.field("y", pa.float64(), nullable=False),
        pa.field("sigma", pa.float32(), nullable=False),
    ]
)

POSES = pa.schema(
    [
        pa.field("image_id", pa.int32(), nullable=False),
        pa.field("qw", pa.float64(), nullable=False),
        pa.field("qx", pa.float64(), nullable=False),
        pa.field("qy", pa.float64(), nullable=False),
        pa.field("qz", pa.float64(), nullable=False),
        # projection centre in the world frame (not the cam_from_world translation)
        pa.field("X", pa.float64(), nullable=False),
        pa.field("Y", pa.float64(), nullable=False),
        pa.field("Z", pa.float64(), nullable=False),
    ]
)

POINTS = pa.schema(
    [
        pa.field("track_id", pa.int64(), nullable=False),
        pa.field("X", pa.float64(), nullable=False),
        pa.field("Y", pa.float64(), nullable=False),
        pa.field("Z", pa.float64(), nullable=False),
        pa.field("n_obs", pa.int32()),
        pa.field("error", pa.float64()),  # mean reprojection error, pixels
    ]
)

#: nullable columns added to a schema after tables were written without them: a table that lacks one is read with
#: the column null (the tables of earlier flights stay readable), every other missing column is an error
ADDED_COLUMNS: dict[str, tuple[str, ...]] = {"images": ("laser_range_m",)}

SCHEMAS: dict[str, pa.Schema] = {
    "images": IMAGES,
    "keypoints": KEYPOINTS,
    "matches": MATCHES,
    "observations": OBSERVATIONS,
    "gcps": GCPS,
    "gcp_observations": GCP_OBSERVATIONS,
    "poses": POSES,
    "points": POINTS,
}

GCP_ROLES = ("control", "check")


class SchemaError(ValueError):
    """A table does not match the schema of its kind; the message names the column and the fix."""


def empty(kind: str) -> pa.Table:
    """An empty table of ``kind``."""
    return SCHEMAS[_kind(kind)].empty_table()


def _kind(kind: str) -> str:
    if kind not in SCHEMAS:
        raise SchemaError(f"unknown table kind {kind!r}; valid kinds: {', '.join(SCHEMAS)}")
    return kind


def from_columns(kind: str, columns: Mapping[str, object], crs: str | None = None) -> pa.Table:
    """Build a table of ``kind`` from column arrays (numpy arrays or lists), casting to the schema.

    Columns missing from ``columns`` that are nullable are filled with nulls; a missing non-nullable
    column raises :class:`SchemaError`.
    """
    schema = SCHEMAS[_kind(kind)]
    lengths = {len(v) for v in columns.values()}  # type: ignore[arg-type]
    if len(lengths) > 1:
        raise SchemaError(f"{kind}: columns have different lengths {sorted(lengths)}")
    n = lengths.pop() if lengths else 0
    unknown = set(columns) - set(schema.names)
    if unknown:
        raise SchemaError(f"{kind}: unknown column(s) {sorted(unknown)}; valid: {', '.join(schema.names)}")
    arrays = []
    for field in schema:
        if field.name in columns:
            try:
                arrays.append(pa.array(columns[field.name], type=field.type))
            except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
                raise SchemaError(f"{kind}.{field.name}: cannot convert to {field.type}: {exc}") from exc
        elif field.nullable:
            arrays.append(pa.nulls(n, type=field.type))
        else:
            raise SchemaError(f"{kind}: required column {field.name!r} is missing")
    table = pa.Table.from_arrays(arrays, schema=schema)
    return with_crs(table, crs) if crs else _tag(table, kind)


def _tag(table: pa.Table, kind: str) -> pa.Table:
    meta = dict(table.schema.metadata or {})
    meta[KIND_KEY] = kind.encode()
    return table.replace_schema_metadata(meta)


def with_crs(table: pa.Table, crs: str) -> pa.Table:
    """Return ``table`` with the flight's projected CRS (e.g. ``"EPSG:32632"``) in its metadata."""
    meta = dict(table.schema.metadata or {})
    meta[CRS_KEY] = crs.encode()
    return table.replace_schema_metadata(meta)


def crs_of(table: pa.Table) -> str | None:
    """The CRS stored in a table's metadata, or ``None``."""
    meta = table.schema.metadata or {}
    value = meta.get(CRS_KEY)
    return value.decode() if value else None


def validate(table: pa.Table, kind: str, source: str | Path | None = None) -> pa.Table:
    """Check ``table`` against the schema of ``kind`` and return it cast to that schema.

    Extra columns are refused (they would be silently dropped by the next writer); missing columns (but those of
    :data:`ADDED_COLUMNS`, read as nulls), wrong types and nulls in required columns raise :class:`SchemaError`
    naming ``source``, the column and what was expected.
    """
    schema = SCHEMAS[_kind(kind)]
    where = f"{source}: " if source else ""
    names = set(table.schema.names)
    for name in ADDED_COLUMNS.get(kind, ()):
        if name not in names:
            table = table.append_column(schema.field(name), pa.nulls(table.num_rows, schema.field(name).type))
            names.add(name)
    missing = [f.name for f in schema if f.name not in names]
    if missing:
        raise SchemaError(f"{where}{kind} table lacks column(s) {missing}; expected {schema.names}")
    extra = sorted(names - set(schema.names))
    if extra:
        raise SchemaError(f"{where}{kind} table has unexpected column(s) {extra}")
    table = table.select(schema.names)
    for field in schema:
        col = table.column(field.name)
        if col.type != field.type:
            try:
                col = col.cast(field.type)
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
                raise SchemaError(
                    f"{where}{kind}.{field.name} has type {col.type}, expected {field.type}"
                ) from exc
            table = table.set_column(schema.get_field_index(field.name), field.name, col)
        if not field.nullable and col.null_count:
            raise SchemaError(f"{where}{kind}.{field.name} has {col.null_count} null value(s); it is required")
    if kind in ("gcps",):
        roles = set(table.column("role").to_pylist())
        bad = roles - set(GCP_ROLES)
        if bad:
            raise SchemaError(f"{where}gcps.role has value(s) {sorted(bad)}; valid: {', '.join(GCP_ROLES)}")
    meta = dict(table.schema.metadata or {})
    return table.cast(schema).replace_schema_metadata(meta)


def write(table: pa.Table, path: str | Path, kind: str) -> Path:
    """Validate and write ``table`` as Parquet atomically (temporary file, fsync, rename)."""
    table = _tag(validate(table, kind), kind)
    path = Path(path)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return path


def read(path: str | Path, kind: str) -> pa.Table:
    """Read a Parquet table and validate it against ``kind``; errors name the file.

    Raises:
        SchemaError: ``path`` is not a readable Parquet file, or the table does not match the ``kind`` schema; the
            message names the file.
    """
    path = Path(path)
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as exc:
        raise SchemaError(f"{path}: not a readable Parquet file ({exc})") from exc
    return validate(table, kind, source=path)


def metadata_json(table: pa.Table, key: str) -> object:
    """Decode a JSON value stored in the table metadata under ``key`` (``None`` when absent)."""
    meta = table.schema.metadata or {}
    raw = meta.get(key.encode())
    return json.loads(raw) if raw else None
