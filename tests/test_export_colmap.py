"""The COLMAP model written from omni-sfm poses projects exactly like omni-sfm itself."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from omni_sfm.cameras import EquirectangularCamera, HyperboloidCamera
from omni_sfm.export.colmap import build_reconstruction, projection_centres, write_reconstruction
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.poses import Trajectory

CAMERAS = {
    "hyperboloid": HyperboloidCamera(width=800, height=600, cx=400.0, cy=300.0, px=0.01,
                                     py=0.01, f=8.0, alpha=14.0, beta=19.4, inner_radius=48.0,
                                     outer_radius=290.0),
    "equirectangular": EquirectangularCamera(width=1600, height=800),
}


def _trajectory(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(np.arange(n, dtype=float), rotvec_to_matrix(0.4 * rng.normal(size=(n, 3))),
                      rng.normal(size=(n, 3)))


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_exported_model_projects_like_omni_sfm(name, tmp_path):
    cam = CAMERAS[name]
    traj = _trajectory(5, 0)
    seed = build_reconstruction(cam, traj, [f"{k:06d}.png" for k in range(len(traj))])
    write_reconstruction(seed, tmp_path / "sparse", text=True)
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    assert rec.num_reg_images() == len(traj)
    rng = np.random.default_rng(1)
    worst = 0.0
    checked = 0
    for k in range(len(traj)):
        img = rec.find_image_with_name(f"{k:06d}.png")
        camera = rec.cameras[img.camera_id]
        # random points around the camera, kept where omni-sfm images them
        x_world = traj.positions[k] + rng.normal(size=(400, 3)) * 3.0
        x_cam = (x_world - traj.positions[k]) @ traj.rotations[k]
        uv_ours = cam.pixels_from_rays(x_cam)
        ok = np.isfinite(uv_ours).all(axis=1)
        uv_expected = seed.export.pixels_to_colmap(uv_ours[ok])
        x_colmap_cam = np.asarray([img.cam_from_world() * p for p in x_world[ok]])
        uv_colmap = np.asarray(camera.img_from_cam(x_colmap_cam))
        worst = max(worst, float(np.abs(uv_colmap - uv_expected).max()))
        checked += int(ok.sum())
    assert checked > 500
    assert worst < 1e-6


def test_projection_centres_equal_trajectory(tmp_path):
    traj = _trajectory(4, 2)
    names = [f"f{k}.png" for k in range(4)]
    seed = build_reconstruction(CAMERAS["hyperboloid"], traj, names)
    write_reconstruction(seed, tmp_path)
    centres = projection_centres(pycolmap.Reconstruction(str(tmp_path)))
    for k, n in enumerate(names):
        np.testing.assert_allclose(centres[n], traj.positions[k], atol=1e-9)


def test_colmap_images_in_the_background_write_and_fail_as_in_the_caller(tmp_path):
    from omni_sfm.export.colmap import ColmapImages

    cam = CAMERAS["hyperboloid"]
    img = np.full((cam.height, cam.width), 128, np.uint8)
    images = ColmapImages(tmp_path, cam, str, background=True)
    for k in range(5):
        images.write(f"{k}.png", img)
    images.keep(["1.png", "3.png"])
    images.close()
    folder = images.directory
    assert sorted(p.name for p in folder.iterdir()) == ["1.png", "3.png"]
    (folder / "sub").write_text("a file where a folder must go")
    images = ColmapImages(tmp_path, cam, str, background=True)
    images.write("sub/x.png", img)
    with pytest.raises(OSError):
        images.wait()
    images.close()
