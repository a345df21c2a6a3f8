"""The output folder of ``omni-sfm track``, written as the poses come (docs/track.md)."""

from __future__ import annotations

import json
from pathlib import Path
from types import TracebackType
from typing import IO

from omni_sfm.estimate.online import TrackedPose, poses_trajectory
from omni_sfm.estimate.pipeline import SEGMENT_FILE
from omni_sfm.folders import TrackFolder
from omni_sfm.poses import TUM_HEADER

FRAMES_FILE = TrackFolder.FRAMES
"""Per-frame results of ``omni-sfm track``: one :meth:`TrackedPose.to_json` line per frame."""


class TrackOutput:
    """The output folder of ``omni-sfm track``, written as the poses come (a context manager).

    :meth:`write` appends a frame's pose (and the start's poses it brings) to
    ``trajectory.tum`` (the first start's world) or ``trajectory_segment_<k>.tum`` (the world
    of the ``k``-th restart), and its :meth:`TrackedPose.to_json` line to ``frames.jsonl``;
    each file is flushed after every frame, so a reader (or a crash) sees every frame so far.
    Earlier runs' files of these names are replaced.
    """

    def __init__(self, directory: Path | str) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        for old in self.directory.glob(SEGMENT_FILE.format("*")):
            old.unlink()
        self._files: dict[int, IO[str]] = {}
        self._frames = open(self.directory / FRAMES_FILE, "w", encoding="utf-8")  # noqa: SIM115
        self._trajectory(0)  # trajectory.tum exists (header only) until the first pose
        self.poses = 0

    def path(self, world: int) -> Path:
        """The trajectory file of ``world``."""
        name = TrackFolder.TRAJECTORY if world == 0 else SEGMENT_FILE.format(world)
        return self.directory / name

    def _trajectory(self, world: int) -> IO[str]:
        if world not in self._files:
            f = open(self.path(world), "w", encoding="utf-8")  # noqa: SIM115
            f.write(TUM_HEADER)
            f.flush()
            self._files[world] = f
        return self._files[world]

    def write(self, pose: TrackedPose) -> None:
        """Append ``pose`` (see the class docstring) and flush."""
        traj = poses_trajectory([pose])
        if len(traj):
            f = self._trajectory(pose.world)
            f.write(traj.tum_rows())
            f.flush()
            self.poses += len(traj)
        self._frames.write(json.dumps(pose.to_json()) + "\n")
        self._frames.flush()

    def close(self) -> None:
        for f in (*self._files.values(), self._frames):
            f.close()

    def __enter__(self) -> TrackOutput:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
