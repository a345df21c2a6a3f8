"""The rig camera: raw dual-fisheye frames (two lenses side by side or stacked) as one camera."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.cameras import OpenCVFisheyeCamera, RigCamera, camera_from_dict, dual_fisheye
from omni_sfm.errors import OmniSfmError


def _lens(size: int = 96) -> OpenCVFisheyeCamera:
    r = 0.49 * size
    f = r / np.radians(100.0)
    c = (size - 1) / 2.0
    return OpenCVFisheyeCamera(width=size, height=size, fx=f, fy=f, cx=c, cy=c, outer_radius=r)


@pytest.mark.parametrize("layout", ["side_by_side", "stacked"])
def test_every_valid_pixel_maps_to_its_ray_and_back(layout: str) -> None:
    rig = dual_fisheye(_lens(), layout=layout)
    assert (rig.width, rig.height) == ((192, 96) if layout == "side_by_side" else (96, 192))
    g = rig.pixel_grid_rays()
    ok = np.isfinite(g[..., 0])
    uv = np.argwhere(ok)[:, ::-1].astype(float)
    assert np.allclose(rig.pixels_from_rays(g[ok]), uv, atol=1e-6)
    # every direction is imaged by exactly one lens: the one nearest its axis
    lens = rig.lens_of_pixels(uv)
    assert np.array_equal(lens, rig.lens_of_rays(g[ok]))
    assert set(lens.tolist()) == {0, 1}
    assert np.allclose(rig.ray_origins(g[ok])[:, 2], np.where(lens == 0, 0.02, -0.02))


def test_lens_1_sees_behind_lens_0() -> None:
    rig = dual_fisheye(_lens())
    uv = rig.pixels_from_rays(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.01]]))
    c = (96 - 1) / 2.0
    assert np.allclose(uv[0], [c, c]) and np.allclose(uv[1], [96 + c, c])
    # a ray just in front of lens 0's equator is lens 0's (its right side, u > c)
    assert uv[2, 0] > c and uv[2, 0] < 96


def test_camera_file_round_trip_and_errors(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from omni_sfm.cameras import load_camera, write_camera_yaml

    rig = dual_fisheye(_lens())
    write_camera_yaml(tmp_path / "rig.yaml", rig)
    back = load_camera(tmp_path / "rig.yaml")
    assert isinstance(back, RigCamera) and back.params() == rig.params()
    p = rig.params()
    p["lenses"][1]["rig_from_lens"][0][0] = 2.0  # not a rotation
    with pytest.raises(OmniSfmError, match=r"lenses\[1\].rig_from_lens.*rigid"):
        camera_from_dict(p, "cam.yaml")
    p = rig.params()
    p["width"] = 100
    with pytest.raises(OmniSfmError, match="side_by_side rig of these lenses is 192 x 96"):
        camera_from_dict(p, "cam.yaml")
    p = rig.params()
    del p["lenses"][0]["rig_from_lens"]
    with pytest.raises(OmniSfmError, match=r"missing key 'lenses\[0\].rig_from_lens'"):
        camera_from_dict(p, "cam.yaml")


def test_pieces_of_one_great_circle_seen_by_two_lenses_stay_two_lines() -> None:
    """Two pieces of a great circle, one in each lens's half of the sphere, 10 deg apart: one
    line for a central camera, two observations for a rig (each lens sees the line from its
    own centre)."""
    from omni_sfm.lines.extract import LineExtractor

    a = np.radians(np.r_[np.linspace(30, 85, 40), np.linspace(95, 150, 40)])
    rays = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=1)
    idx, lab = np.arange(80), np.repeat([0, 1], 40)
    normals = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    rig = dual_fisheye(_lens())
    central = LineExtractor(_lens())._merge(idx, lab, normals, rays)
    split = LineExtractor(rig)._merge(idx, lab, normals, rays)
    assert len(set(central.tolist())) == 1
    assert len(set(split.tolist())) == 2
