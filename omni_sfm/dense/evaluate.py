"""Accuracy and completeness of a dense map against a true surface mesh (rendered scenes)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.geometry import FloatArray
from omni_sfm.libs import open3d_module
from omni_sfm.poses import Trajectory


@dataclass(frozen=True)
class DenseErrors:
    """Dense points against the true mesh, all lengths in the mesh's unit.

    Attributes:
        num_points: dense points evaluated.
        median_distance: median distance of the points to the true surface.
        p90_distance: 90th percentile of that distance.
        mean_scene_depth: mean distance from the cameras to the surface they see (over the valid
            pixels of the frames sampled).
        threshold: the distance counted as "on the surface" for ``completeness``.
        completeness: share of the visible true surface (samples of it seen by the cameras)
            with a dense point within ``threshold``.
        inlier_share: share of the dense points within ``threshold`` of the true surface.
    """

    num_points: int
    median_distance: float
    p90_distance: float
    mean_scene_depth: float
    threshold: float
    completeness: float
    inlier_share: float

    @property
    def relative_median(self) -> float:
        """``median_distance / mean_scene_depth``."""
        return self.median_distance / self.mean_scene_depth


def _raycasting_scene(mesh: Any) -> Any:
    o3d = open3d_module()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def evaluate_dense(points: FloatArray, mesh: Any, trajectory: Trajectory, camera: CameraModel,
                   *, relative_threshold: float = 0.02, frames: int = 10, pixel_step: int = 4,
                   ) -> DenseErrors:
    """Errors of ``points (N, 3)`` against the legacy Open3D triangle ``mesh``; both, and the
    ``trajectory``, in one frame and unit. The visible surface is sampled by casting the
    camera's rays (every ``pixel_step``-th pixel) from ``frames`` poses spread over the
    trajectory; ``threshold = relative_threshold * mean_scene_depth``."""
    o3d = open3d_module()
    scene = _raycasting_scene(mesh)
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    dist = scene.compute_distance(o3d.core.Tensor(pts)).numpy() if len(pts) else np.zeros(0)
    grid = camera.pixel_grid_rays()[::pixel_step, ::pixel_step].reshape(-1, 3)
    rays_cam = grid[np.isfinite(grid[:, 0])]
    idx = np.unique(np.linspace(0, len(trajectory) - 1, frames).round().astype(int))
    dirs = np.einsum("fij,nj->fni", trajectory.rotations[idx], rays_cam).reshape(-1, 3)
    origins = np.repeat(trajectory.positions[idx], len(rays_cam), axis=0)
    hit = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32)))
    t = hit["t_hit"].numpy()
    ok = np.isfinite(t)
    mean_depth = float(t[ok].mean())
    surface = origins[ok] + dirs[ok] * t[ok, None]
    thr = relative_threshold * mean_depth
    if len(pts):
        dense = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
        near = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(surface))
                          .compute_point_cloud_distance(dense))
        completeness = float((near <= thr).mean())
    else:
        completeness = 0.0
    return DenseErrors(
        num_points=int(len(pts)),
        median_distance=float(np.median(dist)) if len(pts) else float("nan"),
        p90_distance=float(np.percentile(dist, 90)) if len(pts) else float("nan"),
        mean_scene_depth=mean_depth, threshold=thr, completeness=completeness,
        inlier_share=float((dist <= thr).mean()) if len(pts) else 0.0)
