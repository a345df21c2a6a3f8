"""360 video without a camera file: ``--camera equirectangular`` (built from the frame size, 2:1
or squeezed to 16:9) and MP4 files whose spherical-video metadata (Google's V2 ``sv3d`` boxes or
V1 XMP ``uuid`` box, written here into rendered H.264 videos) says equirectangular.

The files are made as Google's spatial-media injector makes them: the metadata box is inserted
into the video track's box tree (V1: ``moov/trak/uuid``; V2: ``sv3d`` and ``st3d`` in the
sample entry ``moov/trak/mdia/minf/stbl/stsd/avc1``) and the sizes of the boxes around it are
increased; PyAV writes ``moov`` after ``mdat``, so no chunk offset moves.
"""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from helpers import assert_one_line_error

from omni_sfm.cameras import EquirectangularCamera
from omni_sfm.cli import main
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.lines.source_camera import camera_for_frames
from omni_sfm.lines.spherical import SPHERICAL_V1_UUID, spherical_metadata
from omni_sfm.poses import read_tum
from omni_sfm.synth.effects import VideoCodec
from omni_sfm.synth.render import RenderOptions

# a 2:1 walk and the same walk squeezed to 16:9, H.264 as 360 cameras write it; 10 frames
WIDE = RenderOptions(camera="equirectangular", width=640, height=320, frames=10, seed=4,
                     video=True, video_codec=VideoCodec.H264)
SQUEEZED = RenderOptions(camera="equirectangular", width=640, height=360, frames=10, seed=4,
                         video=True, video_codec=VideoCodec.H264)

XMP = ('<?xml version="1.0"?><rdf:SphericalVideo xmlns:rdf="http://www.w3.org/1999/02/'
       '22-rdf-syntax-ns#" xmlns:GSpherical="http://ns.google.com/videos/1.0/spherical/">'
       "<GSpherical:Spherical>true</GSpherical:Spherical>"
       "<GSpherical:Stitched>true</GSpherical:Stitched>"
       "<GSpherical:StitchingSoftware>omni-sfm test</GSpherical:StitchingSoftware>"
       "<GSpherical:ProjectionType>equirectangular</GSpherical:ProjectionType>{extra}"
       "</rdf:SphericalVideo>")


def _box(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", 8 + len(payload)) + kind + payload


def _children(data: bytes, start: int, end: int) -> list[tuple[bytes, int, int]]:
    out, pos = [], start
    while pos + 8 <= end:
        size, kind = struct.unpack(">I4s", data[pos:pos + 8])
        assert 8 <= size <= end - pos, (kind, size)
        out.append((kind, pos, pos + size))
        pos += size
    return out


def _child(data: bytes, box: tuple[bytes, int, int], kind: bytes, skip: int = 0
           ) -> tuple[bytes, int, int]:
    return next(b for b in _children(data, box[1] + 8 + skip, box[2]) if b[0] == kind)


def _inject(src: Path, dst: Path, v1_xmp: str | None = None, v2: bytes | None = None) -> Path:
    """``src`` with a V1 XMP ``uuid`` box in its video track and/or the V2 boxes ``v2`` in its
    first sample entry, written to ``dst``."""
    data = src.read_bytes()
    top = _children(data, 0, len(data))
    moov = next(b for b in top if b[0] == b"moov")
    assert all(b[0] != b"mdat" or b[1] < moov[1] for b in top), "moov must follow mdat"
    trak = next(t for t in _children(data, moov[1] + 8, moov[2]) if t[0] == b"trak"
                and data[_child(data, _child(data, t, b"mdia"), b"hdlr")[1] + 16:][:4]
                == b"vide")
    mdia = _child(data, trak, b"mdia")
    stsd = _child(data, _child(data, _child(data, mdia, b"minf"), b"stbl"), b"stsd")
    entry = _children(data, stsd[1] + 16, stsd[2])[0]
    inserts = []  # (position, bytes, the boxes that hold it)
    if v2 is not None:
        inserts.append((entry[2], v2, [moov, trak, mdia, _child(data, mdia, b"minf"),
                                       _child(data, _child(data, mdia, b"minf"), b"stbl"),
                                       stsd, entry]))
    if v1_xmp is not None:
        inserts.append((trak[2], _box(b"uuid", SPHERICAL_V1_UUID + v1_xmp.encode()),
                        [moov, trak]))
    out = bytearray(data)
    for at, blob, holders in sorted(inserts, key=lambda x: -x[0]):  # last first
        out[at:at] = blob
        for h in holders:
            size = struct.unpack(">I", out[h[1]:h[1] + 4])[0]
            out[h[1]:h[1] + 4] = struct.pack(">I", size + len(blob))
    dst.write_bytes(bytes(out))
    return dst


def _sv3d(projection: bytes = b"equi", bounds: tuple[int, ...] = (0, 0, 0, 0),
          stereo: int | None = None) -> bytes:
    proj_box = _box(b"equi", bytes(4) + struct.pack(">4I", *bounds)) if projection == b"equi" \
        else _box(projection, bytes(12))
    sv3d = _box(b"sv3d", _box(b"svhd", bytes(4) + b"omni-sfm test\0")
                + _box(b"proj", _box(b"prhd", bytes(16)) + proj_box))
    return sv3d + (b"" if stereo is None else _box(b"st3d", bytes(4) + bytes([stereo])))


def test_squeezed_equirectangular_spans_360_by_180():
    """A 1920x1080 frame (16:9) maps 360 deg across and 180 deg down, as pycolmap's
    EQUIRECTANGULAR camera of the same size does: unequal angular pitches."""
    cam = EquirectangularCamera(width=1920, height=1080)
    # COLMAP pixel (uc, vc) = (u + 0.5, v + 0.5): uc = W/4 is lon -90 deg, vc = H/4 lat -45
    corners = np.array([[1920 / 4 - 0.5, 1080 / 2 - 0.5], [1920 / 2 - 0.5, 1080 / 4 - 0.5],
                        [3 * 1920 / 4 - 0.5, 3 * 1080 / 4 - 0.5]])
    s = np.sqrt(0.5)
    np.testing.assert_allclose(cam.rays_from_pixels(corners),
                               [[-1, 0, 0], [0, -s, s], [s, s, 0]], atol=1e-12)
    uv = np.random.default_rng(0).uniform([0, 0], [1919, 1079], size=(200, 2))
    np.testing.assert_allclose(cam.pixels_from_rays(cam.rays_from_pixels(uv)), uv, atol=1e-9)
    exp = cam.colmap_export()
    np.testing.assert_allclose(
        exp.pixels_from_colmap(exp.camera.img_from_cam(cam.rays_from_pixels(uv))), uv,
        atol=1e-6)
    assert "0.1875 deg across, 0.1667 deg down (squeezed" in cam.summary()


@pytest.fixture(scope="module")
def wide(rendered) -> Path:
    return rendered(WIDE).output


def test_metadata_parser_reads_what_the_injector_writes(wide, tmp_path):
    video = wide / "video.mp4"
    assert spherical_metadata(video) is None  # a plain video
    md = spherical_metadata(_inject(video, tmp_path / "v2.mp4", v2=_sv3d()))
    assert md is not None and md.full_equirectangular and "V2" in md.scheme
    md = spherical_metadata(_inject(video, tmp_path / "v1.mp4", v1_xmp=XMP.format(extra="")))
    assert md is not None and md.full_equirectangular and "V1" in md.scheme
    # V2 wins over V1 when both are there
    both = spherical_metadata(_inject(video, tmp_path / "b.mp4", v1_xmp=XMP.format(extra=""),
                                      v2=_sv3d()))
    assert both is not None and "V2" in both.scheme
    # what is not one whole equirectangular sphere
    cases: list[tuple[str, dict[str, Any], tuple[str, object]]] = [
        ("tb", {"v2": _sv3d(stereo=1)}, ("stereo", "top-bottom")),
        ("cube", {"v2": _sv3d(b"cbmp")}, ("projection", "cubemap")),
        ("crop", {"v2": _sv3d(bounds=(0, 0, 1 << 30, 0))}, ("cropped", True)),
        ("v1lr", {"v1_xmp": XMP.format(
            extra="<GSpherical:StereoMode>left-right</GSpherical:StereoMode>")},
         ("stereo", "left-right")),
        ("v1crop", {"v1_xmp": XMP.format(extra="".join(
            f"<GSpherical:{k}>{v}</GSpherical:{k}>" for k, v in [
                ("CroppedAreaImageWidthPixels", 640), ("CroppedAreaImageHeightPixels", 200),
                ("FullPanoWidthPixels", 640), ("FullPanoHeightPixels", 320),
                ("CroppedAreaLeftPixels", 0), ("CroppedAreaTopPixels", 60)]))},
         ("cropped", True)),
    ]
    for name, kw, what in cases:
        md = spherical_metadata(_inject(video, tmp_path / f"{name}.mp4", **kw))
        assert md is not None and not md.full_equirectangular, name
        assert getattr(md, what[0]) == what[1], (name, md)
    # files that are no MP4 box tree, or a cut one: no metadata, no exception
    (tmp_path / "text.mp4").write_text("not a video at all")
    assert spherical_metadata(tmp_path / "text.mp4") is None
    cut = (tmp_path / "v2.mp4").read_bytes()
    (tmp_path / "cut.mp4").write_bytes(cut[: len(cut) - 40])
    assert spherical_metadata(tmp_path / "cut.mp4") is None
    assert spherical_metadata(tmp_path / "missing.mp4") is None


def test_init_as_typed_on_360_video_without_camera_file(wide, tmp_path, capsys):
    """`init --images walk.mp4 --camera equirectangular` and, for an MP4 with spherical
    metadata, `init --images walk.mp4` give the poses the camera file gives."""
    walk = tmp_path / "walk.mp4"
    shutil.copyfile(wide / "video.mp4", walk)
    base = ["init", "--lines", "--images", str(walk), "--quiet", "--debug-view", "none",
            "--no-colmap", "--workers", "1"]
    assert main([*base, "--camera", str(wide / "camera.yaml"), "-o", str(tmp_path / "a")]) == 0
    assert main([*base, "--camera", "equirectangular", "-o", str(tmp_path / "b")]) == 0
    assert "note" not in capsys.readouterr().err
    a, b = read_tum(tmp_path / "a" / "trajectory.tum"), read_tum(tmp_path / "b" / "trajectory.tum")
    np.testing.assert_array_equal(a.rotations, b.rotations)
    np.testing.assert_array_equal(a.positions, b.positions)
    err = trajectory_errors(b, read_tum(wide / "groundtruth.tum"))
    assert len(b) == WIDE.frames and err.rot_max_deg < 0.5
    rep = json.loads((tmp_path / "b" / "report.json").read_text())
    assert rep["input"]["camera"] == "equirectangular"
    # dense takes it too (the frames the init folder records)
    from omni_sfm.dense.pipeline import read_dense_input

    assert read_dense_input(tmp_path / "b", None, Path("equirectangular")).camera == \
        EquirectangularCamera(width=640, height=320)
    # the same video with V2 metadata, given as typed: one note on stderr, the same poses
    meta = _inject(wide / "video.mp4", tmp_path / "walk360.mp4", v2=_sv3d())
    assert main(["init", "--lines", "--images", str(meta), "--quiet", "--debug-view", "none",
                 "--no-colmap", "--workers", "1", "-o", str(tmp_path / "c")]) == 0
    err_text = capsys.readouterr().err
    assert err_text.count("\n") == 1 and err_text.startswith("omni-sfm: note: ")
    assert "equirectangular 640x320" in err_text and "V2" in err_text
    c = read_tum(tmp_path / "c" / "trajectory.tum")
    np.testing.assert_array_equal(a.rotations, c.rotations)
    # track takes the same values: here the metadata, on the first 3 frames
    assert main(["track", "--images", str(meta), "--frames", "3",
                 "-o", str(tmp_path / "t")]) == 0
    out = capsys.readouterr()
    assert out.err.startswith("omni-sfm: note: ") and "track: 3 frames" in out.out
    # V1 XMP: the camera shown as init would read it
    v1 = _inject(wide / "video.mp4", tmp_path / "v1.mp4", v1_xmp=XMP.format(extra=""))
    assert main(["camera", "show", "--images", str(v1)]) == 0
    out = capsys.readouterr()
    assert "model: equirectangular" in out.out and "V1" in out.err


def test_360_camera_errors_are_one_line(wide, tmp_path, capsys):
    video = wide / "video.mp4"
    out = str(tmp_path / "o")
    assert main(["init", "--images", str(video), "--camera", "equirect", "-o", out]) == 2
    assert_one_line_error(capsys, "equirect: camera file not found", "'equirectangular'")
    assert main(["init", "--images", str(video), "-o", out]) == 2
    assert_one_line_error(capsys, "--camera equirectangular", "no spherical-video metadata")
    assert main(["camera", "show", "equirectangular"]) == 2
    assert_one_line_error(capsys, "--images")
    # metadata that is not one mono, uncropped sphere, or a frame that is not 2:1
    tb = _inject(video, tmp_path / "tb.mp4", v2=_sv3d(stereo=1))
    assert main(["init", "--images", str(tb), "-o", out]) == 2
    assert_one_line_error(capsys, "top-bottom", "--camera")
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "000000.png"), np.zeros((300, 640), np.uint8))
    with pytest.raises(ValueError, match="carries no spherical-video metadata"):
        camera_for_frames(None, frames)
    assert camera_for_frames("equirectangular", frames) == \
        EquirectangularCamera(width=640, height=300)
    assert not (tmp_path / "o").exists()


def test_squeezed_video_gives_the_poses_of_its_2to1_resampling(rendered, tmp_path):
    """A walk rendered 640x360 (equirectangular squeezed to 16:9, as some exporters write it),
    and its frames resampled to 640x320 (2:1): `--camera equirectangular` on each.

    Tolerance: 0.1 deg in rotation and 0.5 % of the path in position between the two runs
    (measured: 0.017 deg and 0.03 %). They see the same H.264 frames through different pixel
    grids (360 rows against 320, and the resampling smooths), so their lines are fitted to
    different samples of the same edges: the two estimates differ by sampling noise only, well
    under each one's error against the ground truth on this short 640 px walk (about 0.1 deg,
    mostly shared, as it comes from the same compressed frames; held under 0.2 deg)."""
    seq = rendered(SQUEEZED).output
    cap = cv2.VideoCapture(str(seq / "video.mp4"))
    wide_frames = tmp_path / "wide"
    wide_frames.mkdir()
    k = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        cv2.imwrite(str(wide_frames / f"{k:06d}.png"),
                    cv2.resize(img, (640, 320), interpolation=cv2.INTER_AREA))
        k += 1
    cap.release()
    assert k == SQUEEZED.frames
    runs = {}
    for name, images in (("squeezed", seq / "video.mp4"), ("wide", wide_frames)):
        assert main(["init", "--lines", "--images", str(images), "--camera", "equirectangular",
                     "--quiet", "--debug-view", "none", "--no-colmap", "--workers", "1",
                     "-o", str(tmp_path / f"init_{name}")]) == 0
        runs[name] = read_tum(tmp_path / f"init_{name}" / "trajectory.tum")
    sq, wd = runs["squeezed"], runs["wide"]
    assert len(sq) == len(wd) == SQUEEZED.frames
    rel = np.einsum("nji,njk->nik", sq.rotations, wd.rotations)
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    gt = read_tum(seq / "groundtruth.tum")
    truth = [trajectory_errors(type(t)(gt.timestamps, t.rotations, t.positions), gt)
             for t in (sq, wd)]
    print(f"squeezed vs 2:1: rotation max {ang.max():.4f} deg, position max "
          f"{np.abs(sq.positions - wd.positions).max():.5f}; against the truth: squeezed "
          f"{truth[0].rot_max_deg:.4f} deg, 2:1 {truth[1].rot_max_deg:.4f} deg")
    assert ang.max() < 0.1, ang
    # both normalised the same way (first camera at 0, first-to-last distance 1)
    assert np.abs(sq.positions - wd.positions).max() < 0.005
    assert max(e.rot_max_deg for e in truth) < 0.2
