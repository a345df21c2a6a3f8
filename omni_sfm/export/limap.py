"""The 3D lines in LIMAP's line-track layout, beside the COLMAP model (``limap``).

LIMAP (https://github.com/cvg/limap) keeps a reconstruction's lines as line tracks:
``finaltracks/track_<k>.txt`` (``limap.base.LineTrack.Write``/``Read``: the 3D segment's two
endpoints, the counts of supporting 2D lines and images, ``image_id_list``, ``line_id_list`` and
``line2d_list``, then ``END``) and the same tracks in one file, ``alltracks.txt``
(``limap.util.io.save_txt_linetracks``). Image ids are those of the COLMAP model written beside
them (``sparse/``, :mod:`omni_sfm.export.colmap`), the 2D segments are the projections of the
3D segment's endpoints by the exported COLMAP camera (COLMAP's pixel convention) in each image
whose valid region both endpoints project into and where COLMAP's model projects them too (no
occlusion test; a line of an omnidirectional image is a curve, of which the two ends are
given), and the line id is the track's number. A rig camera's images are its lenses' (the
COLMAP rig model's ``lensK/NAME``), each lens projecting the segments at its own pose.

LIMAP has no file of parallel families; ``line_families.json`` (omni-sfm's) lists each family's
direction and its tracks, in the same world.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.fileio import atomic_write_text, dumps_json
from omni_sfm.folders import ExportFolder
from omni_sfm.lines3d import LineSegments3D
from omni_sfm.poses import Trajectory

TRACKS_DIR = ExportFolder.LIMAP_TRACKS
ALLTRACKS_FILE = ExportFolder.LIMAP_ALLTRACKS
FAMILIES_FILE = ExportFolder.LIMAP_FAMILIES


def _project(camera: CameraModel, traj: Trajectory, x: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP pixels ``(N, L, 2)`` of world points ``x (L, 3)`` in every pose, as the exported
    COLMAP camera projects them, and ``(N, L)`` bool: in the camera's valid region (and
    projected by COLMAP's model too)."""
    export = camera.colmap_export()
    rays = np.einsum("nji,nlj->nli", traj.rotations, x[None] - traj.positions[:, None])
    flat = rays.reshape(-1, 3)
    uv = camera.pixels_from_rays(flat)
    ok = camera.in_image(uv)
    valid = camera.valid_mask()
    iu = np.clip(np.rint(np.nan_to_num(uv[:, 0])).astype(int), 0, camera.width - 1)
    iv = np.clip(np.rint(np.nan_to_num(uv[:, 1])).astype(int), 0, camera.height - 1)
    ok &= valid[iv, iu]
    uv_colmap = np.full((len(flat), 2), np.nan)
    if ok.any():
        uv_colmap[ok] = np.asarray(export.camera.img_from_cam(export.rays_to_colmap(flat[ok])))
    ok &= np.isfinite(uv_colmap).all(axis=1)
    return uv_colmap.reshape(*rays.shape[:2], 2), ok.reshape(rays.shape[:2])


def line_tracks(camera: CameraModel, traj: Trajectory, lines: LineSegments3D,
                image_ids: Sequence[int] | None = None,
                more: Sequence[tuple[CameraModel, Trajectory, Sequence[int]]] = ()
                ) -> list[dict[str, Any]]:
    """Per segment: ``line`` ``(2, 3)``, ``image_ids`` (the COLMAP image id of each pose,
    ``image_ids[k]``, 0: none; default ``k + 1``) and ``line2d`` ``(M, 4)``: COLMAP pixels of
    the two ends in each supporting image. ``more``: further cameras (the other lenses of a
    rig: each its model, its poses world_from_lens and its images' ids), whose supporting
    images follow the first camera's."""
    ids = np.arange(1, len(traj) + 1) if image_ids is None else np.asarray(image_ids, int)
    views = [(camera, traj, ids)] + [(c, t, np.asarray(i, int)) for c, t, i in more]
    proj = [(*_project(c, t, lines.starts), *_project(c, t, lines.ends), i) for c, t, i in views]
    out = []
    for n in range(len(lines)):
        image_list: list[int] = []
        segs = []
        for uv_s, ok_s, uv_e, ok_e, i in proj:
            rows = np.flatnonzero(ok_s[:, n] & ok_e[:, n] & (i > 0))
            image_list += i[rows].tolist()
            segs.append(np.hstack([uv_s[rows, n], uv_e[rows, n]]))
        out.append({"line": np.stack([lines.starts[n], lines.ends[n]]),
                    "image_ids": image_list, "line2d": np.vstack(segs)})
    return out


def track_text(track: dict[str, Any], line_id: int) -> str:
    """``LineTrack::Write``'s text of one track."""
    f = "{:.10f}".format
    ids = track["image_ids"]
    rows = [" ".join(f(x) for x in track["line"].ravel()) + " ",
            f"{len(ids)} {len(set(ids))}",
            "image_id_list " + "".join(f"{i} " for i in ids),
            "line_id_list " + "".join(f"{line_id} " for _ in ids),
            "line2d_list"]
    rows += [" ".join(f(x) for x in seg) + " " for seg in track["line2d"]]
    rows.append("END")
    return "\n".join(rows) + "\n"


def alltracks_text(tracks: list[dict[str, Any]]) -> str:
    """``save_txt_linetracks``'s text of all tracks."""
    out = [f"{len(tracks)}"]
    for k, t in enumerate(tracks):
        ids = t["image_ids"]
        out.append(f"{k} {len(ids)} {len(set(ids))}")
        out += [" ".join(f"{x:.10f}" for x in p) for p in t["line"]]
        out.append("".join(f"{i} " for i in ids))
        out.append("".join(f"{k} " for _ in ids))
    return "\n".join(out) + "\n"


def write_limap_tracks(directory: Path, camera: CameraModel, traj: Trajectory,
                       lines: LineSegments3D, image_ids: Sequence[int] | None = None,
                       more: Sequence[tuple[CameraModel, Trajectory, Sequence[int]]] = ()
                       ) -> dict[str, Any]:
    """Write ``finaltracks/``, ``alltracks.txt`` and ``line_families.json`` in ``directory``
    (poses and lines in the same world; ``more``: :func:`line_tracks`); returns counts for the
    report."""
    directory = Path(directory)
    tracks = line_tracks(camera, traj, lines, image_ids, more)
    (directory / TRACKS_DIR).mkdir(parents=True, exist_ok=True)
    for k, t in enumerate(tracks):
        (directory / TRACKS_DIR / f"track_{k}.txt").write_text(track_text(t, k), encoding="utf-8")
    atomic_write_text(directory / ALLTRACKS_FILE, alltracks_text(tracks))
    fams = [{"id": g, "direction": d.tolist(),
             "tracks": np.flatnonzero(lines.groups == g).tolist()}
            for g, d in enumerate(lines.group_directions)]
    atomic_write_text(directory / FAMILIES_FILE, dumps_json(
        {"frame": lines.frame, "up": None if lines.up is None else np.asarray(lines.up).tolist(),
         "note": "family 0 is the parallel family the poses were estimated with; 'tracks' are "
                 f"the numbers k of {TRACKS_DIR}/track_k.txt",
         "families": fams}))
    return {"tracks": len(tracks), "supported": int(sum(bool(t["image_ids"]) for t in tracks)),
            "families": len(fams)}


def read_track(path: Path) -> dict[str, Any]:
    """Read one ``track_<k>.txt`` as ``LineTrack::Read`` does (for tests)."""
    tok = Path(path).read_text(encoding="utf-8").split()
    line = np.asarray(tok[:6], float).reshape(2, 3)
    n_lines, n_images = int(tok[6]), int(tok[7])
    assert tok[8] == "image_id_list"
    ids = [int(x) for x in tok[9:9 + n_lines]]
    p = 9 + n_lines
    assert tok[p] == "line_id_list"
    line_ids = [int(x) for x in tok[p + 1:p + 1 + n_lines]]
    p += 1 + n_lines
    assert tok[p] == "line2d_list"
    segs = np.asarray(tok[p + 1:p + 1 + 4 * n_lines], float).reshape(-1, 4)
    assert tok[p + 1 + 4 * n_lines] == "END"
    return {"line": line, "n_images": n_images, "image_ids": ids, "line_ids": line_ids,
            "line2d": segs}
