"""Assertions shared by the test files (imported as ``from helpers import ...``).

- :func:`assert_one_line_error`: a command's bad input became one ``omni-sfm: error:`` line.
- :func:`independent_trajectory_errors`: the figures of ``omni_sfm.evaluate`` recomputed from
  two TUM files with numpy and scipy only (no omni_sfm code), to check reported figures against.
- :func:`refine_perturbed`: ``refine`` from a perturbed ground truth with some frames missing.
- :func:`assert_every_key_declared`: a report a stage wrote names every key it holds and
  reads back to the same bytes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omni_sfm.reports import JsonReport
from omni_sfm.synth.render import RenderOptions

ERROR_PREFIX = "omni-sfm: error: "

# The 360 corridor that test_track.py, test_export_formats.py and test_init_images.py share (the
# ``rendered`` fixture renders equal options once a run): 40 frames, 800 x 400.
EQUIRECT_CORRIDOR = RenderOptions(camera="equirectangular", frames=40, width=800, height=400,
                                  seed=2)


def assert_one_line_error(capsys: pytest.CaptureFixture[str], *needles: str,
                          prefix: str = ERROR_PREFIX) -> str:
    """Everything captured on stderr since the last read is exactly one line,
    ``<prefix><message>\\n`` (no traceback, no warning, nothing before or after), holding every
    one of ``needles``. Returns that line without its newline.

    ``prefix``: argparse's own errors start with the subcommand, e.g. ``omni-sfm dense: error: ``.
    """
    err = capsys.readouterr().err
    assert err.startswith(prefix) and err.endswith("\n") and err.count("\n") == 1, repr(err)
    assert len(err) > len(prefix) + 1, repr(err)  # a message, not just the prefix
    for n in needles:
        assert n in err, (n, err)
    return err[:-1]


def read_tum_independently(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(timestamps (N,), world_from_cam rotations (N, 3, 3), centres (N, 3))`` of a TUM file
    (``t tx ty tz qx qy qz qw`` per line, ``#`` comments), read with numpy and scipy."""
    a = np.loadtxt(path, comments="#", ndmin=2)
    assert a.shape[1] == 8, (path, a.shape)
    return a[:, 0], Rotation.from_quat(a[:, 4:]).as_matrix(), a[:, 1:4]


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``dst ~ s R src + t`` (Umeyama 1991), written out for the tests."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    U, d, Vt = np.linalg.svd(b.T @ a)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ flip @ Vt
    s = float(np.sum(d * np.diag(flip)) / np.sum(a * a))
    return s, R, md - s * R @ ms


def independent_trajectory_errors(est_tum: Path, gt_tum: Path, num_frames: int,
                                  tol: float = 1e-6) -> dict[str, float]:
    """The figures ``omni-sfm compare`` reports for the estimate ``est_tum`` against the ground
    truth ``gt_tum``, from their definitions in ``omni_sfm/evaluate.py``'s docstring:

    ``registered`` (frames in common / ``num_frames``), ``rot_max_deg`` and ``rot_mean_deg``
    (rotation relative to the first common frame), ``ate_rel`` (RMSE of the centres after the
    similarity alignment / true path length), ``rpe`` and ``rpe_rot_deg`` (consecutive frames,
    the estimate scaled by the ratio of summed true to summed estimated motions),
    ``step_error_after_alignment`` (mean step difference after the alignment / mean true step).
    """
    te, Re, pe = read_tum_independently(est_tum)
    tg, Rg, pg = read_tum_independently(gt_tum)
    match = np.abs(te[:, None] - tg[None, :]) <= tol
    keep = match.any(axis=1)
    gi = np.argmax(match, axis=1)[keep]
    Re, pe, Rg, pg = Re[keep], pe[keep], Rg[gi], pg[gi]
    n = len(pe)
    # rotation error relative to the first common frame
    rel_e = Rotation.from_matrix(Re[0].T @ Re)
    rel_g = Rotation.from_matrix(Rg[0].T @ Rg)
    rot = np.degrees((rel_g.inv() * rel_e).magnitude())
    # absolute trajectory error after the similarity alignment
    s, R, t = _similarity(pe, pg)
    aligned = s * pe @ R.T + t
    path = float(sum(np.linalg.norm(pg[k + 1] - pg[k]) for k in range(n - 1)))
    ate = float(np.sqrt(np.mean(np.sum((aligned - pg) ** 2, axis=1)))) / path
    steps_g, steps_a = np.diff(pg, axis=0), np.diff(aligned, axis=0)
    step = float(np.mean(np.linalg.norm(steps_a - steps_g, axis=1))
                 / np.mean(np.linalg.norm(steps_g, axis=1)))
    # relative pose error over consecutive frames, each motion in the earlier camera's frame
    mg = np.array([Rg[k].T @ (pg[k + 1] - pg[k]) for k in range(n - 1)])
    me = np.array([Re[k].T @ (pe[k + 1] - pe[k]) for k in range(n - 1)])
    scale = np.linalg.norm(mg, axis=1).sum() / np.linalg.norm(me, axis=1).sum()
    rpe = float(np.sqrt(np.mean(np.sum((scale * me - mg) ** 2, axis=1)))
                / np.mean(np.linalg.norm(mg, axis=1)))
    step_rot = [Rotation.from_matrix((Rg[k].T @ Rg[k + 1]).T @ (Re[k].T @ Re[k + 1])).magnitude()
                for k in range(n - 1)]
    return {"registered": n / num_frames, "rot_max_deg": float(rot.max()),
            "rot_mean_deg": float(rot.mean()), "ate_rel": ate, "rpe": rpe,
            "rpe_rot_deg": float(np.degrees(np.mean(step_rot))),
            "step_error_after_alignment": step}


def refine_perturbed(render: Path, work: Path, missing: tuple[int, ...], options: object
                     ) -> tuple[Path, object, object, object]:
    """``refine`` of ``render``'s frames from its ground truth perturbed (seed 1), without the
    frames ``missing`` (left for the mapper): ``(work, ground truth, init trajectory,
    RefineResult)``."""
    from omni_sfm.poses import read_tum
    from omni_sfm.refine import refine
    from omni_sfm.refine.synthetic import write_perturbed_init

    gt = read_tum(render / "groundtruth.tum")
    frames = np.array([k for k in range(len(gt)) if k not in missing])
    init = write_perturbed_init(render, work / "init", frames=frames, seed=1)
    res = refine(work / "init", render / "images", work / "out", options,  # type: ignore[arg-type]
                 progress=False)
    return work, gt, init, res


def assert_every_key_declared(cls: type[JsonReport], path: Path) -> None:
    """The report file ``path`` (as ``omni-sfm`` wrote it) read as the report class ``cls``:
    every key at every depth is a field of its section (no section keeps a key in its
    ``other``), and written again it is the same to the byte."""
    from omni_sfm.fileio import dumps_json
    from omni_sfm.reports import undeclared_keys

    rep = cls.read(path)
    assert undeclared_keys(rep) == [], (path, undeclared_keys(rep))
    assert dumps_json(rep.to_json()) == Path(path).read_text(encoding="utf-8"), path
