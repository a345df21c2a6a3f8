"""TSDF fusion of the checked view depths with Open3D's ``VoxelBlockGrid`` (CPU)."""

from __future__ import annotations

from typing import Any

import numpy as np

from omni_sfm.dense.views import StereoRig
from omni_sfm.geometry import FloatArray
from omni_sfm.libs import open3d_module


class TsdfFusion:
    """A truncated signed distance volume with colour, in the world frame of the poses.

    ``voxel_size`` and ``max_depth`` are in pose units (the caller makes them relative to the
    scene's depth, so any pose scale works). Views go in with :meth:`integrate_rig`."""

    def __init__(self, voxel_size: float, *, max_depth: float, trunc_voxels: float = 4.0,
                 block_resolution: int = 8, block_count: int = 20000) -> None:
        if not voxel_size > 0 or not max_depth > 0:
            raise ValueError(f"need voxel_size > 0 and max_depth > 0, got {voxel_size=} "
                             f"{max_depth=}")
        o3d = open3d_module()
        self._o3d = o3d
        self._dev = o3d.core.Device("CPU:0")
        f32 = o3d.core.float32
        self.voxel_size = float(voxel_size)
        self.max_depth = float(max_depth)
        self.trunc_voxels = float(trunc_voxels)
        self.grid: Any = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"), attr_dtypes=(f32, f32, f32),
            attr_channels=((1), (1), (3)), voxel_size=self.voxel_size,
            block_resolution=block_resolution, block_count=block_count, device=self._dev)

    def integrate(self, depth: FloatArray, color: np.ndarray, intrinsic: FloatArray,
                  world_from_view: FloatArray, centre: FloatArray) -> None:
        """One pinhole view: ``depth (H, W)`` view ``z`` (NaN: none), ``color (H, W, 3)``
        uint8 RGB, ``intrinsic (3, 3)``, pose ``world_from_view`` / ``centre`` (world)."""
        o3d = self._o3d
        d = np.nan_to_num(depth, nan=0.0).astype(np.float32)
        d[d >= self.max_depth] = 0.0
        if not (d > 0).any():
            return  # Open3D refuses a frame that touches no block
        view_from_world = np.eye(4)
        view_from_world[:3, :3] = world_from_view.T
        view_from_world[:3, 3] = -world_from_view.T @ centre
        dt = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(d)))
        ct = o3d.t.geometry.Image(o3d.core.Tensor(
            np.ascontiguousarray(color, dtype=np.float32) / 255.0))
        k = o3d.core.Tensor(intrinsic, o3d.core.float64)
        e = o3d.core.Tensor(view_from_world, o3d.core.float64)
        try:
            blocks = self.grid.compute_unique_block_coordinates(
                dt, k, e, depth_scale=1.0, depth_max=self.max_depth,
                trunc_voxel_multiplier=self.trunc_voxels)
        except RuntimeError as exc:  # a few stray depths may touch no block: nothing to fuse
            if "No block is touched" in str(exc):
                return
            raise
        self.grid.integrate(blocks, dt, ct, k, e, depth_scale=1.0, depth_max=self.max_depth,
                            trunc_voxel_multiplier=self.trunc_voxels)

    def integrate_rig(self, rig: StereoRig, depth: FloatArray, colors: np.ndarray,
                      centre: FloatArray) -> None:
        """All views of ``rig``: ``depth (V, H, W)``, ``colors (V, H, W, 3)`` uint8."""
        k = rig.geometry.intrinsic()
        for v in range(depth.shape[0]):
            self.integrate(depth[v], colors[v], k, rig.world_from_views[v], centre)

    def point_cloud(self, weight_threshold: float) -> tuple[FloatArray, FloatArray]:
        """Surface points ``(N, 3)`` (world) and colours ``(N, 3)`` in [0, 1] where the
        accumulated weight is at least ``weight_threshold``."""
        pcd = self.grid.extract_point_cloud(weight_threshold=weight_threshold)
        if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        pts = pcd.point.positions.numpy().astype(np.float64)
        col = pcd.point.colors.numpy().astype(np.float64) if "colors" in pcd.point \
            else np.full_like(pts, 0.5)
        return pts, np.clip(col, 0.0, 1.0)

    def mesh(self, weight_threshold: float) -> Any:
        """The zero level set as a legacy ``open3d.geometry.TriangleMesh`` (vertex colours)."""
        m = self.grid.extract_triangle_mesh(weight_threshold=weight_threshold).to_legacy()
        if m.has_vertex_colors():
            o3d = self._o3d
            m.vertex_colors = o3d.utility.Vector3dVector(
                np.clip(np.asarray(m.vertex_colors), 0.0, 1.0))
        return m
