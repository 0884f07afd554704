"""CRS names as written in sidecar files, normalised to the strings aerocal stores (``"EPSG:32611"``).

Accepted: ``EPSG:xxxx``, PROJ strings (``+proj=utm +zone=11 ...``), WKT, and OpenDroneMap's
``WGS84 UTM 11N`` / ``WGS84 UTM 11S`` / ``WGS84`` forms. A CRS that pyproj identifies with an EPSG code
(confidence >= 70 %) is returned as ``EPSG:code``; otherwise as pyproj's PROJ string.
"""

from __future__ import annotations

import re
from functools import lru_cache

from pyproj import CRS
from pyproj.exceptions import CRSError

_ODM_UTM = re.compile(r"^(?:WGS\s*84\s+)?UTM\s+(\d{1,2})\s*([NS])?$", re.IGNORECASE)


class CrsTextError(ValueError):
    """The text names no CRS pyproj knows; the message says what was read."""


@lru_cache(maxsize=128)
def normalise_crs(text: str) -> str:
    """The CRS ``text`` names, as ``"EPSG:xxxx"`` where possible; raise :class:`CrsTextError` if unknown."""
    raw = text.strip()
    if not raw:
        raise CrsTextError("the CRS is empty")
    if re.fullmatch(r"WGS\s*84", raw, re.IGNORECASE):
        return "EPSG:4326"
    m = _ODM_UTM.match(raw)
    if m:
        zone = int(m.group(1))
        if not 1 <= zone <= 60:
            raise CrsTextError(f"UTM zone {zone} in {raw!r} is not 1..60")
        south = (m.group(2) or "N").upper() == "S"
        return f"EPSG:{(32700 if south else 32600) + zone}"
    try:
        crs = CRS.from_user_input(raw)
    except (CRSError, TypeError, ValueError) as exc:
        raise CrsTextError(f"{raw[:80]!r} is not a CRS pyproj knows ({exc})") from exc
    code = crs.to_epsg(min_confidence=70)
    return f"EPSG:{code}" if code else crs.to_string()


def crs_kind(crs: str) -> str:
    """``"projected"``, ``"geographic"`` or ``"other"`` for a normalised CRS string."""
    c = CRS.from_user_input(crs)
    if c.is_projected:
        return "projected"
    if c.is_geographic:
        return "geographic"
    return "other"
