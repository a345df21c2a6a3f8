"""``omni-sfm init --lines`` on images or video: frames -> line tracks -> poses -> artifacts.

This module only wires the stages together (cameras -> lines -> vanishing/estimate -> export);
the work is in those stages. Output folder (documented in docs/formats.md and docs/colmap.md),
complete or absent:

- ``trajectory.tum``: world_from_cam of every estimated frame (timestamps: frame index for
  image folders, seconds for video);
- ``tracks.json``: the line tracks (with a ray per observation), so the estimator can be re-run
  alone with ``omni-sfm init --lines --tracks``;
- ``lines3d.json``: the estimated 3D line segments, grouped by direction (what ``omni-sfm view``
  and ``omni-sfm dense`` draw);
- ``report.json``: counts, parallel family, per-stage timings, rejected lines, frames not
  estimated, the front end's per-frame figures;
- ``sparse/``, ``camera.yaml``, ``camera_mask.png``, ``colmap.json``, ``images_colmap/``: the
  COLMAP model seeded with the poses (see docs/colmap.md);
- ``debug/``: the frames with tracked lines coloured by parallel group (PNGs, or
  ``debug.mp4``), and ``trajectory.png``: a plot of the estimated trajectory.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.pipeline import EstimationOptions, EstimationResult, estimate_poses
from omni_sfm.fileio import atomic_output_dir, stored_path
from omni_sfm.folders import InitFolder
from omni_sfm.frames import (
    FrameSource,
    read_frames,
    read_mask,
    video_frame_name,
    write_mask,
)
from omni_sfm.geometry import ray_line_closest
from omni_sfm.lines.frontend import FrontEndOptions, FrontEndResult, track_lines
from omni_sfm.lines.source_camera import camera_for_frames
from omni_sfm.lines3d import LineSegments3D, write_lines3d
from omni_sfm.poses import Trajectory
from omni_sfm.reports import (
    AutoMaskReport,
    CameraCheck,
    InitializerInfo,
    InitInput,
    InitReport,
    PluginInitInput,
    PluginInitReport,
    RigScaleRecord,
)
from omni_sfm.transforms import paper_normalised_positions

if TYPE_CHECKING:
    from omni_sfm.export.colmap import ColmapImages
    from omni_sfm.lines.debug import KeptFrames
    from omni_sfm.lines.tracks import LineTracks
    from omni_sfm.plugin_contract import InitializerResult


@dataclass(frozen=True, kw_only=True)
class InitOptions:
    """Options of :func:`init_from_images`."""

    frontend: FrontEndOptions = field(default_factory=FrontEndOptions)
    """Line extraction and tracking."""
    estimation: EstimationOptions = field(default_factory=EstimationOptions)
    """Parallel family, the paper's searches and the line bundle adjustment."""
    start: int = 0
    """First frame (index into the sorted images or the video)."""
    end: int | None = None
    """Stop before this frame; None: to the end."""
    step: int = 1
    """Use every ``step``-th frame."""
    debug_view: str = "auto"
    """Debug view of tracked lines: ``auto`` (PNGs in ``debug/`` of every frame of a run of at
    most :data:`DEBUG_FRAMES` frames, else of that many frames spread evenly over it), ``png``
    (every frame), ``mp4`` (every frame, ``debug.mp4``) or ``none``. The frames come from the
    front end's pass; ``png`` and ``mp4`` on longer runs read the input a second time."""
    keep_uncertain: bool = False
    """Keep the poses of the frames the data do not fix in ``trajectory.tum`` (and the COLMAP
    model); by default they go to ``trajectory_uncertain.tum`` and later stages do without
    them."""
    colmap: bool = True
    """Write the COLMAP model seeded with the poses (``sparse/``, ``images_colmap/``)."""
    colmap_images: bool | None = None
    """Write ``images_colmap/`` (the frames as COLMAP must see them, for COLMAP's own tools;
    ``omni-sfm refine`` reads the input itself) from the front end's pass; None: for runs of at
    most :data:`COLMAP_IMAGE_FRAMES` frames."""
    colmap_text: bool = False
    """Also write the COLMAP model as text."""
    progress: bool = True
    """Progress bars on stderr."""
    auto_mask: bool = True
    """Mask what stays put in the image while the scene moves (the operator, a tripod, the
    mount, the camera's own reflection), found from a sample of the frames
    (:func:`omni_sfm.lines.automask.static_mask`), on top of the user's mask."""
    mask_wobbling: bool = False
    """The automatic mask also takes edges that wobble a few pixels with the camera (a hand
    holding it; :data:`omni_sfm.lines.automask.HAND_HELD_WOBBLE`). Off by default: the far
    end of a corridor stays within a few pixels while the camera walks straight along it."""
    camera_check: bool = True
    """Check on a few frames that the camera model fits the images
    (:func:`omni_sfm.lines.camfit.check_camera_fit`); a misfit is a warning."""
    strict: bool = False
    """Refuse (an error) instead of warning when the camera check fails."""


SAMPLE_FRAMES = 40
"""Frames sampled (evenly over the range) for the automatic mask; the camera check uses 5."""
DEBUG_FRAMES = 300
"""The default debug view draws every frame of a run of at most this many frames, else this
many spread evenly over it (held in memory as JPEG until the estimate colours their lines)."""
COLMAP_IMAGE_FRAMES = 1000
"""By default ``images_colmap/`` is written for runs of at most this many frames (a 10-minute
video would give 18,000 images that ``refine`` does not need)."""


@dataclass(frozen=True)
class InitResult:
    """What :func:`init_from_images` computed and where it wrote it."""

    output: Path
    camera: CameraModel
    frontend: FrontEndResult
    estimation: EstimationResult
    image_names: tuple[str, ...]
    """Names of the estimated frames, in trajectory order (the first is the world frame)."""
    not_estimated: tuple[str, ...] = ()
    """Names of frames that were read but got no pose (report.json says why)."""
    unreadable: tuple[str, ...] = ()
    """Names of frames skipped: not decoded, damaged or of another size."""
    unreadable_reasons: tuple[str, ...] = ()
    """Why each of ``unreadable`` was skipped (one line each)."""
    warnings: tuple[str, ...] = ()
    """One-line warnings (e.g. a camera model that does not fit the images)."""
    auto_mask: str = ""
    """What the automatic mask did, in one line (empty when it was off)."""


def estimated_segments(fe: FrontEndResult, result: EstimationResult,
                       cluster_deg: float = 10.0) -> LineSegments3D:
    """The estimated 3D line segments (written as ``lines3d.json``, docs/formats.md).

    Each used, non-outlier line's extent is where the rays to its observed segment ends come
    closest to it (2nd to 98th percentile over all its observations). Group 0 is the parallel
    family; other lines are grouped greedily by direction (within ``cluster_deg``).
    """
    tr = fe.tracks
    idx = np.flatnonzero(result.estimated)
    pose_of = np.full(tr.num_frames, -1)
    pose_of[idx] = np.arange(len(idx))
    keep = result.used_tracks & ~result.outliers
    sel = keep[tr.obs_track] & (pose_of[tr.obs_frame] >= 0)
    t = tr.obs_track[sel]
    k = pose_of[tr.obs_frame[sel]]
    R, c = result.trajectory.rotations[k], result.trajectory.positions[k]
    d, p = result.line_directions[t], result.line_points[t]
    ends_world = np.einsum("nij,nej->nei", R, fe.obs_endpoint_rays[sel])   # (n, 2, 3)
    _, u, den = ray_line_closest(c[:, None], ends_world, p[:, None], d[:, None])
    u = np.where(den > 1e-12, u, np.nan).T.ravel()  # both ends of every observation
    tt = np.concatenate([t, t])
    groups: list[np.ndarray] = [result.parallel_direction]
    starts, ends, labels, track_ids = [], [], [], []
    cos_tol = np.cos(np.radians(cluster_deg))
    for m in np.flatnonzero(keep):
        um = u[(tt == m) & np.isfinite(u)]
        if len(um) < 2:
            continue
        lo, hi = np.percentile(um, [2, 98])
        if result.parallel[m]:
            g = 0
        else:
            sims = [abs(float(gd @ result.line_directions[m])) for gd in groups[1:]]
            if sims and max(sims) >= cos_tol:
                g = 1 + int(np.argmax(sims))
            else:
                groups.append(result.line_directions[m])
                g = len(groups) - 1
        starts.append(result.line_points[m] + lo * result.line_directions[m])
        ends.append(result.line_points[m] + hi * result.line_directions[m])
        labels.append(g)
        track_ids.append(int(result.track_ids[m]))
    return LineSegments3D(
        np.asarray(starts, dtype=np.float64).reshape(-1, 3),
        np.asarray(ends, dtype=np.float64).reshape(-1, 3),
        np.asarray(labels, dtype=np.int64), np.asarray(groups, dtype=np.float64).reshape(-1, 3),
        ("estimated",) * len(labels), np.asarray(track_ids, dtype=np.int64),
        frame="omni-sfm world: first estimated camera, first-to-last distance = 1")


def _image_names(source: FrameSource, numbers: np.ndarray) -> list[str]:
    files = getattr(source, "files", None)
    if files:
        return [Path(files[int(n)]).name for n in numbers]
    return [video_frame_name(int(n)) for n in numbers]


def plot_trajectory(path: Path, traj: Trajectory, gt: Trajectory | None = None,
                    title: str = "omni-sfm trajectory") -> None:
    """PNG: top view and side view of the camera centres (and ground truth, if given)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    p = traj.positions
    for ax, (i, j), name in zip(axes, [(0, 2), (0, 1)], ["x-z", "x-y"], strict=True):
        if gt is not None:
            ax.plot(gt.positions[:, i], gt.positions[:, j], "k--", lw=1, label="ground truth")
        ax.plot(p[:, i], p[:, j], "-", color="tab:blue", lw=1.5, label="estimated")
        ax.plot(p[:1, i], p[:1, j], "o", color="tab:green", label="first frame")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
        ax.set_title(f"{name} plane (world = first camera)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@dataclass(frozen=True)
class _Checks:
    """The automatic mask and the camera check of one ``init`` run."""

    mask: np.ndarray | None
    camera_check: CameraCheck | None
    auto_mask_report: AutoMaskReport | None
    warnings: tuple[str, ...]
    auto_mask: str


def _check_frames(images: Path | str, cam: CameraModel, o: InitOptions,
                  user_mask: np.ndarray | None,
                  warn: Callable[[str], None] | None) -> _Checks:
    """Camera check (a misfit warns, or refuses with ``strict``), then the automatic mask."""
    from omni_sfm.lines.automask import HAND_HELD_WOBBLE, AutoMaskOptions, static_mask
    from omni_sfm.lines.camfit import check_camera_fit

    if not (o.auto_mask or o.camera_check):
        return _Checks(user_mask, None, None, (), "")
    sample = read_frames(images, o.start, o.end, o.step, size=(cam.width, cam.height),
                         size_error=cam.frame_size_mismatch).sample(SAMPLE_FRAMES)
    camera_check, auto_mask = None, None
    warnings: list[str] = []
    if o.camera_check and sample:
        fit = check_camera_fit(sample[::max(1, len(sample) // 5)][:5], cam, user_mask,
                               o.frontend.extraction)
        camera_check = CameraCheck.from_json(
            {"ok": fit.ok, "message": fit.message,
             **{k: (None if not np.isfinite(v) else float(v)) for k, v in fit.figures.items()}},
            "camera check")
        if not fit.ok:
            if o.strict:
                raise OmniSfmError(f"{fit.message} (--strict)")
            warnings.append(fit.message)
            if warn is not None:
                warn(fit.message)
    mask, said = user_mask, ""
    if o.auto_mask and len(sample) >= 5:
        auto = static_mask(sample, cam, user_mask, AutoMaskOptions(
            wobble_px=HAND_HELD_WOBBLE if o.mask_wobbling else 0.0))
        auto_mask = auto.summary()
        said = f"automatic mask: {auto.reason}"
        if auto.applied:
            mask = auto.mask
    elif o.auto_mask:
        said = f"automatic mask: not applied: {len(sample)} frames, too few to tell"
        auto_mask = AutoMaskReport(applied=False, reason=said)
    return _Checks(mask, camera_check, auto_mask, tuple(warnings), said)


def init_from_images(images: Path | str, camera: Path | str | CameraModel | None,
                     output: Path | str, options: InitOptions | None = None, *,
                     mask: Path | str | None = None, overwrite: bool = False,
                     warn: Callable[[str], None] | None = None,
                     note: Callable[[str], None] | None = None) -> InitResult:
    """Estimate the camera motion of an image folder or video from its straight lines.

    ``camera``: a camera file, a model, ``"equirectangular"`` (built from the frame size) or
    None (an MP4's spherical-video metadata), as :func:`~omni_sfm.lines.source_camera.
    camera_for_frames` reads it; ``note`` gets its line when the metadata chose the camera.
    ``warn`` is called at once with each one-line warning (they are also in the result and
    ``report.json``).

    Raises:
        OmniSfmError: unreadable input, a camera that does not load or does not match the
            images (with ``strict``: a camera model that does not fit them), too few lines
            (with the front end's reason: dark or low-contrast frames, an empty mask, edges
            that are not straight) or no parallel family, degenerate motion.
    """
    from omni_sfm.estimate.pipeline import trusted, write_init_outputs
    from omni_sfm.export.colmap import write_init_model
    from omni_sfm.fileio import check_output_dir
    from omni_sfm.lines.debug import KeptFrames
    from omni_sfm.lines.tracks import write_tracks

    o = options or InitOptions()
    if o.debug_view not in DEBUG_VIEWS:
        raise OmniSfmError(f"debug view must be one of {', '.join(DEBUG_VIEWS)}, got "
                           f"{o.debug_view!r}")
    output = Path(output)
    check_output_dir(output, overwrite=overwrite, inputs=(Path(images),))
    cam = camera_for_frames(camera, images, note=note)
    size = (cam.width, cam.height)
    user_mask = read_mask(mask, size) if mask is not None else None
    source = read_frames(images, o.start, o.end, o.step, size=size,
                         size_error=cam.frame_size_mismatch)
    fe_opts = replace(o.frontend, progress=o.progress and o.frontend.progress)
    with atomic_output_dir(output, overwrite=overwrite, inputs=(Path(images),)) as tmp, \
            contextlib.ExitStack() as stop:  # (the writing threads stop before tmp goes)
        t0 = time.perf_counter()
        checks = _check_frames(images, cam, o, user_mask, warn)
        line_mask = checks.mask
        # what else needs the frames takes them from the front end's pass
        n = len(source)
        kept = KeptFrames(_debug_numbers(source, o.debug_view)) if o.debug_view != "none" \
            else None
        colmap_images = _colmap_images(tmp, cam, source, o, n)
        if colmap_images is not None:
            stop.callback(colmap_images.close)
        taps = [t for t in (kept, None if colmap_images is None else colmap_images.tap)
                if t is not None]

        def tap(number: int, stamp: float, gray: np.ndarray) -> None:
            for t in taps:
                t(number, stamp, gray)

        fe = track_lines(source, cam, fe_opts, line_mask, tap=tap if taps else None)
        if colmap_images is not None:  # its thread done before the estimator forks
            colmap_images.wait()
            colmap_images.close()
        fe, fixed_ids, auto_said = _without_camera_fixed(fe, o.auto_mask, checks.auto_mask)
        t1 = time.perf_counter()
        tracks, result = _estimate(fe, o, cam)
        t2 = time.perf_counter()

        names = _image_names(source, fe.frame_numbers)
        est_names = [names[f] for f in np.flatnonzero(result.estimated)]
        skipped_not_estimated = [names[f] for f in np.flatnonzero(~result.estimated)]
        unreadable = _image_names(source, np.asarray(fe.frames_skipped, dtype=int))
        report = _init_report(result.report, images, camera, cam, mask, output, o, source, fe,
                              unreadable, skipped_not_estimated,
                              {"front_end": t1 - t0, "estimation": t2 - t1}, checks, fixed_ids)
        write_init_outputs(tmp, result, report, keep_uncertain=o.keep_uncertain)
        write_tracks(tmp / InitFolder.TRACKS, tracks)
        write_lines3d(tmp / InitFolder.LINES3D, estimated_segments(fe, result))
        if line_mask is not None:  # the user's mask and the automatic one: what refine uses
            write_mask(tmp / InitFolder.MASK, line_mask)
        plot_trajectory(tmp / InitFolder.TRAJECTORY_PLOT, result.trajectory)
        if kept is not None:
            _write_debug(tmp, images, cam, o, fe, result, kept, n)
        if o.colmap:
            keep = np.ones(len(est_names), bool) if o.keep_uncertain else trusted(result)
            model_names = [n for n, k in zip(est_names, keep, strict=True) if k]
            write_init_model(tmp, cam, result.trajectory.subset(keep), model_names,
                             text=o.colmap_text, metres_per_unit=_rig_scale(tmp, cam, output))
            if colmap_images is not None:
                colmap_images.keep(model_names)
    return InitResult(output=output, camera=cam, frontend=fe, estimation=result,
                      image_names=tuple(est_names), not_estimated=tuple(skipped_not_estimated),
                      unreadable=tuple(unreadable),
                      unreadable_reasons=fe.frames_skipped_reasons,
                      warnings=checks.warnings, auto_mask=auto_said)


def _rig_scale(tmp: Path, cam: CameraModel, output: Path) -> float | None:
    """A rig camera's metric scale, from the ``report.json`` written in ``tmp`` (the output
    ``output`` becomes; :func:`~omni_sfm.export.colmap_lenses.rig_metres_per_unit`); None for
    any other camera."""
    from omni_sfm.cameras import RigCamera
    from omni_sfm.export.colmap_lenses import rig_metres_per_unit

    return rig_metres_per_unit(tmp, shown_as=output) if isinstance(cam, RigCamera) else None


def _colmap_images(tmp: Path, cam: CameraModel, source: FrameSource, o: InitOptions,
                   n: int) -> ColmapImages | None:
    """The COLMAP image writer fed from the front end's pass, when the images are written."""
    from omni_sfm.export.colmap import ColmapImages

    if not (o.colmap and (o.colmap_images or (o.colmap_images is None and
                                              n <= COLMAP_IMAGE_FRAMES))):
        return None
    return ColmapImages(tmp, cam, lambda k: _image_names(source, np.asarray([k]))[0],
                        background=True)


def _without_camera_fixed(fe: FrontEndResult, auto_mask: bool,
                          auto_said: str) -> tuple[FrontEndResult, list[int], str]:
    """With the automatic mask, drop what it left of structure fixed to the camera."""
    fixed_ids: list[int] = []
    if auto_mask:
        fixed = fe.camera_fixed_tracks()
        if fixed.any():
            fixed_ids = fe.tracks.track_ids[fixed].tolist()
            fe = fe.without_tracks(fixed)
            auto_said += f"; {len(fixed_ids)} line tracks fixed to the camera dropped"
    return fe, fixed_ids, auto_said


def _estimate(fe: FrontEndResult, o: InitOptions,
              camera: CameraModel) -> tuple[LineTracks, EstimationResult]:
    """The estimator's tracks and poses; errors name the images' likely problem."""
    too_few = fe.why_too_few_lines()
    if too_few:
        raise OmniSfmError(too_few)
    tracks = fe.estimator_tracks(camera)
    try:
        result = estimate_poses(tracks, replace(o.estimation, progress=o.progress))
    except OmniSfmError as exc:
        problem = fe.image_problem()  # the likely cause, where the images have one
        if problem:
            raise OmniSfmError(f"{exc} ({problem})") from exc
        raise
    return tracks, result


def _init_report(report: InitReport, images: Path | str,
                 camera: Path | str | CameraModel | None, cam: CameraModel,
                 mask: Path | str | None, output: Path, o: InitOptions, source: FrameSource,
                 fe: FrontEndResult, unreadable: list[str], skipped_not_estimated: list[str],
                 wall_time_s: dict[str, float], checks: _Checks,
                 fixed_ids: list[int]) -> InitReport:
    """The estimator's ``report`` with what ``init`` adds to it."""
    front_end = fe.summary()
    front_end = replace(front_end, frames_skipped_reasons=[
        replace(entry, name=name)
        for entry, name in zip(front_end.frames_skipped_reasons, unreadable, strict=True)])
    return replace(
        report,
        input=InitInput(images=stored_path(images, output),
                        camera=_camera_entry(camera, cam, output),
                        mask=None if mask is None else stored_path(mask, output),
                        start=o.start, end=o.end, step=o.step,
                        timestamps="seconds" if source.is_video else "frame index"),
        front_end=front_end,
        front_end_per_frame=fe.per_frame(),
        frames_not_estimated_names=skipped_not_estimated,
        wall_time_s=wall_time_s,
        camera_check=checks.camera_check,
        auto_mask=checks.auto_mask_report,
        camera_fixed_tracks=fixed_ids,
        warnings=list(checks.warnings))


def _write_debug(tmp: Path, images: Path | str, cam: CameraModel, o: InitOptions,
                 fe: FrontEndResult, result: EstimationResult, kept: KeptFrames,
                 n: int) -> None:
    """The debug view: frames kept from the front end's pass, or the frames read again."""
    from omni_sfm.lines.debug import write_debug_view

    # colour 0: the parallel family, 1: other lines, grey (-1): rejected as outliers
    groups = np.where(result.outliers, -1, np.where(result.parallel, 0, 1))
    target = tmp / (InitFolder.DEBUG_VIDEO if o.debug_view == "mp4"
                    else InitFolder.DEBUG_FRAMES)
    # a video whose container gives no frame count (n = 0) is read again
    from_pass = n > 0 and (len(kept.numbers) >= n or o.debug_view == "auto")
    frames = kept if from_pass else read_frames(images, o.start, o.end, o.step,
                                                size=(cam.width, cam.height),
                                                size_error=cam.frame_size_mismatch)
    write_debug_view(frames, cam, fe, target, groups=groups, progress=o.progress)


DEBUG_VIEWS = ("auto", "png", "mp4", "none")


def _debug_numbers(source: FrameSource, view: str) -> list[int]:
    """Source indices of the frames the debug view draws from the front end's pass: every
    frame of a run of at most :data:`DEBUG_FRAMES`; of a longer one, that many spread evenly
    (``auto``) or none (``png``, ``mp4``: the frames are read again, as they are for a video
    whose length is unknown)."""
    n = len(source)
    if n <= DEBUG_FRAMES:
        ks = np.arange(n)
    elif view == "auto":
        ks = np.unique(np.linspace(0, n - 1, DEBUG_FRAMES).round().astype(int))
    else:
        ks = np.zeros(0, int)
    return [source.start + source.step * int(k) for k in ks]


@dataclass(frozen=True)
class PluginInitResult:
    """What :func:`init_with_initializer` wrote: the folder, the normalised poses, the names of
    the posed frames (trajectory order; the first is the world frame) and of the others, and
    the ``report.json`` document."""

    output: Path
    trajectory: Trajectory
    image_names: tuple[str, ...]
    not_estimated: tuple[str, ...]
    report: PluginInitReport


def normalised_trajectory(traj: Trajectory) -> Trajectory:
    """``traj`` in ``init``'s convention: world = its first camera, first-to-last camera
    distance = 1 (OmniSfmError when the two coincide, as for the line-based estimate)."""
    rot = np.einsum("ji,njk->nik", traj.rotations[0], traj.rotations)
    return Trajectory(traj.timestamps.copy(), rot, paper_normalised_positions(traj))


def _camera_entry(given: Path | str | CameraModel | None, camera: CameraModel,
                  output: Path | str) -> str:
    """How ``report.json`` records the camera: the file's stored path, else the model's name
    (a model, ``equirectangular`` from the frame size, or the video's metadata)."""
    if isinstance(given, str | Path) and Path(given).is_file():
        return stored_path(given, output)
    return camera.model


def _plugin_rig_scale(cam: CameraModel, res: InitializerResult, name: str
                      ) -> RigScaleRecord | None:
    """A rig camera's metric scale after :func:`normalised_trajectory`, where the initializer
    gives its poses' (``info.metres_per_unit``: ``colmap`` holds the lens offsets in metres);
    None otherwise (the rig's COLMAP side then needs one, and says so)."""
    from omni_sfm.cameras import RigCamera

    m = res.info.get("metres_per_unit")
    if not isinstance(cam, RigCamera) or not isinstance(m, int | float) or not m > 0:
        return None
    if res.trajectory is None:
        return None
    p = res.trajectory.positions
    return RigScaleRecord(metres_per_unit=float(np.linalg.norm(p[-1] - p[0])) * float(m),
                          note=f"{name}: its poses in metres, the lens offsets held",
                          fixed=True)


def init_with_initializer(images: Path | str, camera: Path | str | CameraModel | None,
                          output: Path | str, name: str, *,
                          options: dict[str, Any] | None = None,
                          overwrite: bool = False,
                          note: Callable[[str], None] | None = None) -> PluginInitResult:
    """``omni-sfm init --initializer NAME``: the poses of a registered initializer (a plugin,
    e.g. ``five-point``) on the frames, written as an init folder that ``refine`` and
    ``dense`` take like the line-based one: ``trajectory.tum`` (normalised as ``init``'s),
    ``report.json``, ``camera.yaml`` and the COLMAP model seeded with the poses.

    Raises:
        OmniSfmError: unknown initializer, unreadable frames or camera, or an initializer that
            posed fewer than 3 frames (its reason in the message).
    """
    from omni_sfm.export.colmap import write_init_model
    from omni_sfm.fileio import check_output_dir
    from omni_sfm.plugin_contract import run_initializer, sequence_from_frames

    output = Path(output)
    check_output_dir(output, overwrite=overwrite, inputs=(Path(images),))
    cam = camera_for_frames(camera, images, note=note)
    seq = sequence_from_frames(Path(images), cam)
    assert seq.images is not None  # sequence_from_frames reads frames
    res, seconds = run_initializer(name, seq, options)
    if res.status != "ok" or res.trajectory is None or len(res.trajectory) < 3:
        raise OmniSfmError(f"initializer {name!r} posed no usable trajectory: "
                           f"{res.reason or 'fewer than 3 frames'}")
    traj = normalised_trajectory(res.trajectory)
    frame_of = {float(t): k for k, t in enumerate(seq.timestamps)}
    posed = [frame_of[float(t)] for t in traj.timestamps]
    names = [seq.images.names[k] for k in posed]
    missing = sorted(set(range(seq.num_frames)) - set(posed))
    report = PluginInitReport(
        input=PluginInitInput(images=stored_path(images, output),
                              camera=_camera_entry(camera, cam, output),
                              timestamps="seconds" if seq.images.is_video else "frame index"),
        initializer=name, status=res.status, reason=res.reason,
        info=InitializerInfo.from_json(res.info, f"{name}: info"),
        num_frames=seq.num_frames, num_frames_estimated=len(traj),
        frames_not_estimated_names=[seq.images.names[k] for k in missing],
        wall_time_s={"initializer": seconds},
        scale_convention="world = first estimated camera, first-to-last distance = 1",
        rig=_plugin_rig_scale(cam, res, name))
    with atomic_output_dir(output, overwrite=overwrite, inputs=(Path(images),)) as tmp:
        report.write(tmp / InitFolder.REPORT)
        write_init_model(tmp, cam, traj, names, metres_per_unit=_rig_scale(tmp, cam, output))
    return PluginInitResult(output=output, trajectory=traj, image_names=tuple(names),
                            not_estimated=tuple(seq.images.names[k] for k in missing),
                            report=report)
