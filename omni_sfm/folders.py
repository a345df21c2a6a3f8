"""What every stage's output folder shares, so the stages chain: ``init`` -> ``refine`` ->
``dense`` -> ``view``.

Each folder holds the poses (``trajectory.tum``) and carries forward what a later stage needs
without being told again: the camera (``camera.yaml``), the user's mask (``mask.png``, when one
was given), the estimated 3D lines (``lines3d.json``) and where the frames are (the image folder
or video, recorded in ``report.json`` under ``input.images``). Paths are recorded so that the
folder can be moved (:func:`omni_sfm.fileio.stored_path`): relative to the folder when inside
it, absolute otherwise. A stage reads its input folder with :func:`recorded_images` and copies
the carried files with :func:`carry_forward`.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import read_json, resolve_stored

TRAJECTORY_FILE = "trajectory.tum"
CAMERA_FILE = "camera.yaml"
LINES_FILE = "lines3d.json"
USER_MASK_FILE = "mask.png"
REPORT_FILE = "report.json"

CARRIED_FILES = (CAMERA_FILE, USER_MASK_FILE, LINES_FILE)
"""Files a stage copies from its input folder when it does not write its own."""


def recorded_images(folder: Path | str) -> Path | None:
    """The image folder or video that ``folder`` (an init, refine or dense output) was made
    from, as recorded in its ``report.json``, or None when it records none."""
    folder = Path(folder)
    report = folder / REPORT_FILE
    if not report.is_file():
        return None
    doc = read_json(report, "report")
    inp = doc.get("input") if isinstance(doc, dict) else None
    images = inp.get("images") if isinstance(inp, dict) else None
    return resolve_stored(images, folder) if isinstance(images, str) and images else None


def images_for(folder: Path | str, images: Path | str | None) -> Path:
    """``images`` if given, else the frames ``folder`` records (one-line error if neither)."""
    if images is not None:
        return Path(images)
    found = recorded_images(folder)
    if found is None:
        raise OmniSfmError(f"{folder}: the folder does not record its frames (give --images "
                           "PATH, the image folder or video it was made from)")
    if not found.exists():
        raise OmniSfmError(f"{found}: the frames recorded in {Path(folder) / REPORT_FILE} are "
                           "gone (give --images PATH)")
    return found


def carry_forward(src: Path | str, dst: Path | str, names: tuple[str, ...] = CARRIED_FILES
                  ) -> list[str]:
    """Copy those of ``names`` that ``src`` has and ``dst`` does not into ``dst``; returns the
    names copied."""
    src, dst = Path(src), Path(dst)
    copied = []
    for name in names:
        if (src / name).is_file() and not (dst / name).exists():
            shutil.copyfile(src / name, dst / name)
            copied.append(name)
    return copied
