"""Reading foreign calibration files safely, with one-line errors that name the file, field and fix.

* Files larger than :data:`MAX_FILE_BYTES` are refused before they are read (a calibration file is a few
  kilobytes).
* XML goes through ``defusedxml`` with document type declarations refused outright: no entity expansion
  (billion laughs), no external entities or DTDs. Calibration files of OpenCV and Metashape never carry
  a ``<!DOCTYPE>``.
* YAML goes through a :class:`yaml.SafeLoader` subclass that also refuses aliases (the YAML form of
  billion laughs) and every tag except plain data and OpenCV's ``!!opencv-matrix`` and
  ``!!opencv-nd-matrix`` (OpenCV 5 writes 1-D arrays so); OpenCV's
  ``%YAML:1.0`` directive line, which PyYAML rejects, is blanked (keeping line numbers).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import defusedxml.ElementTree as DET
import numpy as np
import yaml
from defusedxml.common import DefusedXmlException, DTDForbidden

#: Largest file any importer reads (bytes).
MAX_FILE_BYTES = 16 * 1024 * 1024

#: YAML tags accepted in OpenCV files: plain data and OpenCV matrices.
ALLOWED_YAML_TAGS = frozenset(
    "tag:yaml.org,2002:" + t
    for t in ("str", "int", "float", "bool", "null", "seq", "map", "timestamp", "opencv-matrix",
              "opencv-nd-matrix")
)


class FormatError(ValueError):
    """A calibration file cannot be read or written; one line naming the file, the field and the fix."""


def format_error(path: str | Path, where: str | None, problem: str, fix: str) -> FormatError:
    """``FormatError("<path>: <where>: <problem>; <fix>")`` (``where`` is a line and/or field)."""
    loc = f"{path}: {where}" if where else f"{path}"
    return FormatError(f"{loc}: {problem}; {fix}")


def read_bytes(path: str | Path) -> bytes:
    """The file's bytes, after checking it exists, is a regular file and is not absurdly large.

    Raises:
        FormatError: ``path`` does not exist, is not a regular file, or is larger than :data:`MAX_FILE_BYTES`.
    """
    path = Path(path)
    if not path.exists():
        raise format_error(path, None, "file not found", "check the path")
    if not path.is_file():
        raise format_error(path, None, "not a regular file", "give the path of a calibration file")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise format_error(path, None, f"file is {size} bytes, more than the {MAX_FILE_BYTES} bytes a "
                           "calibration file can need", "check that this is a calibration file")
    return path.read_bytes()


def decode_text(path: str | Path, data: bytes) -> str:
    """UTF-8 text (a byte-order mark is dropped).

    Raises:
        FormatError: ``data`` is not UTF-8 text; the message names ``path`` and the first bad byte.
    """
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise format_error(path, f"byte {e.start}", "not UTF-8 text", "save the file as UTF-8") from None


# --------------------------------------------------------------------------------------------- XML
def parse_xml(path: str | Path, data: bytes) -> ET.Element:
    """Parse XML with ``defusedxml``; any DTD, entity declaration or external reference is refused.

    Raises:
        FormatError: ``data`` holds a document type declaration, an entity declaration or an external reference; it is
            malformed XML (the message names the line and column); its declared encoding is unknown or does not decode
            it.
    """
    try:
        return DET.fromstring(data, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except DTDForbidden:
        raise format_error(
            path, "<!DOCTYPE>", "XML document type declarations are refused (they carry entity-expansion "
            "and external-entity attacks, and calibration files never need one)",
            "remove the <!DOCTYPE ...> block",
        ) from None
    except DefusedXmlException as e:
        raise format_error(path, None,
                           f"XML entities and external references are refused ({type(e).__name__})",
                           "remove the entity declarations and references") from None
    except ET.ParseError as e:
        line, col = e.position
        msg = str(e).split(":")[0]
        raise format_error(path, f"line {line}, column {col + 1}", f"malformed XML ({msg})",
                           "fix the XML syntax there") from None
    except (LookupError, ValueError) as e:  # an unknown encoding in the XML declaration, bytes it cannot decode
        raise format_error(path, "<?xml ...?>", f"cannot decode the XML ({short_repr(str(e), 80)})",
                           "write the file as UTF-8 with encoding=\"UTF-8\" in its declaration") from None


# --------------------------------------------------------------------------------------------- YAML
class _OpenCVSafeLoader(yaml.SafeLoader):
    """SafeLoader that refuses aliases and understands ``!!opencv-matrix``."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, f"YAML alias *{event.anchor} refused (aliases can expand without bound)",
                event.start_mark,
            )
        return super().compose_node(parent, index)


def _construct_opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> np.ndarray:
    m = loader.construct_mapping(node, deep=True)
    if node.tag.endswith("opencv-nd-matrix"):
        sizes = m.get("sizes")
        if not (isinstance(sizes, list) and len(sizes) in (1, 2)):
            raise yaml.constructor.ConstructorError(
                None, None, f"!!opencv-nd-matrix sizes must list 1 or 2 dimensions, got {sizes!r}",
                node.start_mark)
        m = {"rows": sizes[0], "cols": sizes[1] if len(sizes) == 2 else 1, "dt": m.get("dt"),
             "data": m.get("data")}
    problem = None
    rows, cols, dtype, data = m.get("rows"), m.get("cols"), m.get("dt"), m.get("data")
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (rows, cols)):
        problem = (f"!!opencv-matrix needs positive integer rows and cols, got rows={short_repr(rows)}, "
                   f"cols={short_repr(cols)}")
    elif dtype not in ("d", "f", "i", "u", "s", "c", "w"):
        problem = f"!!opencv-matrix dt {dtype!r} is not a single-channel numeric type"
    elif not isinstance(data, list) or len(data) != rows * cols or not all(
        finite_float(v) is not None for v in data
    ):
        problem = f"!!opencv-matrix data must be {rows * cols} numbers (rows x cols)"
    if problem:
        raise yaml.constructor.ConstructorError(None, None, problem, node.start_mark)
    return np.asarray(data, dtype=float).reshape(rows, cols)


_OpenCVSafeLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _construct_opencv_matrix)
_OpenCVSafeLoader.add_constructor("tag:yaml.org,2002:opencv-nd-matrix", _construct_opencv_matrix)


def _check_tags(node: yaml.Node) -> yaml.Node | None:
    """The first node whose tag is not in :data:`ALLOWED_YAML_TAGS`, or ``None``."""
    if node.tag not in ALLOWED_YAML_TAGS:
        return node
    children: list = []
    if isinstance(node, yaml.MappingNode):
        for k, v in node.value:
            children += [k, v]
    elif isinstance(node, yaml.SequenceNode):
        children = list(node.value)
    for child in children:
        bad = _check_tags(child)
        if bad is not None:
            return bad
    return None


def load_yaml_mapping(path: str | Path, text: str) -> tuple[dict[str, Any], dict[str, int]]:
    """Top-level ``{key: value}`` of a YAML document and the line (1-based) of each key.

    A leading ``%YAML`` directive line (OpenCV's ``%YAML:1.0`` or ``%YAML 1.2``) is blanked.
    Errors name the file, the line and the top-level field being read.

    Raises:
        FormatError: invalid YAML; an empty document or one whose top level is not a mapping; a YAML tag other than
            plain data and ``!!opencv-matrix``; a top-level key that is not text or is given twice.
    """
    lines = text.split("\n")
    if lines and lines[0].lstrip().startswith("%YAML"):
        lines[0] = ""
    loader = _OpenCVSafeLoader("\n".join(lines))
    try:
        try:
            root = loader.get_single_node()
        except yaml.YAMLError as e:
            raise _yaml_error(path, e, None) from None
        if root is None:
            raise format_error(path, None, "empty YAML document", "write the calibration fields")
        if not isinstance(root, yaml.MappingNode):
            raise format_error(path, f"line {root.start_mark.line + 1}", "expected a YAML mapping at the top",
                               "write the fields as 'name: value' lines")
        values: dict[str, Any] = {}
        key_lines: dict[str, int] = {}
        for key_node, value_node in root.value:
            line = key_node.start_mark.line + 1
            for node in (key_node, value_node):
                bad = _check_tags(node)
                if bad is not None:
                    raise format_error(
                        path, f"line {bad.start_mark.line + 1}, field {key_node.value}",
                        f"YAML tag {bad.tag} refused (only plain data and !!opencv-matrix are read, "
                        "never Python objects)", "remove the tag",
                    )
            try:
                key = loader.construct_object(key_node, deep=True)
                value = loader.construct_object(value_node, deep=True)
            except yaml.YAMLError as e:
                raise _yaml_error(path, e, key_node.value) from None
            if not isinstance(key, str):
                raise format_error(path, f"line {line}", f"top-level key {key!r} is not a string",
                                   "name the field with text")
            if key in values:
                raise format_error(path, f"line {line}, field {key}", "field given twice",
                                   f"keep one '{key}' (the first is on line {key_lines[key]})")
            values[key] = value
            key_lines[key] = line
        return values, key_lines
    finally:
        loader.dispose()


def _yaml_error(path: str | Path, e: yaml.YAMLError, field: str | None) -> FormatError:
    mark = getattr(e, "problem_mark", None)
    where = []
    if mark is not None:
        where.append(f"line {mark.line + 1}")
    if field is not None:
        where.append(f"field {field}")
    problem = getattr(e, "problem", None) or str(e).split("\n")[0]
    return format_error(path, ", ".join(where) or None, f"invalid YAML ({problem})", "fix the YAML there")


def finite_float(v: object) -> float | None:
    """``v`` as a finite float when it is a JSON/YAML number (not a bool), else None. An integer too large
    for a float (10^400 written out) is None, not an OverflowError."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    try:
        x = float(v)
    except OverflowError:
        return None
    return x if math.isfinite(x) else None


def short_repr(value: object, limit: int = 24) -> str:
    """``repr(value)`` cut to ``limit`` characters (a number written with 400 digits is echoed as its start)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
