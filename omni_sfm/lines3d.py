"""3D line segments and their file, ``lines3d.json`` (docs/formats.md, docs/rendering.md).

One artifact, one class: the renderer writes the true segments of a scene, ``init`` the
estimated ones, ``refine`` and ``dense`` carry them forward (``dense`` in its output units) and
``view`` draws them; all of them go through :class:`LineSegments3D` and
:func:`read_lines3d` / :func:`write_lines3d`. Below every stage: any stage may import it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text, dumps_json, read_json
from omni_sfm.geometry import FloatArray


@dataclass(frozen=True)
class LineSegments3D:
    """Straight 3D line segments (world frame; metres for a scene, pose units for estimates).

    Attributes:
        starts: ``(L, 3)`` first endpoint of each segment.
        ends: ``(L, 3)`` second endpoint.
        groups: ``(L,)`` int direction group; segments of one group are parallel (group 0: the
            most populated, for estimates the parallel family).
        group_directions: ``(G, 3)`` unit direction of each group (sign arbitrary).
        kinds: ``L`` names of what each segment is (``"door_frame"``, ``"estimated"``...).
        track_ids: ``(L,)`` int line track of each estimated segment, or None (true lines).
        frame: what the coordinates are, in words (written to the file).
        up: ``(3,)`` unit up direction in that frame, or None.
    """

    starts: FloatArray
    ends: FloatArray
    groups: np.ndarray
    group_directions: FloatArray
    kinds: tuple[str, ...]
    track_ids: np.ndarray | None = None
    frame: str = "scene frame: metres, +Z up, floor at z=0"
    up: FloatArray | None = field(default=None)

    def __len__(self) -> int:
        return int(self.starts.shape[0])

    @classmethod
    def empty(cls, frame: str = "") -> LineSegments3D:
        """No segments."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64),
                   np.zeros((0, 3)), (), frame=frame)

    @property
    def directions(self) -> FloatArray:
        """``(L, 3)`` unit direction of each segment (start to end)."""
        d = self.ends - self.starts
        return np.asarray(d / np.linalg.norm(d, axis=1, keepdims=True))

    @property
    def lengths(self) -> FloatArray:
        return np.asarray(np.linalg.norm(self.ends - self.starts, axis=1))

    def transformed(self, rotation: FloatArray, translation: FloatArray) -> LineSegments3D:
        """The segments in another frame: ``x' = rotation @ x + translation``."""
        R, t = np.asarray(rotation), np.asarray(translation)
        up = None if self.up is None else R @ self.up
        return replace(self, starts=self.starts @ R.T + t, ends=self.ends @ R.T + t,
                       group_directions=self.group_directions @ R.T, up=up)

    def scaled(self, scale: float) -> LineSegments3D:
        """The endpoints multiplied by ``scale`` (about the origin), e.g. pose units to metres."""
        return replace(self, starts=scale * self.starts, ends=scale * self.ends)

    def to_json(self, frame: str | None = None, up: FloatArray | None = None) -> dict[str, Any]:
        """The ``lines3d.json`` document; ``frame`` and ``up`` override the instance's."""
        frame = self.frame if frame is None else frame
        up = self.up if up is None else up
        counts = np.bincount(self.groups, minlength=len(self.group_directions))
        segments = []
        for i, (s, e, g, k) in enumerate(zip(self.starts, self.ends, self.groups, self.kinds,
                                             strict=True)):
            seg: dict[str, Any] = {"start": s.tolist(), "end": e.tolist(), "group": int(g),
                                   "kind": k}
            if self.track_ids is not None:
                seg["track_id"] = int(self.track_ids[i])
            segments.append(seg)
        return {
            "frame": frame,
            **({"up": np.asarray(up).tolist()} if up is not None else {}),
            "groups": [
                {"id": g, "direction": d.tolist(), "count": int(c)}
                for g, (d, c) in enumerate(zip(self.group_directions, counts, strict=True))
            ],
            "segments": segments,
        }


def write_lines3d(path: Path, lines: LineSegments3D, **kwargs: Any) -> None:
    """Write ``lines`` as ``lines3d.json`` (atomically); ``kwargs`` go to ``to_json``."""
    atomic_write_text(Path(path), dumps_json(lines.to_json(**kwargs)))


def read_lines3d(path: Path) -> LineSegments3D:
    """Read a ``lines3d.json`` file; defects become a one-line :class:`OmniSfmError`."""
    data = read_json(Path(path), "lines3d file")
    try:
        segs = data["segments"]
        starts = np.array([s["start"] for s in segs], dtype=np.float64).reshape(-1, 3)
        ends = np.array([s["end"] for s in segs], dtype=np.float64).reshape(-1, 3)
        groups = np.array([int(s["group"]) for s in segs], dtype=np.int64)
        kinds = tuple(str(s.get("kind", "")) for s in segs)
        tracks = [s.get("track_id") for s in segs]
        track_ids = np.array(tracks, dtype=np.int64) if segs and all(
            t is not None for t in tracks) else None
        dirs = np.array([g["direction"] for g in data["groups"]], dtype=np.float64).reshape(-1, 3)
        up = np.asarray(data["up"], dtype=np.float64) if data.get("up") is not None else None
        frame = str(data.get("frame", ""))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise OmniSfmError(f"{path}: malformed lines3d file: {exc!r}") from None
    if len(groups) and (groups.min() < 0 or groups.max() >= len(dirs)):
        raise OmniSfmError(f"{path}: segment group out of range 0..{len(dirs) - 1}")
    return LineSegments3D(starts, ends, groups, dirs, kinds, track_ids, frame, up)
