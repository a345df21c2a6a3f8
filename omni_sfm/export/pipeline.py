"""``omni-sfm export``: an init, refine or dense folder in the format another tool reads
(docs/formats.md, "Exports").

Formats (:data:`FORMATS`): ``tum`` and ``kitti`` trajectories, ``colmap`` (the folder's COLMAP
model, or one built from its poses, with the frames as COLMAP must see them), ``nerfstudio``
(``transforms.json``), ``limap`` (the 3D lines as LIMAP line tracks beside the COLMAP model)
and ``colmap-rig`` (a COLMAP 4.2 rig of perspective views rendered from the frames). Each
writes its output folder complete or not at all, with its own ``report.json`` that records the
world it is in (:mod:`omni_sfm.export.up`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import write_camera_yaml
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.up import MOUNT_UP_AXIS, UpFrame, find_up, parse_axis
from omni_sfm.fileio import atomic_output_dir, atomic_write_text, dumps_json
from omni_sfm.folders import (
    ExportFolder,
    InitFolder,
    StageFolder,
    images_for,
    manifest_names,
    pose_frame_names,
)
from omni_sfm.geometry import normalize
from omni_sfm.poses import Trajectory
from omni_sfm.reports import (
    ColmapWritten,
    ExportReport,
    ExportWorld,
    ExportWritten,
    NerfstudioWritten,
    RigWritten,
    TrajectoryWritten,
)

FORMATS: dict[str, bool] = {
    "tum": False, "kitti": False, "colmap": False,
    "nerfstudio": True, "limap": True, "colmap-rig": True,
}
"""Every format, and whether it turns the world gravity-up by default (``--up``)."""

SPARSE_DIR = ExportFolder.SPARSE
IMAGES_DIR = ExportFolder.IMAGES
MASKS_DIR = ExportFolder.MASKS
PLY_FILE = ExportFolder.POINTS


@dataclass(frozen=True)
class ExportOptions:
    """What to export.

    Attributes:
        fmt: one of :data:`FORMATS`.
        up: turn the world gravity-up (None: the format's default).
        up_axis: the camera axis that points up (``"-y"``...), None: the model's own.
        views: the perspective views' layout, ``overlapping`` or ``cubemap``
            (:mod:`omni_sfm.export.perspective`).
    """

    fmt: str
    up: bool | None = None
    up_axis: str | None = None
    views: str = "overlapping"

    @property
    def turn_up(self) -> bool:
        return FORMATS[self.fmt] if self.up is None else self.up


class _Source:
    """The folder's poses, camera, lines and frames."""

    def __init__(self, folder: Path, images: Path | None, opts: ExportOptions) -> None:
        self.path = Path(folder)
        if not self.path.is_dir():
            raise OmniSfmError(f"{self.path}: input folder not found")
        owner = StageFolder(self.path)
        if not (owner / owner.TRAJECTORY).is_file():
            raise OmniSfmError(f"{owner / owner.TRAJECTORY}: no trajectory (need an init, refine "
                               "or dense folder)")
        self.owner = owner
        art = owner.load_stage()
        if art.camera is None:
            raise OmniSfmError(f"{owner / owner.CAMERA}: camera file not found")
        self.traj, self.camera, self.lines, self.report = (art.trajectory, art.camera,
                                                           art.lines3d, art.report)
        self.images_arg = images
        if opts.turn_up:
            axis = parse_axis(opts.up_axis) if opts.up_axis else None
            self.up = find_up(self.traj, self.camera, self.lines, self.report, axis,
                              _line_tracks(self.path))
        else:
            self.up = UpFrame.identity()
        self.traj_out = self.up.trajectory(self.traj)
        self.lines_out = self.up.lines(self.lines) if self.lines is not None else None
        self._frames: Any = None
        self._names: list[str] | None = None

    def frames(self, required: bool) -> tuple[Any, list[str]] | None:
        """``(FrameStore, name of every pose's frame)``, or None when not ``required`` and the
        folder records no frames."""
        if self._frames is None:
            from omni_sfm.frames import FrameStore

            try:
                src = images_for(self.path, self.images_arg)
            except OmniSfmError:
                if required:
                    raise
                return None
            self._frames = FrameStore(src)
            self._names = pose_frame_names(self.path, self.traj, self._frames)
        assert self._names is not None
        return self._frames, self._names

    def read(self, store: Any, name: str) -> np.ndarray:
        """Frame ``name``, BGR, checked against the camera's size."""
        img = store.read(name)
        if img.shape[:2] != (self.camera.height, self.camera.width):
            raise OmniSfmError(f"{store.where(name)}: image is {img.shape[1]}x{img.shape[0]} px, "
                               f"the camera is {self.camera.width}x{self.camera.height}")
        return np.asarray(img)

    def default_names(self) -> list[str]:
        """Image names without frames: ``colmap.json``'s, else the timestamps as
        ``NNNNNN.png``."""
        names = manifest_names(self.path, len(self.traj))
        if names is not None:
            return names
        return [f"{int(round(t)):06d}.png" for t in self.traj.timestamps]

    def up_in_cam(self) -> np.ndarray:
        """The vertical in the camera frame (mean over the frames), for laying out views."""
        if self.up.vertical is not None:
            return normalize(np.einsum("nji,j->ni", self.traj.rotations,
                                       self.up.vertical).mean(axis=0))
        axis = MOUNT_UP_AXIS.get(self.camera.model, (0.0, -1.0, 0.0))
        return np.asarray(axis, float)


def _line_tracks(folder: Path, hops: int = 3) -> Any:
    """The ``tracks.json`` the folder's poses were estimated from: the folder's own, else that
    of the folder its ``report.json`` names as input (``input.init`` of refine, ``input.poses``
    of dense), up to ``hops`` folders back; None when there is none."""
    from omni_sfm.lines.tracks import read_tracks

    for _ in range(hops):
        if (folder / InitFolder.TRACKS).is_file():
            try:
                return read_tracks(folder / InitFolder.TRACKS)
            except OmniSfmError:
                return None
        report = StageFolder(folder).read_stage_report()
        prev = None if report is None else report.previous_folder(folder)
        if prev is None:
            return None
        folder = prev
    return None


def _progress(items: list[Any], desc: str, progress: bool) -> Iterator[Any]:
    if not progress:
        yield from items
        return
    from tqdm import tqdm

    yield from tqdm(items, desc=desc, unit="frame", file=sys.stderr)


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OmniSfmError(f"{path}: OpenCV cannot write this image")


def png_name(name: str) -> str:
    """A frame's image name with the extension ``.png``."""
    from pathlib import PurePosixPath

    return PurePosixPath(name).with_suffix(".png").as_posix()


# --- the formats ----------------------------------------------------------------------------

def _export_trajectory(src: _Source, out: Path, opts: ExportOptions, progress: bool
                       ) -> TrajectoryWritten:
    from omni_sfm.export.trajectories import write_trajectory_export

    return TrajectoryWritten(files=write_trajectory_export(out, src.traj_out, opts.fmt),
                             camera_frame="the camera model's ray frame (docs/cameras.md)")


def _colmap_model(src: _Source, out: Path) -> tuple[Any, list[str], ColmapWritten]:
    """The folder's COLMAP model (``sparse/``, with its points) moved to the export's world, or
    one built from the poses; written to ``out/sparse``."""
    from omni_sfm.cameras import RigCamera
    from omni_sfm.export.colmap import build_reconstruction

    if isinstance(src.camera, RigCamera):
        return _colmap_lens_rig(src, out, src.camera)
    export = src.camera.colmap_export()
    sparse = src.owner / SPARSE_DIR
    rec, model = _folder_model(src)
    frames = src.frames(required=False)
    if rec is None:
        names = frames[1] if frames is not None else src.default_names()
        rec = build_reconstruction(src.camera, src.traj_out, names).reconstruction
        model = "built from the poses (no points)"
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    names = [n for n in (frames[1] if frames is not None else src.default_names())
             if n in by_name]
    if frames is not None:
        centres = np.asarray([by_name[n].projection_center() for n in names])
        rows = {n: k for k, n in enumerate(frames[1])}
        want = src.traj_out.positions[[rows[n] for n in names]]
        tol = 1e-6 * max(1.0, float(np.abs(want).max()))
        if len(names) and not np.allclose(centres, want, atol=tol):
            raise OmniSfmError(f"{sparse}: the model's camera centres differ from "
                               f"{src.owner / src.owner.TRAJECTORY}")
    (out / SPARSE_DIR).mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(out / SPARSE_DIR))
    write_camera_yaml(out / ExportFolder.CAMERA, src.camera)
    return rec, sorted(by_name), ColmapWritten(
        model=model, flip_u=export.flip_u,
        colmap_cam_from_cam=export.colmap_cam_from_cam.tolist(), num_images=rec.num_images(),
        num_points3D=rec.num_points3D())


def _folder_model(src: _Source) -> tuple[Any, str]:
    """The folder's COLMAP model (``sparse/``, with its points) moved to the export's world and
    what it is; ``(None, "")`` when the folder has none."""
    import pycolmap

    sparse = src.owner / SPARSE_DIR
    if not (sparse / "cameras.bin").is_file() and not (sparse / "cameras.txt").is_file():
        return None, ""
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise OmniSfmError(f"{sparse}: cannot read the COLMAP model: {exc}") from None
    R, t = src.up.up_from_world, -src.up.up_from_world @ src.up.origin
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(R), t[:, None]))
    return rec, f"the folder's {SPARSE_DIR}/ ({rec.num_points3D()} points), turned"


def _colmap_lens_rig(src: _Source, out: Path, camera: Any
                     ) -> tuple[Any, list[str], ColmapWritten]:
    """A rig camera's COLMAP rig (:mod:`omni_sfm.export.colmap_lenses`): the folder's model
    (checked against the one the poses give) or the one the poses give, its lens offsets at the
    scale the folder's ``report.json`` records; written to ``out/sparse``. The names are the
    frames the model poses."""
    from omni_sfm.export.colmap import projection_centres
    from omni_sfm.export.colmap_lenses import (
        build_lens_rig,
        lens_image_name,
        rig_metres_per_unit,
        write_rig_config,
    )

    frames = src.frames(required=False)
    all_names = frames[1] if frames is not None else src.default_names()
    built = build_lens_rig(camera, src.traj_out, all_names, rig_metres_per_unit(src.path))
    rec, model = _folder_model(src)
    if rec is None:
        rec, model = built.reconstruction, "built from the poses (no points)"
    else:
        want = projection_centres(built.reconstruction)
        got = projection_centres(rec)
        common = sorted(set(want) & set(got))
        tol = 1e-6 * max(1.0, float(np.abs(src.traj_out.positions).max()))
        if common and not np.allclose([got[n] for n in common], [want[n] for n in common],
                                      atol=tol):
            raise OmniSfmError(f"{src.owner / SPARSE_DIR}: the model's camera centres differ "
                               f"from {src.owner / src.owner.TRAJECTORY} and the rig's lenses")
    posed = {im.name for im in rec.images.values() if im.has_pose}
    names = [n for n in all_names if lens_image_name(0, n) in posed]
    (out / SPARSE_DIR).mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(out / SPARSE_DIR))
    write_rig_config(out, rec)
    write_camera_yaml(out / ExportFolder.CAMERA, camera)
    return rec, names, ColmapWritten(
        model=model, num_images=rec.num_images(), num_points3D=rec.num_points3D(),
        rig={"metres_per_unit": built.metres_per_unit, "lenses": built.lenses.manifest()})


def _export_colmap(src: _Source, out: Path, opts: ExportOptions, progress: bool
                   ) -> ColmapWritten:
    from omni_sfm.cameras import RigCamera
    from omni_sfm.export.colmap import write_colmap_mask

    rec, names, info = _colmap_model(src, out)
    frames = src.frames(required=False)
    if frames is None:
        return replace(info, images="none: the folder records no frames (give --images)")
    store, _ = frames
    if isinstance(src.camera, RigCamera):
        from omni_sfm.export.colmap_lenses import LensExports, lens_image_name, write_lens_masks

        lenses = LensExports.of(src.camera)
        for name in _progress(names, "export", progress):
            for k, img in enumerate(lenses.images(src.read(store, name))):
                _write_png(out / IMAGES_DIR / lens_image_name(k, name), img)
        write_lens_masks(out, lenses)
        return replace(info, images=f"{IMAGES_DIR}/lensK/ ({len(names)} frames, each lens's "
                                    "part as COLMAP sees it)")
    export = src.camera.colmap_export()
    for name in _progress(names, "export", progress):
        _write_png(out / IMAGES_DIR / name, export.image_to_colmap(src.read(store, name)))
    write_colmap_mask(out / ExportFolder.COLMAP_MASK, src.camera)
    return replace(info, images=f"{IMAGES_DIR}/ ({len(names)} frames as COLMAP sees them)")


def _export_limap(src: _Source, out: Path, opts: ExportOptions, progress: bool
                  ) -> ColmapWritten:
    from omni_sfm.export.limap import write_limap_tracks

    if src.lines_out is None or not len(src.lines_out):
        raise OmniSfmError(f"{src.owner / src.owner.LINES3D}: no 3D lines to export for LIMAP")
    from omni_sfm.cameras import RigCamera

    rec, _, info = _colmap_model(src, out)
    # the LIMAP tracks' image ids are the model's: pose row k is image k + 1 when the model was
    # built from the poses or is the init's; a refine model is matched by name
    if not isinstance(src.camera, RigCamera):
        return replace(info, limap=write_limap_tracks(
            out, src.camera, src.traj_out, src.lines_out, image_ids=_image_ids(rec, src)))
    from omni_sfm.export.colmap_lenses import lens_image_name, rig_metres_per_unit

    rig, scale = src.camera, rig_metres_per_unit(src.path)
    lenses = []
    for k, lens in enumerate(rig.lenses):
        lenses.append((lens, src.traj_out.fixed_camera(rig.rig_from_lens_in(k, scale)),
                       _image_ids(rec, src, partial(lens_image_name, k))))
    return replace(info, limap=write_limap_tracks(out, *lenses[0][:2], src.lines_out,
                                                  image_ids=lenses[0][2], more=lenses[1:]))


def _image_ids(rec: Any, src: _Source, image_name: Callable[[str], str] = str) -> list[int]:
    """The model's image id of every pose, by name (pose order; ``image_name``: the model's
    name of a frame's image); 0 where it has none."""
    frames = src.frames(required=False)
    names = frames[1] if frames is not None else src.default_names()
    by_name = {im.name: im.image_id for im in rec.images.values()}
    return [int(by_name.get(image_name(n), 0)) for n in names]


def _export_nerfstudio(src: _Source, out: Path, opts: ExportOptions, progress: bool
                       ) -> NerfstudioWritten:
    from omni_sfm.cameras import RigCamera
    from omni_sfm.export.nerfstudio import (
        TRANSFORMS_FILE,
        camera_intrinsics,
        frame_entry,
        transform_matrices,
        transforms_document,
    )

    fr = src.frames(required=True)
    assert fr is not None
    store, names = fr
    traj = src.traj_out
    intr = None if isinstance(src.camera, RigCamera) else camera_intrinsics(src.camera)
    entries = []
    layout_json: dict[str, Any] | None = None
    if intr is not None:
        c2w = transform_matrices(traj.rotations, traj.positions)
        for k, name in enumerate(_progress(names, "export", progress)):
            rel = f"{IMAGES_DIR}/{png_name(name)}"
            _write_png(out / rel, src.read(store, name))
            entries.append(frame_entry(rel, c2w[k], timestamp=float(traj.timestamps[k])))
        images = f"the frames themselves ({intr['camera_model']})"
    else:
        intr, entries, layout_json = _perspective_views(src, out, opts, store, names,
                                                        progress)
        per = len(entries) // max(len(names), 1)
        images = f"perspective views ({opts.views}: {per} per frame" + (
            f", each lens's in {IMAGES_DIR}/lensK/VIEW/)" if "lenses" in layout_json else ")")
    doc = transforms_document(intr, entries, src.up.matrix() if src.up.vertical is not None
                              else None)
    points, said = _sparse_points(src), None
    if points is not None:
        from omni_sfm.libs import open3d_module

        o3d = open3d_module()
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.up.points(points[0])))
        pcd.colors = o3d.utility.Vector3dVector(points[1])
        if not o3d.io.write_point_cloud(str(out / PLY_FILE), pcd):
            raise OmniSfmError(f"{out / PLY_FILE}: Open3D could not write the points")
        doc["ply_file_path"] = PLY_FILE
        said = f"{PLY_FILE}: {len(points[0])} points of the folder's COLMAP model"
    atomic_write_text(out / TRANSFORMS_FILE, dumps_json(doc))
    return NerfstudioWritten(images=images, views=layout_json, points=said, num_images=len(entries))


@dataclass(frozen=True)
class _ViewSource:
    """One camera whose frames the perspective views are rendered from: a central camera, or
    one lens of a rig (its part of each frame), fixed to the body the poses are of at
    ``body_from_cam`` (``(4, 4)``, the centre in the poses' units)."""

    camera: Any
    body_from_cam: np.ndarray
    prefix: str
    lens: int | None = None



def _view_sources(src: _Source, opts: ExportOptions) -> list[tuple[_ViewSource, Any]]:
    """The central camera, or each lens of a rig at its place in it (its centre
    ``rig_from_lens`` metres from the rig's, the folder's ``rig.metres_per_unit`` to pose
    units: :meth:`~omni_sfm.cameras.rig.RigCamera.rig_from_lens_in`), each with its
    perspective views' layout (:mod:`omni_sfm.export.perspective`) about its own level frame."""
    from omni_sfm.cameras import RigCamera
    from omni_sfm.export.perspective import view_layout

    up = src.up_in_cam()
    if not isinstance(src.camera, RigCamera):
        return [(_ViewSource(src.camera, np.eye(4), ""), view_layout(src.camera, up,
                                                                      opts.views))]
    from omni_sfm.export.colmap_lenses import rig_metres_per_unit

    rig, scale = src.camera, rig_metres_per_unit(src.path)
    return [(_ViewSource(lens, rig.rig_from_lens_in(k, scale), f"lens{k}/", k),
             view_layout(lens, rig.rotations[k].T @ up, opts.views))
            for k, lens in enumerate(rig.lenses)]


def _source_frame(src: _Source, s: _ViewSource, frame: np.ndarray) -> np.ndarray:
    """The camera's own image of a frame: the frame, or the lens's part of it."""
    from omni_sfm.cameras import RigCamera

    if s.lens is None or not isinstance(src.camera, RigCamera):
        return frame
    return np.ascontiguousarray(src.camera.lens_image(frame, s.lens))


def _perspective_views(src: _Source, out: Path, opts: ExportOptions, store: Any,
                       names: list[str], progress: bool
                       ) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, Any]]:
    """nerfstudio's pinhole views rendered from the frames of a camera it has no model of
    (:mod:`omni_sfm.export.perspective`), from each lens of a rig: ``(intrinsics, frame
    entries, the layout's JSON)``. The intrinsics are shared where every lens's views have one
    geometry, else each entry carries its own (nerfstudio reads them per frame then)."""
    from omni_sfm.export.nerfstudio import frame_entry, transform_matrices, view_intrinsics

    sources = _view_sources(src, opts)
    own = [view_intrinsics(g.width, g.height, g.focal, g.cx, g.cy)
           for g in (layout.geometry for _, layout in sources)]
    shared = all(i == own[0] for i in own)
    # nerfstudio takes a mask for every image or for none
    masked = not all(bool(layout.valid.all()) for _, layout in sources)
    poses = [src.traj_out.fixed_camera(s.body_from_cam) for s, _ in sources]
    valid = [s.camera.valid_mask() for s, _ in sources]
    entries = []
    for k, name in enumerate(_progress(names, "export", progress)):
        frame = src.read(store, name)
        for (s, layout), pose, ok_cam, intr in zip(sources, poses, valid, own, strict=True):
            views, ok = layout.render(_source_frame(src, s, frame), ok_cam)
            R = pose.rotations[k][None] @ layout.cam_from_views
            c2w = transform_matrices(R, np.repeat(pose.positions[k][None], len(R), axis=0))
            for v, view in enumerate(layout.names):
                rel = f"{IMAGES_DIR}/{s.prefix}{view}/{png_name(name)}"
                _write_png(out / rel, views[v])
                mask = None
                if masked:
                    mask = f"{MASKS_DIR}/{s.prefix}{view}/{png_name(name)}"
                    _write_png(out / mask, np.where(ok[v], 255, 0).astype(np.uint8))
                extra = {} if shared else {key: value for key, value in intr.items()
                                           if key != "camera_model"}
                entries.append(frame_entry(rel, c2w[v], mask_path=mask,
                                           timestamp=float(src.traj_out.timestamps[k]),
                                           view=f"{s.prefix}{view}", **extra))
    intr_doc = own[0] if shared else {"camera_model": own[0]["camera_model"]}
    if sources[0][0].lens is None:
        return intr_doc, entries, sources[0][1].to_json()
    return intr_doc, entries, {"lenses": [{"lens": s.lens, **layout.to_json()}
                                          for s, layout in sources]}

def _sparse_points(src: _Source) -> tuple[np.ndarray, np.ndarray] | None:
    """``(N, 3)`` points and ``(N, 3)`` RGB in [0, 1] of the folder's COLMAP model (refine's
    triangulated points), or None when it has none."""
    sparse = src.owner / SPARSE_DIR
    if not (sparse / "points3D.bin").is_file():
        return None
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise OmniSfmError(f"{sparse}: cannot read the COLMAP model: {exc}") from None
    if rec.num_points3D() == 0:
        return None
    pts = list(rec.points3D.values())
    return (np.asarray([p.xyz for p in pts], float),
            np.asarray([p.color for p in pts], float) / 255.0)


def _export_colmap_rig(src: _Source, out: Path, opts: ExportOptions, progress: bool
                       ) -> RigWritten:
    from omni_sfm.export.colmap_rig import build_rig_reconstruction, view_image_name

    fr = src.frames(required=True)
    assert fr is not None
    store, names = fr
    sources = _view_sources(src, opts)
    rec = build_rig_reconstruction([layout for _, layout in sources], src.traj_out, names,
                                   np.asarray([s.body_from_cam for s, _ in sources]),
                                   [s.prefix for s, _ in sources])
    (out / SPARSE_DIR).mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(out / SPARSE_DIR))
    valid = [s.camera.valid_mask() for s, _ in sources]
    for name in _progress(names, "export", progress):
        frame = src.read(store, name)
        for (s, layout), ok_cam in zip(sources, valid, strict=True):
            views, ok = layout.render(_source_frame(src, s, frame), ok_cam)
            for v, view in enumerate(layout.names):
                rel = view_image_name(s.prefix + view, name)
                _write_png(out / IMAGES_DIR / rel, views[v])
                if not layout.valid[v].all():
                    # COLMAP's mask of image I is MASK_PATH/I.png (0: no features)
                    _write_png(out / MASKS_DIR / f"{rel}.png",
                               np.where(ok[v], 255, 0).astype(np.uint8))
    rig = sources[0][0].lens is not None
    views_json = sources[0][1].to_json() if not rig else {
        "lenses": [{"lens": s.lens, **layout.to_json()} for s, layout in sources]}
    return RigWritten(num_images=rec.num_images(), num_frames=rec.num_frames(),
                      views=views_json,
                      images=f"{IMAGES_DIR}/{'lensK/' if rig else ''}VIEW/NAME.png",
                      masks=f"{MASKS_DIR}/{'lensK/' if rig else ''}VIEW/NAME.png.png where a "
                            "view is not all covered")

WRITERS: dict[str, Callable[[_Source, Path, ExportOptions, bool], ExportWritten]] = {
    "tum": _export_trajectory, "kitti": _export_trajectory, "colmap": _export_colmap,
    "nerfstudio": _export_nerfstudio, "limap": _export_limap, "colmap-rig": _export_colmap_rig}


def run_export(input_dir: Path, output_dir: Path, options: ExportOptions, *,
               images: Path | None = None, overwrite: bool = False,
               progress: bool = False) -> ExportReport:
    """Export the folder ``input_dir`` as ``options.fmt`` into ``output_dir`` (complete or not
    at all); returns the export's ``report.json``."""
    from omni_sfm import __version__
    from omni_sfm.fileio import stored_path

    if options.fmt not in FORMATS:
        raise OmniSfmError(f"--format must be one of {', '.join(FORMATS)}; got {options.fmt!r}")
    t0 = time.perf_counter()
    src = _Source(Path(input_dir), images, options)
    frames_path = src.images_arg
    with atomic_output_dir(Path(output_dir), overwrite=overwrite,
                           inputs=(Path(input_dir), frames_path)) as tmp:
        written = WRITERS[options.fmt](src, tmp, options, progress)
        report = ExportReport(
            omni_sfm_version=__version__, format=options.fmt,
            input=stored_path(input_dir, output_dir), num_poses=len(src.traj),
            world=src.up.report(),
            camera_model=src.camera.colmap_export().camera.model_name
            if isinstance(written, ColmapWritten) and written.rig is None
            else src.camera.model,
            written=written,
            seconds=round(time.perf_counter() - t0, 3))
        report.write(ExportFolder(tmp) / ExportFolder.REPORT)
    return report


def export_trajectory_of(report: ExportReport | Mapping[str, Any], traj: Trajectory
                         ) -> Trajectory:
    """``traj`` (the input folder's world) in the world an export's ``report`` (or its JSON
    document) records."""
    world = report.world if isinstance(report, ExportReport) else \
        ExportWorld.from_json(report["world"], "world")
    m = np.asarray(world.export_from_world, float)
    R, t = m[:3, :3], m[:3, 3]
    return Trajectory(traj.timestamps.copy(), R[None] @ traj.rotations, traj.positions @ R.T + t)

