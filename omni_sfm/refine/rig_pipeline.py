"""``omni-sfm refine`` of a rig camera (raw dual-fisheye frames, a camchain; docs/colmap.md,
"Refining a rig"): COLMAP's rig on the line-based poses.

1. images: each lens's part of every frame (``images_colmap/lensK/NAME``) and each lens's mask
   (:func:`omni_sfm.refine.rig.write_lens_images`);
2. features and matching: SIFT in every lens image with the lens's exact camera, the rig applied
   to the database (the lens images of one frame are one COLMAP frame, the lenses at their
   offsets in metres), COLMAP's sequential matching (:func:`omni_sfm.refine.rig.rig_database`);
3. triangulation: the frames posed from the init in metres (its ``rig.metres_per_unit``, rough or
   not), ``pycolmap.triangulate_points`` on them, poses, intrinsics and lens offsets held;
4. mapper: the frames without an input pose (and those the init flags), each frame's lens
   images together, registered by COLMAP's mapper, the seeded frames held;
5. adjustment: COLMAP's bundle adjustment in rounds with outlier filtering (as ``--adjustment
   colmap``), frames and points free, intrinsics and lens offsets held; the gauge is the
   best-observed frame held, the scale the lens baseline's (no position priors: they would hold
   the init's scale);
6. acceptance: as for one camera (``_accept``): the adjusted frames mapped onto the input's world
   and units by a similarity, a frame keeps its input pose unless its lens images hold enough
   observations and its change is plausible. The similarity's scale is the refined metric scale
   (``report.json`` ``rig``), which ``dense`` and the exports take.

The mapper's frames are placed by the acceptance's similarity. The joint adjustment with the
lines takes one camera: the report says it was skipped.
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
    Sections,
    Stages,
    accept_poses,
    colmap_bundle_adjust,
    flagged_seed_poses,
    frame_errors,
    frame_timestamps,
    merge_poses,
    model_statistics,
    observation_counts,
    register_unposed,
    untrusted_model,
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
    flagged = flagged_seed_poses(art, init_dir)
    metres = _init_scale(init_dir, art.trajectory)
    frames = FrameStore(images_dir)
    names = [n for n, f in zip(pose_frame_names(init_dir, art.trajectory, frames), flagged,
                               strict=True) if not f]
    inp = art.trajectory.subset(~flagged)
    posed = set(names)
    unposed = [n for n in frames.names if n not in posed]
    register = o.register_missing and bool(unposed)
    lenses_models = [lens.colmap_export() for lens in camera.lenses]
    parts = Sections(
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
    stages = Stages(["images", "features and matching", "triangulation", "mapper",
                     "bundle adjustment", "acceptance and output"], progress)
    try:
        with library_logging(verbose), atomic_output_dir(
                output, overwrite=overwrite, inputs=(init_dir, images_dir, database)) as tmp:
            run = _RigRun(o, camera, inp, names, list(frames.names),
                          unposed if register else [], metres, tmp,
                          Path(database) if database else tmp / RefineFolder.DATABASE, parts)
            used = run.all_names if register else names
            with stages.stage("images"):
                write_lens_images(tmp / RefineFolder.COLMAP_IMAGES, run.lenses,
                                  ((n, frames.read(n)) for n in used))
            with stages.stage("features and matching"):
                run.database(used)
            with stages.stage("triangulation"):
                rec, ids = run.triangulated()
            with stages.stage("mapper"):
                rec = run.mapper(rec, o.register_missing)
            with stages.stage("bundle adjustment"):
                obs0, trusted = run.adjusted(rec, ids)
            with stages.stage("acceptance and output"):
                acc = run.accepted(rec, ids, obs0, trusted)
                traj, refined, out_names = run.placed(rec, acc)
                run.write(rec, acc, traj, out_names, init_dir)
            report = parts.report(dict(stages.times))
            report = replace(report, rig=run.scale(acc, art))
            report.write(tmp / RefineFolder.REPORT)
    finally:
        stages.close()
    return RefineResult(output, traj, inp, refined, report)


class _RigRun:
    """One rig refinement's state, its steps in the order :func:`refine_rig` calls them."""

    def __init__(self, o: RefineOptions, camera: RigCamera, inp: Trajectory, names: list[str],
                 all_names: list[str], unposed: list[str], metres_per_unit: float, tmp: Path,
                 db: Path, report: Sections) -> None:
        """``names``: the frames of the input poses ``inp``; ``all_names``: every frame of the
        folder, in order; ``unposed``: the frames without an input pose the mapper is to
        register."""
        from omni_sfm.export.colmap_lenses import LensExports

        self.o, self.camera, self.inp, self.names = o, camera, inp, names
        self.all_names, self.unposed = all_names, unposed
        self.metres_per_unit, self.tmp, self.db, self.report = metres_per_unit, tmp, db, report
        self.lenses = LensExports.of(camera)
        self.parallax_px = 0.0
        """The lens baseline's median parallax at the points (:func:`baseline_parallax_px`)."""

    def database(self, names: list[str]) -> None:
        """Features, the rig and the matches of the frames ``names``
        (:func:`~omni_sfm.refine.rig.rig_database`)."""
        o = self.o
        got = rig_database(self.db, self.tmp, self.tmp / RefineFolder.COLMAP_IMAGES,
                           self.camera, names, max_features=o.max_features,
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

    def mapper(self, rec: Any, enabled: bool) -> Any:
        """COLMAP's registration of the frames without an input pose (each frame's lens images
        together, the seeded frames held: :func:`~omni_sfm.refine.pipeline.register_unposed`);
        the model."""
        if not self.unposed:
            self.report.mapper = MapperReport(skipped="disabled" if not enabled else
                                              "every frame of the folder has an input pose")
            return rec
        lens_names = [n for name in self.unposed for n in self.lenses.image_names(name)]
        rec, _ = register_unposed(rec, True, lens_names, self.db,
                                  self.tmp / RefineFolder.COLMAP_IMAGES, self.o)
        got = [n for n in self.unposed if (im := rec.find_image_with_name(
            lens_image_name(0, n))) is not None and im.has_pose]
        self.report.mapper = MapperReport(registered=got, not_registered=[
            n for n in self.unposed if n not in set(got)])
        return rec

    def placed(self, rec: Any, acc: Acceptance) -> tuple[Trajectory, np.ndarray, list[str]]:
        """The output's poses, which of them the images refined, and their frames: the input
        frames' (:meth:`accepted`) and, where the folder's frames have timestamps and the model
        is trusted, the mapper's frames mapped by the acceptance's similarity; frames the
        mapper posed that are not placed leave the model."""
        mapper = self.report.mapper
        assert mapper is not None
        added = list(mapper.registered or [])
        ts_all, why = frame_timestamps(self.all_names, self.names, self.inp.timestamps)
        traj, refined, names = acc.trajectory, acc.refined, list(self.names)
        placed: list[str] = []
        if added and acc.alignment is not None and ts_all is not None:
            index = {n: k for k, n in enumerate(self.all_names)}
            new, ok = rig_trajectory(rec, self.camera, added, ts_all[[index[n] for n in added]])
            placed = [n for n, k in zip(added, ok, strict=True) if k]
            order = np.argsort(np.concatenate([traj.timestamps, new.timestamps]), kind="stable")
            traj, refined = merge_poses(traj, refined, acc.alignment.apply(new))
            names = [(names + placed)[int(k)] for k in order]
        for n in added:
            if n not in placed:
                rec.deregister_frame(rec.find_image_with_name(lens_image_name(0, n)).frame_id)
        if added:
            self.report.mapper = replace(
                mapper, added_to_trajectory=placed,
                timestamps=why if acc.alignment is not None else
                "not placed: the adjusted model was not trusted")
        return traj, refined, names

    def observations(self, rec: Any, ids: list[list[int]]) -> np.ndarray:
        """``(N,)`` each frame's point observations over its lens images."""
        return np.asarray([observation_counts(rec, row).sum() for row in ids], dtype=np.int64)

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
        rounds = colmap_bundle_adjust(rec, held, None, o)
        self.report.bundle_adjustment = BundleAdjustmentReport(
            rounds=rounds, held_fixed_frames=len(held), after=model_statistics(rec))
        return obs0, True

    def accepted(self, rec: Any, ids: list[list[int]], obs0: np.ndarray,
                 trusted: bool) -> Acceptance:
        """Per frame, the adjusted pose mapped onto the input's world and units, or the input
        pose (``accept_poses``)."""
        inp = self.inp
        self.parallax_px = baseline_parallax_px(rec, self.camera)
        why = untrusted_model(rec, trusted, self.o)
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

    def write(self, rec: Any, acc: Acceptance, traj: Trajectory, names: list[str],
              init_dir: Path) -> None:
        """The output model (the rig at the output's poses ``traj`` of the frames ``names``, in
        its units, with the points), ``trajectory.tum``, ``camera.yaml`` and the files carried
        from the input."""
        import pycolmap

        tmp = self.tmp
        metres = self.output_metres_per_unit(acc)
        if acc.alignment is not None:
            a = acc.alignment
            rec.transform(pycolmap.Sim3d(float(a.scale), pycolmap.Rotation3d(a.rotation),
                                         np.asarray(a.translation)))
        else:  # the input's units: the triangulation's metres over its scale
            rec.transform(pycolmap.Sim3d(1.0 / self.metres_per_unit, pycolmap.Rotation3d(),
                                         np.zeros(3)))
        posed = build_lens_rig(self.camera, traj, names, metres)
        _put_rig(rec, posed.reconstruction, names, self.lenses.num_lenses)
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
        seen = self.parallax_px >= MIN_BASELINE_PARALLAX_PX
        return RigScaleRecord(
            metres_per_unit=self.output_metres_per_unit(acc), fixed=bool(seen),
            note=(f"the lens baseline in COLMAP's adjustment of the points (median parallax "
                  f"{self.parallax_px:.2f} px; the init's: {self.metres_per_unit:.6g})" if seen
                  else f"a rough scale: the points are too far for the lens baseline (median "
                  f"parallax {self.parallax_px:.2f} px < {MIN_BASELINE_PARALLAX_PX})"))


MIN_BASELINE_PARALLAX_PX = 1.0
"""The lens baseline fixes the metric scale where its parallax at the points (the median over
them) is at least this many pixels; below it the refined scale is reported as rough."""


def baseline_parallax_px(rec: Any, camera: RigCamera) -> float:
    """The median over the model's points of the angle the widest lens baseline subtends at the
    point, seen from the nearest frame that observes it, in pixels of the lenses' mean focal
    length (the model in metres, as the adjustment has it); 0 without points."""
    centres = np.asarray([T[:3, 3] for T in camera.rig_from_lens])
    baseline = float(max(np.linalg.norm(a - b) for a in centres for b in centres))
    focal = float(np.mean([c.mean_focal_length() for c in rec.cameras.values()]))
    where: dict[int, np.ndarray] = {}
    for f in rec.reg_frame_ids():
        T = rec.frame(f).rig_from_world
        where[f] = -np.asarray(T.rotation.matrix()).T @ np.asarray(T.translation)
    angles = []
    for pt in rec.points3D.values():
        frames = {rec.images[e.image_id].frame_id for e in pt.track.elements}
        dist = min(float(np.linalg.norm(pt.xyz - where[f])) for f in frames if f in where)
        angles.append(baseline / max(dist, 1e-9))
    return float(focal * np.median(angles)) if angles else 0.0


def _put_rig(rec: Any, posed: Any, names: list[str], lenses: int) -> None:
    """Give ``rec`` (the database's ids) the frame poses and lens offsets of ``posed``
    (:func:`~omni_sfm.export.colmap_lenses.build_lens_rig`'s ids: frame ``k + 1`` is
    ``names[k]``, camera ``l + 1`` lens ``l``), matched by image name."""
    import pycolmap

    for k, name in enumerate(names):
        im = rec.find_image_with_name(lens_image_name(0, name))
        rec.frame(im.frame_id).rig_from_world = posed.frame(k + 1).rig_from_world
    first = rec.find_image_with_name(lens_image_name(0, names[0]))
    rig = rec.rig(rec.frame(first.frame_id).rig_id)
    posed_rig = posed.rig(1)
    for lens in range(1, lenses):
        cam = rec.find_image_with_name(lens_image_name(lens, names[0])).camera_id
        rig.set_sensor_from_rig(
            pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=cam),
            posed_rig.sensor_from_rig(pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA,
                                                        id=lens + 1)))


def _init_scale(init_dir: Path, traj: Trajectory) -> float:
    """The init's metres per unit of its poses (``rig.metres_per_unit``, rough or not); where
    the init has none (its lines too far for the lens baseline), those of a 1 m first-to-last
    distance (the adjustment finds the scale the baseline fixes)."""
    try:
        return rig_metres_per_unit(init_dir)
    except OmniSfmError:
        span = float(np.linalg.norm(traj.positions[-1] - traj.positions[0]))
        return 1.0 / span if span > 0 else 1.0


def _mean_error(rec: Any, image_ids: list[int]) -> float:
    """The mean reprojection error (px) of a frame's lens images' observations, weighted by
    their number (inf without any)."""
    err = frame_errors(rec, image_ids)
    n = observation_counts(rec, image_ids).astype(float)
    ok = np.isfinite(err) & (n > 0)
    return float(np.average(err[ok], weights=n[ok])) if ok.any() else float("inf")
