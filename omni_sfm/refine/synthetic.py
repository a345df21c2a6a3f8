"""A stand-in for the line-based init on rendered sequences: ground truth with realistic errors;
and an init directory with frames taken out (frames for the mapper stage to register).

Used by the tests and ``scripts/bench/refine.py`` (its default seed) where a perturbation of known
size is wanted instead of a real init; both this and ``omni-sfm init`` go through
:func:`omni_sfm.export.colmap.write_init_model`, so refinement sees the same layout either way.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from omni_sfm.cameras import load_camera
from omni_sfm.export.colmap import write_init_model
from omni_sfm.fileio import atomic_output_dir
from omni_sfm.folders import InitFolder, RenderFolder
from omni_sfm.frames import FrameStore
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.poses import Trajectory, read_tum, write_tum


def perturb(gt: Trajectory, *, rotation_deg: float = 0.3, position_fraction: float = 0.005,
            seed: int = 0) -> Trajectory:
    """``gt`` with independent per-frame errors: a rotation about a random axis with RMS angle
    ``rotation_deg`` (deg) applied in the camera frame, and a centre offset with RMS length
    ``position_fraction`` of the path length. Frame 0 is perturbed too."""
    rng = np.random.default_rng(seed)
    n = len(gt)
    dR = rotvec_to_matrix(np.radians(rotation_deg) * rng.normal(size=(n, 3)) / np.sqrt(3))
    dc = position_fraction * gt.path_length() * rng.normal(size=(n, 3)) / np.sqrt(3)
    return Trajectory(gt.timestamps.copy(), gt.rotations @ dR, gt.positions + dc)


def write_perturbed_init(render_dir: Path, init_dir: Path, *, rotation_deg: float = 0.3,
                         position_fraction: float = 0.005, seed: int = 0,
                         frames: np.ndarray | None = None, overwrite: bool = False
                         ) -> Trajectory:
    """An init directory for a rendered sequence (``omni-sfm render`` output): the perturbed
    ground truth of ``frames`` (indices; default all) as ``trajectory.tum`` and the COLMAP model
    (no ``images_colmap/``: refine writes its own). Returns the perturbed poses."""
    render_dir = Path(render_dir)
    camera = load_camera(render_dir / RenderFolder.CAMERA)
    gt = read_tum(render_dir / RenderFolder.GROUNDTRUTH)
    names = list(FrameStore(render_dir / RenderFolder.IMAGES).names)
    if len(names) != len(gt):
        raise ValueError(f"{render_dir}: {len(names)} images for {len(gt)} poses")
    traj = perturb(gt, rotation_deg=rotation_deg, position_fraction=position_fraction, seed=seed)
    if frames is not None:
        traj = traj.subset(np.asarray(frames))
        names = [names[k] for k in np.asarray(frames)]
    with atomic_output_dir(Path(init_dir), overwrite=overwrite) as tmp:
        write_tum(tmp / InitFolder.TRAJECTORY, traj)
        write_init_model(tmp, camera, traj, names)
    return traj


def write_init_without(init_dir: Path, out_dir: Path, drop: Sequence[str], *,
                       overwrite: bool = False) -> Path:
    """A copy of the init directory ``init_dir`` whose frames ``drop`` (image names) have no
    pose: frames the init "missed", for the mapper stage of refine to register. Everything else
    (the line tracks, 3D lines, report) is copied as it is; the trajectory and the COLMAP model
    are written again without them. Returns ``out_dir``."""
    from omni_sfm.export.colmap import read_init_model

    init = read_init_model(Path(init_dir))
    gone = set(drop)
    unknown = gone - set(init.image_names)
    if unknown:
        raise ValueError(f"{init_dir}: no pose for {sorted(unknown)[:3]}")
    keep = np.asarray([k for k, n in enumerate(init.image_names) if n not in gone], np.intp)
    traj = init.trajectory.subset(keep)
    with atomic_output_dir(Path(out_dir), overwrite=overwrite) as tmp:
        shutil.copytree(init_dir, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(
            InitFolder.SPARSE, InitFolder.TRAJECTORY, InitFolder.MANIFEST))
        write_tum(tmp / InitFolder.TRAJECTORY, traj)
        write_init_model(tmp, init.camera, traj, [init.image_names[k] for k in keep])
    return Path(out_dir)
