"""Straight lines in omnidirectional images: extraction, tracking, and the tracks artifact."""

from typing import Any

from omni_sfm.lines.tracks import LineTracks, make_tracks, read_tracks, write_tracks

# the front end pulls in OpenCV and SciPy: imported on first use, not with the package
_LAZY = {
    "ExtractedLines": "omni_sfm.lines.extract",
    "ExtractionOptions": "omni_sfm.lines.extract",
    "LineExtractor": "omni_sfm.lines.extract",
    "extract_lines": "omni_sfm.lines.extract",
    "LineTracker": "omni_sfm.lines.track",
    "TrackingOptions": "omni_sfm.lines.track",
    "FrontEndOptions": "omni_sfm.lines.frontend",
    "FrontEndResult": "omni_sfm.lines.frontend",
    "track_lines": "omni_sfm.lines.frontend",
    "write_debug_view": "omni_sfm.lines.debug",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["LineTracks", "make_tracks", "read_tracks", "write_tracks", *_LAZY]
