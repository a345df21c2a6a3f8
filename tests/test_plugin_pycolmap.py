"""The pycolmap-seed adapter: a user's own pycolmap flow seeded by an init directory."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from omni_sfm.cameras import load_camera
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap import write_init_model
from omni_sfm.poses import read_tum
from omni_sfm.registry import ADAPTERS, available, load
from omni_sfm.synth.render import RenderOptions, render_sequence


@pytest.fixture(scope="module")
def init_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("plugin")
    render_sequence(root / "room", RenderOptions(scene="room", camera="hyperboloid", width=320,
                                                 height=240, frames=10, textured=True,
                                                 supersample=1, preset="small", seed=5),
                    progress=False)
    cam = load_camera(root / "room" / "camera.yaml")
    gt = read_tum(root / "room" / "groundtruth.tum")
    names = [f"{k:06d}.png" for k in range(len(gt))]
    imgs = (cv2.imread(str(root / "room" / "images" / n))[:, :, ::-1] for n in names)
    write_init_model(root / "init", cam, gt, names, imgs)
    return root / "init"


def test_adapter_is_registered():
    assert "pycolmap-seed" in available(ADAPTERS)
    from omni_sfm_plugins.pycolmap_adapter import seeded_reconstruction

    assert load(ADAPTERS, "pycolmap-seed") is seeded_reconstruction


def test_user_flow_triangulates_with_the_seeded_poses(init_dir, tmp_path):
    # the flow of docs/colmap.md, with database ids deliberately not in trajectory order
    from omni_sfm_plugins.pycolmap_adapter import reader_options

    seeded_reconstruction = load(ADAPTERS, "pycolmap-seed")
    images = init_dir / "images_colmap"
    db = tmp_path / "database.db"
    names = sorted(p.name for p in images.iterdir())
    opts = reader_options(init_dir)
    pycolmap.Database.open(db).close()  # import_images needs the database file
    half = len(names) // 2  # the second half first: its ids come before the first half's
    pycolmap.import_images(db, images, pycolmap.CameraMode.SINGLE, image_names=names[half:],
                           options=opts)
    opts.existing_camera_id = 1  # the rest of the frames share the imported camera
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=opts, device=pycolmap.Device.cpu)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 4
    pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)

    rec = seeded_reconstruction(db, images, init_dir)
    with pycolmap.Database.open(db) as d:
        db_ids = {im.name: im.image_id for im in d.read_all_images()}
    assert db_ids[names[half]] == 1 and db_ids[names[0]] > half
    assert {im.name: im.image_id for im in rec.images.values()} == db_ids
    assert rec.num_reg_images() == len(names) and rec.num_points3D() == 0
    exact = load_camera(init_dir / "camera.yaml").colmap_export().camera
    cam = next(iter(rec.cameras.values()))
    assert cam.model_name == "EUCM"
    np.testing.assert_array_equal(cam.params, exact.params)

    tri = pycolmap.triangulate_points(rec, db, images, tmp_path / "tri")
    assert tri.num_points3D() > 100
    # exact poses and the exact camera: points reproject to sub-pixel error
    assert tri.compute_mean_reprojection_error() < 0.7
    gt = read_tum(init_dir / "trajectory.tum")
    for k, n in enumerate(names):
        np.testing.assert_allclose(tri.find_image_with_name(n).projection_center(),
                                   gt.positions[k], atol=1e-9)


def test_adapter_refuses_a_mismatch(init_dir, tmp_path):
    seeded_reconstruction = load(ADAPTERS, "pycolmap-seed")
    images = init_dir / "images_colmap"
    with pytest.raises(OmniSfmError, match="missing"):
        seeded_reconstruction(tmp_path / "none.db", tmp_path, init_dir)
    db = tmp_path / "pinhole.db"
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = "PINHOLE"
    pycolmap.Database.open(db).close()
    pycolmap.import_images(db, images, pycolmap.CameraMode.SINGLE, options=opts)
    with pytest.raises(OmniSfmError, match="PINHOLE"):
        seeded_reconstruction(db, images, init_dir)
