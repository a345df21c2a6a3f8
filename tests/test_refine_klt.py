"""``omni-sfm refine --features klt``: point evidence from corner tracks instead of SIFT.

Same small rendered room as tests/test_refine.py (400 x 300 hyperboloid, 20 frames, the
"line stage" missing frames 6 and 13), seeded with the perturbed ground truth.
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from helpers import assert_one_line_error, refine_perturbed

from omni_sfm.cli import main
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.fileio import read_json
from omni_sfm.poses import read_tum
from omni_sfm.refine import RefineOptions, refine
from omni_sfm.refine.database import sequential_pairs
from omni_sfm.refine.synthetic import write_perturbed_init

MISSING = (6, 13)


def _table_rows(db: Path, table: str) -> list[tuple[int, int]]:
    """``(image or pair id, rows)`` of a COLMAP database table, read with sqlite3."""
    key = "pair_id" if table in ("matches", "two_view_geometries") else "image_id"
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return con.execute(f"SELECT {key}, rows FROM {table}").fetchall()
    finally:
        con.close()


@pytest.fixture(scope="module")
def klt_refined(room, built_once):
    """``refine_perturbed`` of the room, once per test run (``built_once``: read-only)."""
    return built_once("refine-room-klt", lambda d: refine_perturbed(
        room, d, MISSING, RefineOptions(features="klt", overlap=5)))[1]


def test_klt_refine_improves_the_seed_and_triangulates_points(klt_refined):
    work, gt, init, res = klt_refined
    r = res.report
    before = trajectory_errors(init, gt)
    after = trajectory_errors(res.trajectory, gt)
    assert after.num_common == len(gt)  # the mapper placed the two unposed frames
    assert sorted(r.mapper.registered or []) == [f"{k:06d}.png" for k in MISSING]
    # better than the input, by far (SIFT reaches about 0.08 % / 0.05 deg on this seed)
    assert after.ate_rel < 0.5 * before.ate_rel, (after.ate_rel, before.ate_rel)
    assert after.rot_mean_deg < 0.5 * before.rot_mean_deg
    assert r.refined_frames >= 0.8 * len(init)
    assert r.features.source == "klt" and (r.features.tracks or 0) > 300
    assert r.model.points > 300 and r.model.mean_reprojection_error_px < 0.5
    rec = pycolmap.Reconstruction(str(work / "out" / "sparse"))
    assert rec.num_points3D() == r.model.points


def _own_copy(work: Path, tmp_path: Path) -> Path:
    """The shared refine's database, copied: pycolmap opens a database for writing, and two
    test processes opening the shared one at once find it locked."""
    db = tmp_path / "database.db"
    shutil.copy(work / "out" / "database.db", db)
    return db


@pytest.mark.parametrize("overlap", [3, 10])
def test_sequential_pairs_are_colmaps(klt_refined, overlap, tmp_path):
    """The KLT pairs are the pairs COLMAP's own sequential matching would match."""
    work, gt, _, _ = klt_refined
    with pycolmap.Database.open(str(_own_copy(work, tmp_path))) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        options = pycolmap.SequentialPairingOptions()
        options.overlap = overlap
        theirs = {tuple(sorted(p)) for p in
                  pycolmap.SequentialPairGenerator(options, d).all_pairs()}
    order = [ids[n] for n in sorted(ids)]
    ours = {tuple(sorted((order[i], order[j])))
            for i, j in sequential_pairs(len(order), overlap)}
    assert ours == theirs and len(ours) > len(order)


def test_klt_database_holds_keypoints_tracks_and_no_descriptors(klt_refined, tmp_path):
    """Keypoints on a common track are matched for the sequential pairs (and only those), each
    match written as an inlier; no SIFT descriptors."""
    work, gt, _, _ = klt_refined
    db = _own_copy(work, tmp_path)
    assert _table_rows(db, "descriptors") == []
    keypoints = _table_rows(db, "keypoints")
    assert len(keypoints) == len(gt) and min(n for _, n in keypoints) > 300
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        order = [ids[f"{k:06d}.png"] for k in range(len(gt))]
        want = {pycolmap.image_pair_to_pair_id(order[i], order[j])
                for i, j in sequential_pairs(len(gt), 5)}
        pair_ids, matches = d.read_all_matches()
        assert set(pair_ids) <= want and len(pair_ids) >= 0.9 * len(want)
        for pair_id, m in zip(pair_ids, matches, strict=True):
            i1, i2 = pycolmap.pair_id_to_image_pair(pair_id)
            g = d.read_two_view_geometry(i1, i2)
            np.testing.assert_array_equal(g.inlier_matches, m)
        # matched keypoints are the same corner: a short hop in the image between neighbours
        k1, k2 = order[3], order[4]
        m = d.read_matches(k1, k2)
        step = d.read_keypoints(k2)[m[:, 1], :2] - d.read_keypoints(k1)[m[:, 0], :2]
        assert len(m) > 300 and np.median(np.linalg.norm(step, axis=1)) < 5.0


def test_klt_rerun_reuses_the_database_and_sources_do_not_mix(room, klt_refined, tmp_path,
                                                               capsys):
    work, gt, init, _ = klt_refined
    db = tmp_path / "database.db"
    shutil.copy(work / "out" / "database.db", db)
    before = {t: _table_rows(db, t) for t in ("keypoints", "matches", "two_view_geometries")}
    rc = main(["refine", "--input", str(work / "init"), "--images", str(room / "images"),
               "--output", str(tmp_path / "out"), "--database", str(db), "--overlap", "5",
               "--features", "klt"])
    assert rc == 0
    capsys.readouterr()
    report = read_json(tmp_path / "out" / "report.json")
    assert report["features"] == {"source": "klt", "extracted_images": 0,
                                  "reused_images": len(gt),
                                  "keypoints": sum(n for _, n in before["keypoints"])}
    assert {t: _table_rows(db, t) for t in before} == before  # nothing tracked or matched
    assert trajectory_errors(read_tum(tmp_path / "out" / "trajectory.tum"), gt).ate_rel < \
        trajectory_errors(init, gt).ate_rel
    # the other source on this database: one line, nothing written
    rc = main(["refine", "--input", str(work / "init"), "--images", str(room / "images"),
               "--output", str(tmp_path / "out_sift"), "--database", str(db),
               "--features", "sift"])
    assert rc == 2
    assert_one_line_error(capsys, "KLT corners", "--features klt")
    assert not (tmp_path / "out_sift").exists()
    assert {t: _table_rows(db, t) for t in before} == before


def test_klt_on_a_sift_database_is_refused(room, tmp_path, capsys):
    """A database holding SIFT features (written here by pycolmap on two frames) is not mixed
    with corner tracks."""
    init = tmp_path / "init"
    write_perturbed_init(room, init, seed=1)
    images = tmp_path / "colmap_images"
    images.mkdir()
    for n in ("000000.png", "000001.png"):
        shutil.copy(room / "images" / n, images / n)
    db = tmp_path / "database.db"
    pycolmap.extract_features(str(db), str(images), device=pycolmap.Device.cpu)
    rc = main(["refine", "--input", str(init), "--images", str(room / "images"),
               "--output", str(tmp_path / "out"), "--database", str(db), "--features", "klt"])
    assert rc == 2
    assert_one_line_error(capsys, "SIFT features", "--features sift")
    assert not (tmp_path / "out").exists()


def test_klt_tracks_again_when_the_database_lacks_frames(room, klt_refined, tmp_path):
    """A database made without the mapper (posed frames only) and reused with it: the missing
    frames break the tracks, so every frame is tracked again, the old keypoints replaced and the
    old matches dropped (no match may point at a keypoint of the old tracking)."""
    work, gt, init, _ = klt_refined
    db = tmp_path / "database.db"
    refine(work / "init", room / "images", tmp_path / "posed_only",
           RefineOptions(features="klt", overlap=3, register_missing=False), database=db,
           progress=False)
    n_posed = len(_table_rows(db, "keypoints"))
    assert n_posed == len(init)
    res = refine(work / "init", room / "images", tmp_path / "all",
                 RefineOptions(features="klt", overlap=3), database=db, progress=False)
    f = res.report.features
    assert (f.extracted_images, f.reused_images) == (len(gt), 0)
    assert len(_table_rows(db, "keypoints")) == len(gt)
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        order = [ids[f"{k:06d}.png"] for k in range(len(gt))]
        # frames 5 and 7 were neighbours in the posed-only tracking, 6 lay between them now
        m = d.read_matches(order[5], order[7])
        step = d.read_keypoints(order[7])[m[:, 1], :2] - d.read_keypoints(order[5])[m[:, 0], :2]
        assert np.median(np.linalg.norm(step, axis=1)) < 10.0
        for pair_id, mm in zip(*d.read_all_matches(), strict=True):
            i1, i2 = pycolmap.pair_id_to_image_pair(pair_id)
            assert mm[:, 0].max() < d.num_keypoints_for_image(i1)
            assert mm[:, 1].max() < d.num_keypoints_for_image(i2)
    assert trajectory_errors(res.trajectory, gt).ate_rel < trajectory_errors(init, gt).ate_rel
