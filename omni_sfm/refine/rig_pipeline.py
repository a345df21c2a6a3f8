"""``omni-sfm refine`` of a rig camera (raw dual-fisheye frames, a camchain; docs/colmap.md,
"Refining a rig"): COLMAP's rig on the line-based poses.

1. images: each lens's part of every posed frame (``images_colmap/lensK/NAME``) and each lens's
   mask (:func:`omni_sfm.refine.rig.write_lens_images`);
2. features and matching: SIFT in every lens image with the lens's exact camera, the rig applied
   to the database (the lens images of one frame are one COLMAP frame, the lenses at their
   offsets in metres), COLMAP's sequential matching (:func:`omni_sfm.refine.rig.rig_database`);
3. triangulation: the frames posed from the init in metres (its ``rig.metres_per_unit``, rough or
   not), ``pycolmap.triangulate_points`` on them, poses, intrinsics and lens offsets held;
4. adjustment: COLMAP's bundle adjustment in rounds with outlier filtering (as ``--adjustment
   colmap``), frames and points free, intrinsics and lens offsets held; the gauge is the
   best-observed frame held, the scale the lens baseline's (no position priors: they would hold
   the init's scale);
5. acceptance: as for one camera (``_accept``): the adjusted frames mapped onto the input's world
   and units by a similarity, a frame keeps its input pose unless its lens images hold enough
   observations and its change is plausible. The similarity's scale is the refined metric scale
   (``report.json`` ``rig``), which ``dense`` and the exports take.

Frames without an input pose are not registered (the mapper takes one camera); the joint
adjustment with the lines neither: the report says both.
"""

from __future__ import annotations

import shutil
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import RigCamera, write_camera_yaml
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap_lenses import (
    build_lens_rig,
    lens_image_name,
    rig_manifest,
    rig_metres_per_unit,
)
from omni_sfm.fileio import atomic_output_dir, atomic_write_text, dumps_json, stored_path
from omni_sfm.folders import InitFolder, RefineFolder, carry_forward, pose_frame_names
from omni_sfm.frames import FrameStore
from omni_sfm.libs import library_logging
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.refine.pipeline import (
    Acceptance,
    RefineOptions,
    RefineResult,
    _bundle_adjust,
    _frame_errors,
    _observations,
    _Sections,
    _Stages,
    _untrusted_model,
    accept_poses,
    model_statistics,
)
from omni_sfm.refine.rig import (
    rig_database,
    rig_trajectory,
    seed_rig_for_database,
    write_lens_images,
)
from omni_sfm.reports import (
    BundleAdjustmentReport,
    FeaturesReport,
    JointAdjustmentNote,
    MapperReport,
    RefineCamera,
    RefineInput,
    RefineSettings,
    RigScaleRecord,
    TriangulationReport,
)


def refine_rig(init_dir: Path, images_dir: Path, output: Path, o: RefineOptions, *,
               database: Path | None, overwrite: bool, progress: bool, verbose: bool
               ) -> RefineResult:
    """:func:`omni_sfm.refine.refine` for an init folder of a rig camera (module docstring)."""
    art = InitFolder(init_dir).load()
    camera = art.camera
    assert isinstance(camera, RigCamera)
    if o.features != "sift":
        raise OmniSfmError(f"{init_dir}: a rig camera is refined with SIFT features "
                           f"(--features {o.features} takes one camera)")
    flagged = art.uncertain_rows()
    if (~flagged).sum() < 3:
        raise OmniSfmError(
            f"{init_dir}: the data fix {int((~flagged).sum())} of the {len(flagged)} poses in "
            f"{InitFolder.TRAJECTORY} (report.json frames_uncertain); refine needs 3")
    metres = rig_metres_per_unit(init_dir)
    frames = FrameStore(images_dir)
    names = [n for n, f in zip(pose_frame_names(init_dir, art.trajectory, frames), flagged,
                               strict=True) if not f]
    inp = art.trajectory.subset(~flagged)
    unposed = [n for n in frames.names if n not in set(names)]
    lenses_models = [lens.colmap_export() for lens in camera.lenses]
    parts = _Sections(
        input=RefineInput(init=stored_path(init_dir, output),
                          images=stored_path(images_dir, output),
                          database=stored_path(database, output) if database
                          else RefineFolder.DATABASE),
        camera=RefineCamera(model=camera.model,
                            colmap_model=", ".join(e.camera.model_name for e in lenses_models),
                            image_mirrored_for_colmap=any(e.flip_u for e in lenses_models)),
        frames={"input_poses": len(inp), "images_in_folder": len(frames.names),
                "unposed_in_folder": len(unposed), "input_poses_uncertain": int(flagged.sum())},
        options=RefineSettings(**asdict(o)))
    parts.joint_adjustment = JointAdjustmentNote(
        skipped="a rig camera: COLMAP's adjustment (the joint adjustment takes one camera)")
    parts.mapper = MapperReport(skipped=(
        "a rig camera: the frames without an input pose are not registered (the mapper takes "
        "one camera)") if unposed else "every frame of the folder has an input pose")
    stages = _Stages(["images", "features and matching", "triangulation", "bundle adjustment",
                      "acceptance and output"], progress)
    try:
        with library_logging(verbose), atomic_output_dir(
                output, overwrite=overwrite, inputs=(init_dir, images_dir, database)) as tmp:
            run = _RigRun(o, camera, inp, names, metres, tmp,
                          Path(database) if database else tmp / RefineFolder.DATABASE, parts)
            with stages.stage("images"):
                write_lens_images(tmp / RefineFolder.COLMAP_IMAGES, run.lenses,
                                  ((n, frames.read(n)) for n in names))
            with stages.stage("features and matching"):
                run.database()
            with stages.stage("triangulation"):
                rec, ids = run.triangulated()
            with stages.stage("bundle adjustment"):
                obs0, trusted = run.adjusted(rec, ids)
            with stages.stage("acceptance and output"):
                acc = run.accepted(rec, ids, obs0, trusted)
                run.write(rec, acc, init_dir)
            report = parts.report(dict(stages.times))
            report = replace(report, rig=run.scale(acc, art))
            report.write(tmp / RefineFolder.REPORT)
    finally:
        stages.close()
    return RefineResult(output, acc.trajectory, inp, acc.refined, report)


class _RigRun:
    """One rig refinement's state, its steps in the order :func:`refine_rig` calls them."""

    def __init__(self, o: RefineOptions, camera: RigCamera, inp: Trajectory, names: list[str],
                 metres_per_unit: float, tmp: Path, db: Path, report: _Sections) -> None:
        from omni_sfm.export.colmap_lenses import LensExports

        self.o, self.camera, self.inp, self.names = o, camera, inp, names
        self.metres_per_unit, self.tmp, self.db, self.report = metres_per_unit, tmp, db, report
        self.lenses = LensExports.of(camera)

    def database(self) -> None:
        """Features, the rig and the matches (:func:`~omni_sfm.refine.rig.rig_database`)."""
        o = self.o
        got = rig_database(self.db, self.tmp, self.tmp / RefineFolder.COLMAP_IMAGES,
                           self.camera, self.names, max_features=o.max_features,
                           num_threads=o.num_threads, overlap=o.overlap)
        self.report.features = FeaturesReport(
            source="sift", extracted_images=got.extracted_images,
            reused_images=got.reused_images, keypoints=got.keypoints)
        self.report.matching = {"verified_pairs": got.verified_pairs,
                                "inlier_matches": got.inlier_matches}

    def triangulated(self) -> tuple[Any, list[list[int]]]:
        """The points triangulated on the input poses in metres (poses, intrinsics and lens
        offsets held), and each frame's image ids."""
        import pycolmap

        inp = self.inp
        metric = Trajectory(inp.timestamps, inp.rotations, inp.positions * self.metres_per_unit)
        seed, ids = seed_rig_for_database(self.camera, metric, self.names, self.db)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.ba_refine_sensor_from_rig = False  # its default moves the lenses apart
        opts.ba_refine_focal_length = opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.num_threads = self.o.num_threads
        work = self.tmp / "triangulation"
        work.mkdir()
        rec = pycolmap.triangulate_points(seed, str(self.db),
                                          str(self.tmp / RefineFolder.COLMAP_IMAGES), str(work),
                                          clear_points=True, options=opts)
        shutil.rmtree(work, ignore_errors=True)
        self.report.triangulation = TriangulationReport(**asdict(model_statistics(rec)))
        return rec, ids

    def observations(self, rec: Any, ids: list[list[int]]) -> np.ndarray:
        """``(N,)`` each frame's point observations over its lens images."""
        return np.asarray([_observations(rec, row).sum() for row in ids], dtype=np.int64)

    def adjusted(self, rec: Any, ids: list[list[int]]) -> tuple[np.ndarray, bool]:
        """COLMAP's adjustment where the model is strong enough (the best-observed frame and the
        weak ones held); each frame's observations before it and whether the model is
        trusted."""
        o = self.o
        obs0 = self.observations(rec, ids)
        weak = obs0 < o.min_observations
        need = max(o.min_points, int(np.ceil(o.min_points_per_frame * len(ids))))
        trusted = rec.num_points3D() >= need and (~weak).sum() >= 3
        if not trusted:
            self.report.bundle_adjustment = BundleAdjustmentReport(
                skipped=f"too few points ({rec.num_points3D()} < {need}) or well-observed "
                        f"frames ({int((~weak).sum())} < 3)")
            return obs0, False
        frame_of = [rec.images[row[0]].frame_id for row in ids]
        held = {frame_of[k] for k in np.flatnonzero(weak)} | {frame_of[int(np.argmax(obs0))]}
        rounds = _bundle_adjust(rec, held, None, o)
        self.report.bundle_adjustment = BundleAdjustmentReport(
            rounds=rounds, held_fixed_frames=len(held), after=model_statistics(rec))
        return obs0, True

    def accepted(self, rec: Any, ids: list[list[int]], obs0: np.ndarray,
                 trusted: bool) -> Acceptance:
        """Per frame, the adjusted pose mapped onto the input's world and units, or the input
        pose (``accept_poses``)."""
        inp = self.inp
        why = _untrusted_model(rec, trusted, self.o)
        if why is not None:
            acc = Acceptance(inp, np.zeros(len(inp), bool), kept_input_for_all=why)
        else:
            ref, ok = rig_trajectory(rec, self.camera, self.names, inp.timestamps)
            obs = self.observations(rec, ids)
            err = np.asarray([_mean_error(rec, row) for row in ids])
            acc = accept_poses(inp, self.names, ref, ok, obs0, obs, err, self.o,
                               inp.path_length())
        self.report.acceptance = acc
        return acc

    def write(self, rec: Any, acc: Acceptance, init_dir: Path) -> None:
        """The output model (the rig at the output's poses, in its units, with the points),
        ``trajectory.tum``, ``camera.yaml`` and the files carried from the input."""
        import pycolmap

        tmp, traj = self.tmp, acc.trajectory
        metres = self.output_metres_per_unit(acc)
        if acc.alignment is not None:
            a = acc.alignment
            rec.transform(pycolmap.Sim3d(float(a.scale), pycolmap.Rotation3d(a.rotation),
                                         np.asarray(a.translation)))
        else:  # the input's units: the triangulation's metres divided by its scale
            rec.transform(pycolmap.Sim3d(1.0 / self.metres_per_unit, pycolmap.Rotation3d(),
                                         np.zeros(3)))
        posed = build_lens_rig(self.camera, traj, self.names, metres)
        for k, name in enumerate(self.names):
            im = rec.find_image_with_name(lens_image_name(0, name))
            rec.frame(im.frame_id).rig_from_world = \
                posed.reconstruction.frame(k + 1).rig_from_world
        rec.update_point_3d_errors()
        self.report.model = model_statistics(rec)
        self.report.summary = rec.summary()
        (tmp / RefineFolder.SPARSE).mkdir()
        rec.write_binary(str(tmp / RefineFolder.SPARSE))
        if self.o.text:
            rec.write_text(str(tmp / RefineFolder.SPARSE))
        write_tum(tmp / RefineFolder.TRAJECTORY, traj)
        atomic_write_text(tmp / InitFolder.MANIFEST, dumps_json(rig_manifest(
            posed, traj, "the frames and images of sparse/ have the COLMAP database's ids; the "
            "image of lens L of the frame <name> is images_colmap/lensL/<name>")))
        write_camera_yaml(tmp / RefineFolder.CAMERA, self.camera)
        self.report.carried_from_input = carry_forward(init_dir, tmp)
        self.report.trajectory_frames = len(traj)

    def output_metres_per_unit(self, acc: Acceptance) -> float:
        """Metres in one unit of the output's poses: the adjustment's (in metres, fixed by the
        lens baseline) mapped by the acceptance's scale, else the input's."""
        if acc.alignment is None:
            return self.metres_per_unit
        return 1.0 / float(acc.alignment.scale)

    def scale(self, acc: Acceptance, art: Any) -> RigScaleRecord:
        """``report.json`` ``rig``."""
        if acc.alignment is None:
            rep = art.read_report()
            return rep.rig if rep is not None and rep.rig is not None else RigScaleRecord(
                metres_per_unit=self.metres_per_unit, note="the init's")
        return RigScaleRecord(
            metres_per_unit=self.output_metres_per_unit(acc), fixed=True,
            note=("the lens baseline in COLMAP's adjustment of the points (the init's: "
                  f"{self.metres_per_unit:.6g})"))


def _mean_error(rec: Any, image_ids: list[int]) -> float:
    """The mean reprojection error (px) of a frame's lens images' observations, weighted by
    their number (inf without any)."""
    err = _frame_errors(rec, image_ids)
    n = _observations(rec, image_ids).astype(float)
    ok = np.isfinite(err) & (n > 0)
    return float(np.average(err[ok], weights=n[ok])) if ok.any() else float("inf")
