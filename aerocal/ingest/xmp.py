"""XMP packets: find them (JPEG APP1, TIFF tag 700) and flatten their simple properties.

An XMP packet is RDF/XML. Simple properties appear either as attributes of ``rdf:Description``
(DJI writes ``drone-dji:GpsLatitude="+51.3665532"``) or as child elements with text (senseFly writes
``<sensefly:Latitude>41.0346708</sensefly:Latitude>``); both are returned as ``{"prefix:Name": text}``.
Prefixes are fixed by namespace URI (:data:`KNOWN_NAMESPACES`) rather than taken from the document,
so a file that binds another prefix to the same namespace reads the same. Arrays (``rdf:Seq``,
``rdf:Bag``, ``rdf:Alt``) are joined with ``"; "``. Parsing uses :mod:`defusedxml` (no entity
expansion, no external entities).

Kept as our own flattening: Pillow's ``Image.getxmp()`` (also on defusedxml) drops the namespace URIs and
keeps local names only, so DJI's ``drone-dji:GpsLatitude`` cannot be told from another vendor's
``GpsLatitude`` nor ``tiff:Make`` from ``drone-dji:Make``; it returns seneca's two ``rdf:Description``
elements as a list and DJI's ``rdf:Seq`` values as nested dicts. tifffile returns the packet as bytes.
"""

from __future__ import annotations

import re
from xml.etree.ElementTree import Element

from defusedxml import ElementTree as SafeET

XMP_APP1_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"
RDF = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
MAX_PACKET_BYTES = 4 * 1024 * 1024

#: namespace URI prefix -> the prefix ingest uses for its properties
KNOWN_NAMESPACES: dict[str, str] = {
    "http://www.dji.com/drone-dji/": "drone-dji",
    "http://ns.sensefly.com/sensefly/": "sensefly",
    "http://www.parrot.com/drone-parrot/": "drone-parrot",
    "http://ns.adobe.com/xap/1.0/mm/": "xmpMM",
    "http://ns.adobe.com/xap/1.0/": "xmp",
    "http://ns.adobe.com/exif/1.0/aux/": "aux",
    "http://ns.adobe.com/exif/1.0/": "exif",
    "http://ns.adobe.com/tiff/1.0/": "tiff",
    "http://ns.adobe.com/camera-raw-settings/1.0/": "crs",
    "http://purl.org/dc/elements/1.1/": "dc",
    "http://ns.google.com/photos/1.0/panorama/": "GPano",
    "http://pix4d.com/camera/1.0/": "Camera",
    "http://www.dji.com/FLIR/": "FLIR",  # DJI Zenmuse XT/XT2: CentralTemperature, BandName, ...
    "http://ns.flir.com/xmp/": "FLIR",  # FLIR's own cameras (Duo Pro R, Vue Pro R)
}

_QNAME = re.compile(r"^\{([^}]*)\}(.+)$")


class XmpError(ValueError):
    """The packet is not well-formed XML or not XMP."""


def packet_from_app1(payload: bytes) -> bytes | None:
    """The XMP packet of a JPEG APP1 payload, or ``None`` if this APP1 is not standard XMP."""
    if payload.startswith(XMP_APP1_HEADER):
        return payload[len(XMP_APP1_HEADER) :]
    return None


def _prefix(uri: str) -> str:
    for known, prefix in KNOWN_NAMESPACES.items():
        if uri.startswith(known):
            return prefix
    return uri


def _key(qname: str) -> str | None:
    m = _QNAME.match(qname)
    if not m:
        return qname
    uri, local = m.groups()
    if uri == RDF:
        return None
    return f"{_prefix(uri)}:{local}"


def parse_xmp(packet: bytes) -> dict[str, str]:
    """Flatten the simple properties of an XMP packet; raise :class:`XmpError` if it is not XML."""
    if len(packet) > MAX_PACKET_BYTES:
        raise XmpError(f"XMP packet of {len(packet)} bytes exceeds {MAX_PACKET_BYTES}")
    start = packet.find(b"<x:xmpmeta")
    end = packet.rfind(b"</x:xmpmeta>")
    if start >= 0 and end > start:
        xml = packet[start : end + len(b"</x:xmpmeta>")]
    else:  # a bare rdf:RDF packet
        start = packet.find(b"<rdf:RDF")
        end = packet.rfind(b"</rdf:RDF>")
        if start < 0 or end < start:
            raise XmpError("no <x:xmpmeta> or <rdf:RDF> element in the XMP packet")
        xml = packet[start : end + len(b"</rdf:RDF>")]
    try:
        root = SafeET.fromstring(xml)
    except Exception as exc:  # ParseError, defusedxml's EntitiesForbidden and friends
        raise XmpError(f"XMP packet is not well-formed XML ({type(exc).__name__}: {exc})") from exc
    out: dict[str, str] = {}
    for desc in root.iter(f"{{{RDF}}}Description"):
        for qname, value in desc.attrib.items():
            key = _key(qname)
            if key is not None:
                out.setdefault(key, value.strip())
        for child in desc:
            key = _key(child.tag)
            if key is None:
                continue
            value = _element_text(child)
            if value is not None:
                out.setdefault(key, value)
    return out


def _element_text(elem: Element) -> str | None:
    if len(elem) == 0:
        return (elem.text or "").strip()
    items = [(li.text or "").strip() for li in elem.iter(f"{{{RDF}}}li") if len(li) == 0]
    if items:
        return "; ".join(items)
    res = elem.attrib.get(f"{{{RDF}}}resource")
    return res.strip() if res else None
