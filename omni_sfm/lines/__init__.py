"""Straight lines in omnidirectional images: extraction, tracking, and the tracks artifact."""

from omni_sfm.lines.tracks import LineTracks, make_tracks, read_tracks, write_tracks

__all__ = ["LineTracks", "make_tracks", "read_tracks", "write_tracks"]
