"""Spherical-video metadata of an MP4 / MOV file, read from its box tree (the video is not
decoded and its media data is never read).

Two schemes are read, as Google's spatial-media tools write them and 360 cameras record them:

- Spherical Video V2: a ``sv3d`` box in the video track's sample entry
  (``moov/trak/mdia/minf/stbl/stsd/<avc1|hvc1|...>/sv3d``) holding ``proj`` with the projection
  box (``equi``: equirectangular, with four crop bounds; ``cbmp``: cube map; ``mshp``: mesh),
  and beside it an optional ``st3d`` box (stereo mode: 0 mono, 1 top-bottom, 2 left-right);
- Spherical Video V1: a ``uuid`` box ``ffcc8263-f855-4a93-8814-587a02521fdd`` in the video
  track (``moov/trak/uuid``) holding XMP text with ``GSpherical:Spherical`` true,
  ``GSpherical:ProjectionType`` (``equirectangular``), ``GSpherical:StereoMode`` and the crop
  (``CroppedAreaImageWidthPixels`` ... ``FullPanoHeightPixels``).

:func:`spherical_metadata` returns what it finds as :class:`SphericalMetadata`, or None for a
file that is not an MP4 box tree or carries neither scheme.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

SPHERICAL_V1_UUID = bytes.fromhex("ffcc8263f8554a938814587a02521fdd")
"""The 16-byte identifier of the V1 spherical XMP ``uuid`` box."""

CONTAINERS = frozenset({b"moov", b"trak", b"mdia", b"minf", b"stbl", b"sv3d", b"proj"})
"""Boxes whose payload is a list of boxes, followed on the way to the metadata."""

VISUAL_SAMPLE_ENTRY_BYTES = 78
"""Bytes of a visual sample entry's fixed fields (ISO 14496-12 VisualSampleEntry) before its
child boxes (``avcC``, ``pasp``, ``sv3d``, ``st3d``, ...)."""

MAX_DEPTH = 12
MAX_PAYLOAD = 1 << 20
"""Largest metadata box read into memory (the XMP of a V1 ``uuid`` box is a few hundred bytes)."""

STEREO_V2 = {0: "mono", 1: "top-bottom", 2: "left-right", 3: "stereo-custom"}
PROJECTION_V2 = {b"equi": "equirectangular", b"cbmp": "cubemap", b"mshp": "mesh"}


@dataclass(frozen=True)
class SphericalMetadata:
    """What a file's spherical-video metadata says about its video track."""

    scheme: str
    """``"Spherical Video V2 (sv3d)"`` or ``"Spherical Video V1 (XMP)"``."""
    projection: str
    """``equirectangular``, ``cubemap``, ``mesh`` or the V1 ``ProjectionType`` text."""
    stereo: str = "mono"
    """``mono``, ``top-bottom``, ``left-right`` (or the file's own word)."""
    cropped: bool = False
    """The frame is only part of the sphere (V2 ``equi`` bounds or a V1 cropped area)."""

    @property
    def full_equirectangular(self) -> bool:
        """One eye's whole sphere as one equirectangular frame (what omni-sfm reads)."""
        return self.projection == "equirectangular" and self.stereo == "mono" \
            and not self.cropped

    def describe(self) -> str:
        """One line: scheme, projection, stereo mode and crop."""
        parts = [self.projection]
        if self.stereo != "mono":
            parts.append(f"stereo {self.stereo}")
        if self.cropped:
            parts.append("cropped")
        return f"{self.scheme}: {', '.join(parts)}"


def _boxes(f: BinaryIO, start: int, end: int) -> Iterator[tuple[bytes, int, int]]:
    """``(type, payload start, box end)`` of the boxes in ``[start, end)`` of the file; stops at
    the first malformed header (a size that is too small or runs past ``end``)."""
    pos = start
    while pos + 8 <= end:
        f.seek(pos)
        head = f.read(8)
        if len(head) < 8:
            return
        size, kind = struct.unpack(">I4s", head)
        payload = pos + 8
        if size == 1:  # 64-bit size follows the type
            ext = f.read(8)
            if len(ext) < 8:
                return
            size = struct.unpack(">Q", ext)[0]
            payload += 8
        elif size == 0:  # to the end of the enclosing box (or file)
            size = end - pos
        if size < payload - pos or pos + size > end:
            return
        yield kind, payload, pos + size
        pos += size


def _read(f: BinaryIO, start: int, end: int) -> bytes:
    f.seek(start)
    return f.read(min(end - start, MAX_PAYLOAD))


def _handler(f: BinaryIO, start: int, end: int) -> bytes | None:
    """The handler type (``vide``, ``soun``, ...) of an ``mdia`` box's ``hdlr``."""
    for kind, p, e in _boxes(f, start, end):
        if kind == b"hdlr":
            data = _read(f, p, e)
            return data[8:12] if len(data) >= 12 else None
    return None


def _v2(f: BinaryIO, start: int, end: int) -> SphericalMetadata | None:
    """The ``sv3d`` / ``st3d`` children of a visual sample entry (payload ``[start, end)``)."""
    projection: str | None = None
    cropped = False
    stereo = "mono"
    for kind, p, e in _boxes(f, start + VISUAL_SAMPLE_ENTRY_BYTES, end):
        if kind == b"st3d":
            data = _read(f, p, e)
            if len(data) >= 5:
                stereo = STEREO_V2.get(data[4], f"mode {data[4]}")
        elif kind == b"sv3d":
            for k2, p2, e2 in _boxes(f, p, e):
                if k2 != b"proj":
                    continue
                for k3, p3, e3 in _boxes(f, p2, e2):
                    if k3 in PROJECTION_V2:
                        projection = PROJECTION_V2[k3]
                        if k3 == b"equi":
                            data = _read(f, p3, e3)
                            bounds = struct.unpack(">4I", data[4:20]) if len(data) >= 20 \
                                else (0, 0, 0, 0)
                            cropped = any(bounds)
            if projection is None:
                projection = "unknown (sv3d without a projection box)"
    if projection is None:
        return None
    return SphericalMetadata("Spherical Video V2 (sv3d)", projection, stereo, cropped)


def _xmp_value(text: str, tag: str) -> str | None:
    """A ``GSpherical:tag`` value, written as an element or as an attribute."""
    m = re.search(rf"GSpherical:{tag}\s*(?:>\s*([^<]*?)\s*<|=\s*\"([^\"]*)\")", text)
    return None if m is None else (m.group(1) if m.group(1) is not None else m.group(2))


def _v1(data: bytes) -> SphericalMetadata | None:
    """The V1 XMP of a ``uuid`` box payload (after the 16-byte identifier)."""
    text = data.decode("utf-8", errors="replace")
    if (_xmp_value(text, "Spherical") or "").strip().lower() != "true":
        return None
    projection = (_xmp_value(text, "ProjectionType") or "equirectangular").strip().lower()
    stereo = (_xmp_value(text, "StereoMode") or "mono").strip().lower()
    crop = [_xmp_value(text, t) for t in ("CroppedAreaImageWidthPixels",
                                           "CroppedAreaImageHeightPixels",
                                           "FullPanoWidthPixels", "FullPanoHeightPixels",
                                           "CroppedAreaLeftPixels", "CroppedAreaTopPixels")]
    cropped = False
    if all(c is not None and c.strip().isdigit() for c in crop):
        cw, ch, fw, fh, left, top = (int(str(c)) for c in crop)
        cropped = (cw, ch, left, top) != (fw, fh, 0, 0)
    return SphericalMetadata("Spherical Video V1 (XMP)", projection, stereo, cropped)


def _walk(f: BinaryIO, start: int, end: int, depth: int,
          video: bool) -> Iterator[SphericalMetadata]:
    for kind, p, e in _boxes(f, start, end):
        if kind == b"uuid":
            data = _read(f, p, e)
            if data[:16] == SPHERICAL_V1_UUID:
                md = _v1(data[16:])
                if md is not None:
                    yield md
        elif kind == b"mdia" and depth < MAX_DEPTH:
            is_video = _handler(f, p, e) == b"vide"
            yield from _walk(f, p, e, depth + 1, is_video)
        elif kind == b"stsd" and video:
            # full box header (4) and entry count (4), then one sample entry per format
            for _, p2, e2 in _boxes(f, p + 8, e):
                md = _v2(f, p2, e2)
                if md is not None:
                    yield md
        elif kind in CONTAINERS and depth < MAX_DEPTH:
            yield from _walk(f, p, e, depth + 1, video)


def spherical_metadata(path: Path | str) -> SphericalMetadata | None:
    """The spherical-video metadata of an MP4 / MOV file's video track (V2 ``sv3d`` first, then
    V1 XMP), or None: not such a file, or no metadata. Reads box headers and the few small
    metadata boxes only; never raises for a malformed file (what cannot be parsed is absent)."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            size = path.stat().st_size
            found = list(_walk(f, 0, size, 0, False))
    except OSError:
        return None
    v2 = [m for m in found if m.scheme.startswith("Spherical Video V2")]
    first = v2 or found
    return first[0] if first else None
