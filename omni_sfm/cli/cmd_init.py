"""``omni-sfm init``: initial camera poses of a sequence (docs/estimator.md, docs/formats.md).

Two input modes, mutually exclusive: ``--tracks FILE`` (tracked line normals, ``tracks.json``)
runs the estimator alone; ``--images PATH [--camera FILE]`` (an image folder or a video) runs the
line front end first (:func:`omni_sfm.pipelines.init.init_from_images`). Both share
:func:`omni_sfm.estimate.pipeline.estimate_poses` and
:func:`omni_sfm.estimate.pipeline.write_init_outputs`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from omni_sfm.lines.extract import ExtractionOptions
    from omni_sfm.reports import InitReport


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "init",
        help="estimate initial camera poses from straight lines",
        description="Estimate the pose of every frame from straight lines (the parallel-line "
                    "method of Kawanishi et al. 2012, refined by a line bundle adjustment), from "
                    "an image folder or video (--images, --camera) or from tracked lines "
                    "(--tracks). Writes OUTPUT/trajectory.tum (world_from_cam, world = first "
                    "estimated frame's camera, first-to-last distance = 1) and "
                    "OUTPUT/report.json, plus for images the tracks, a COLMAP model seeded with "
                    "the poses and a debug view; complete or not at all.",
    )
    method = p.add_mutually_exclusive_group()
    method.add_argument("--lines", action="store_true",
                        help="the line-based method (the default): front end, the paper's "
                             "searches, line bundle adjustment")
    method.add_argument("--initializer", metavar="NAME", default=None,
                        help="instead, a registered initializer plugin on the frames (e.g. "
                             "five-point, colmap, upright-3pt; see 'omni-sfm compare'), written "
                             "as an init folder that refine and dense take")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--tracks", type=Path,
                        help="tracked line normals, tracks.json (docs/formats.md)")
    source.add_argument("--images", type=Path,
                        help="folder of images (sorted by name) or a video file")
    p.add_argument("--camera", type=Path,
                   help="camera file (any format omni-sfm reads; docs/cameras.md), or "
                        "'equirectangular' for 360 video (built from the frame size, 2:1 or "
                        "squeezed); without it, an MP4 with spherical-video metadata and a 2:1 "
                        "frame is read as equirectangular")
    p.add_argument("--mask", type=Path, help="mask image: nonzero where pixels may be used")
    p.add_argument("--no-auto-mask", action="store_true",
                   help="do not mask what stays put in the image while the scene moves (the "
                        "operator, a tripod, the mount, the camera's own reflection); by "
                        "default it is found from the frames, reported and written with the "
                        "user's mask as OUTPUT/mask.png")
    p.add_argument("--mask-wobbling", action="store_true",
                   help="the automatic mask also takes edges that wobble a few pixels with "
                        "the camera (a hand holding a 360 camera; docs/frontend.md); off by "
                        "default: a corridor's far end stays within a few pixels too")
    p.add_argument("--strict", action="store_true",
                   help="refuse, instead of warning, when the camera model does not fit the "
                        "images (docs/frontend.md, 'Camera check')")
    p.add_argument("--start", type=int, default=0, help="first frame to use (default 0)")
    p.add_argument("--end", type=int, default=None, help="stop before this frame")
    p.add_argument("--step", type=int, default=1, help="use every STEP-th frame (default 1)")
    p.add_argument("--edge-low", type=float, default=None, metavar="G",
                   help="low edge threshold of line extraction (default 20): Canny on the "
                        "gradient of the smoothed image, in grey levels of a frame whose grey "
                        "levels spread over 80 or more (5th to 95th percentile); darker or "
                        "flatter frames scale both thresholds down (docs/frontend.md, "
                        "'Real footage')")
    p.add_argument("--edge-high", type=float, default=None, metavar="G",
                   help="high edge threshold of line extraction (default 50, same units): "
                        "lower finds fainter edges, and more noise")
    p.add_argument("--debug-view", choices=["auto", "png", "mp4", "none"], default="auto",
                   help="frames with tracked lines coloured by parallel group: auto (default): "
                        "PNGs in OUTPUT/debug/ of every frame of a run of at most 300 frames, "
                        "else of 300 frames spread over it; png: every frame; mp4: every frame "
                        "in OUTPUT/debug.mp4; none. png and mp4 read a longer input twice")
    p.add_argument("--keep-uncertain", action="store_true",
                   help="keep the poses of the frames the data do not fix in trajectory.tum "
                        "(default: they go to trajectory_uncertain.tum, listed with their "
                        "reasons in report.json frames_uncertain, and later stages do without "
                        "them)")
    p.add_argument("--no-colmap", action="store_true",
                   help="do not write the COLMAP model (sparse/, images_colmap/)")
    p.add_argument("--colmap-images", action=argparse.BooleanOptionalAction, default=None,
                   help="write OUTPUT/images_colmap/, the frames as COLMAP's own tools must "
                        "see them (omni-sfm refine reads the input itself); default: for runs "
                        "of at most 1000 frames")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="processes extracting lines while this one decodes and tracks, "
                        "and running the estimator's independent solves at once (its "
                        "windows, starts and adjustments) "
                        "(default: one per CPU core; 1: all in this process); the result is "
                        "the same for any N")
    p.add_argument("--text", action="store_true", help="also write the COLMAP model as text")
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.add_argument("--no-refine", action="store_true",
                   help="skip the bundle adjustment (the paper's method alone)")
    p.add_argument("--estimator", choices=["auto", "paper", "global"], default="auto",
                   help="auto (default): the paper's method where lines seen in every frame "
                        "make one window (the paper's setting), else global; paper: the "
                        "paper's method on that window, then the bundle adjustment; global: "
                        "rotations of all frames at once, positions of all frames at once, one "
                        "bundle adjustment (docs/estimator.md, \"Which estimator runs\")")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def _names(names: list[str], most: int = 5) -> str:
    more = f", ... ({len(names) - most} more)" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def _index_runs(idx: list[int], most: int = 6) -> str:
    """Frame indices as runs (``0-22, 24, 27-29``), the first ``most`` of them."""
    import numpy as np

    from omni_sfm.estimate.segments import runs

    mask = np.zeros(max(idx) + 1, bool)
    mask[idx] = True
    spans = runs(mask)
    text = [f"{a}-{b - 1}" if b - 1 > a else f"{a}" for a, b in spans[:most]]
    return ", ".join(text) + (f", ... ({len(spans) - most} more runs)" if len(spans) > most
                              else "")


def _skipped(names: list[str], reasons: list[str], most: int = 3) -> str:
    """``skipped: ...``: the skipped frames with their reasons, runs of frames with one reason
    as one entry (``000018.png-000029.png: ...``)."""
    runs: list[tuple[str, str, str]] = []
    for name, why in zip(names, reasons, strict=True):
        if runs and runs[-1][2] == why:
            runs[-1] = (runs[-1][0], name, why)
        else:
            runs.append((name, name, why))
    parts = [f"{a}{'' if a == b else '-' + b}: {why}" for a, b, why in runs[:most]]
    more = f"; ... ({len(runs) - most} more, in report.json)" if len(runs) > most else ""
    n = len(names)
    return f"skipped: {n} damaged frame{'' if n == 1 else 's'} ({'; '.join(parts)}{more})"


def summary(rep: InitReport, output: Path, estimated: list[str],
            not_estimated: list[str], unreadable: list[str],
            reasons: list[str] | None = None) -> str:
    """The result lines ``init`` prints on stdout: frames estimated out of all given, the world
    frame, the frames without a pose and why to look in report.json, and the frames skipped
    (``unreadable``) with their ``reasons`` where known. ``rep``: the folder's report."""
    total = rep.num_frames + len(unreadable)
    rms = float("nan") if rep.rms_final_deg is None else rep.rms_final_deg
    lines = [f"init: {len(estimated)} of {total} frames estimated, "
             f"{len(rep.family_track_ids)} parallel lines, "
             f"{len(rep.rejected_tracks or [])} outlier tracks, residual "
             f"{rms:.3g} deg RMS -> {output}",
             f"world: the camera of frame {estimated[0]} (first estimated), "
             + ("rotation only: the camera turned without moving, positions are 0 and the "
                "scale is undetermined" if rep.rotation_only else
                "first-to-last camera distance = 1")]
    if rep.estimator:
        lines.append(f"estimator: {rep.estimator} ({rep.estimator_choice or 'asked for'})")
    segs = rep.segment_list
    n_seg = sum(int(sg.num_frames_estimated) for sg in segs)
    if segs:
        files = [sg.file for sg in segs]
        shown = ", ".join(files) if len(files) <= 3 else f"{files[0]} ... {files[-1]}"
        lines.append(f"segments: {n_seg} more frames in {len(segs)} separate piece"
                     f"{'' if len(segs) == 1 else 's'}, each in its own world and scale "
                     f"({shown}): too few lines link them to the main trajectory")
    if len(not_estimated) > n_seg:
        lines.append(f"not estimated: {len(not_estimated) - n_seg} frames"
                     + (f" besides the segments' {n_seg}" if n_seg else "")
                     + f" ({_names(not_estimated)}; reasons in report.json)")
    if rep.frames_uncertain:
        idx = sorted(int(k) for k in rep.frames_uncertain)
        where = (f"poses in {rep.uncertain_poses}, not in trajectory.tum" if rep.uncertain_poses
                 else "poses in trajectory.tum")
        if rep.num_frames_estimated is not None and len(idx) >= rep.num_frames_estimated:
            lines.append(f"uncertain: every frame estimated ({len(idx)}): the data fix none of "
                         f"them, do not trust this trajectory (frames {_index_runs(idx)}; "
                         f"{where}; reasons in report.json frames_uncertain)")
        else:
            lines.append(f"uncertain: {len(idx)} frames the data do not fix (frames "
                         f"{_index_runs(idx)}; {where}; reasons in report.json "
                         f"frames_uncertain)")
    spread = _expected_error(rep)
    if spread:
        lines.append(spread)
    if unreadable and reasons:
        lines.append(_skipped(unreadable, reasons))
    elif unreadable:
        lines.append(f"unreadable: {len(unreadable)} frames could not be decoded "
                     f"({_names(unreadable)})")
    return "\n".join(lines)


def _expected_error(rep: InitReport) -> str | None:
    """The summary's line on the errors the adjustment's covariance expects of the frames not
    flagged (``report.json`` ``pose_spread``), or None without such figures."""
    spread = rep.pose_spread
    if spread is None:
        return None
    flagged = {int(k) for k in rep.frames_uncertain or {}}
    pairs = [(r, q) for k, (r, q) in enumerate(zip(spread.rotation_deg,
                                                     spread.position_pct_of_path, strict=True))
             if k not in flagged and r is not None and q is not None]
    if not pairs:
        return None
    rot, pos = (sorted(v) for v in zip(*pairs, strict=True))
    return (f"expected error of the {len(pairs)} trusted frames (the adjustment's covariance, "
            f"RMS): median {rot[len(rot) // 2]:.3f} deg and {pos[len(pos) // 2]:.3f} % of the "
            f"path, largest {rot[-1]:.3f} deg and {pos[-1]:.3f} %")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from omni_sfm.errors import OmniSfmError
    from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses, write_init_outputs
    from omni_sfm.fileio import atomic_output_dir, check_output_dir, stored_path
    from omni_sfm.folders import InitFolder
    from omni_sfm.reports import InitInput

    if args.initializer is not None:
        return _run_plugin(args)
    if args.workers is not None and args.workers < 1:
        raise OmniSfmError(f"--workers must be at least 1, got {args.workers}")
    estimation = EstimationOptions(refine=not args.no_refine, progress=not args.quiet,
                                   workers=args.workers, estimator=args.estimator)
    if args.images is not None:
        from omni_sfm.lines.frontend import FrontEndOptions
        from omni_sfm.pipelines.init import InitOptions, init_from_images

        frontend = FrontEndOptions(extraction=_extraction(args), progress=not args.quiet,
                                   workers=args.workers)
        res = init_from_images(
            args.images, args.camera, args.output,
            InitOptions(frontend=frontend, estimation=estimation,
                        start=args.start, end=args.end, step=args.step,
                        debug_view=args.debug_view, colmap=not args.no_colmap,
                        colmap_images=args.colmap_images,
                        colmap_text=args.text, progress=not args.quiet,
                        keep_uncertain=args.keep_uncertain,
                        auto_mask=not args.no_auto_mask, mask_wobbling=args.mask_wobbling,
                        strict=args.strict),
            mask=args.mask, overwrite=args.overwrite,
            warn=lambda text: print(f"omni-sfm: warning: {text}", file=sys.stderr, flush=True),
            note=_note)
        print(summary(InitFolder(args.output).read_report(), args.output,
                      list(res.image_names),
                      list(res.not_estimated), list(res.unreadable),
                      list(res.unreadable_reasons)))
        if res.auto_mask:
            print(res.auto_mask)
        return 0

    for flag in ("camera", "mask", "edge_low", "edge_high", "colmap_images"):
        if getattr(args, flag) is not None:
            raise OmniSfmError(f"--{flag.replace('_', '-')} applies to --images input, not to "
                               "--tracks")
    for flag in ("no_auto_mask", "mask_wobbling", "strict"):
        if getattr(args, flag):
            raise OmniSfmError(f"--{flag.replace('_', '-')} applies to --images input, not to "
                               "--tracks")
    check_output_dir(args.output, overwrite=args.overwrite, inputs=(args.tracks,))
    from omni_sfm.lines.tracks import read_tracks

    tracks = read_tracks(args.tracks)
    result = estimate_poses(tracks, estimation)
    with atomic_output_dir(args.output, overwrite=args.overwrite, inputs=(args.tracks,)) as tmp:
        write_init_outputs(
            tmp, result, replace(result.report,
                                 input=InitInput(tracks=stored_path(args.tracks, args.output))),
            keep_uncertain=args.keep_uncertain)
    frames = [f"{k}" for k in range(tracks.num_frames)]
    est = result.estimated
    print(summary(InitFolder(args.output).read_report(), args.output,
                  [f for f, e in zip(frames, est, strict=True) if e],
                  [f for f, e in zip(frames, est, strict=True) if not e], []))
    return 0


def _note(text: str) -> None:
    """A one-line note on stderr (how the camera was chosen)."""
    print(f"omni-sfm: note: {text}", file=sys.stderr, flush=True)


def _extraction(args: argparse.Namespace) -> ExtractionOptions:
    """The line extraction options of ``--edge-low``/``--edge-high`` (checked here, so a bad
    value is one line, not a traceback)."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.lines.extract import ExtractionOptions

    default = ExtractionOptions()
    low = default.canny_low if args.edge_low is None else args.edge_low
    high = default.canny_high if args.edge_high is None else args.edge_high
    if not 0 < low <= high:
        raise OmniSfmError(f"need 0 < --edge-low <= --edge-high, got {low:g} and {high:g}")
    return ExtractionOptions(canny_low=low, canny_high=high)


def _run_plugin(args: argparse.Namespace) -> int:
    """``init --initializer NAME``: a plugin's poses as an init folder."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.pipelines.init import init_with_initializer

    if args.images is None:
        raise OmniSfmError("--initializer needs --images PATH (and --camera FILE)")
    line_only = {"--mask": args.mask is not None, "--no-refine": args.no_refine,
                 "--start/--end/--step": (args.start, args.end, args.step) != (0, None, 1),
                 "--edge-low/--edge-high": (args.edge_low, args.edge_high) != (None, None),
                 "--no-colmap": args.no_colmap, "--text": args.text,
                 "--no-auto-mask": args.no_auto_mask, "--mask-wobbling": args.mask_wobbling,
                 "--strict": args.strict,
                 "--keep-uncertain": args.keep_uncertain,
                 "--workers": args.workers is not None}
    given = [flag for flag, on in line_only.items() if on]
    if given:
        raise OmniSfmError(f"{given[0]} applies to the line-based method, not --initializer")
    res = init_with_initializer(args.images, args.camera, args.output, args.initializer,
                                overwrite=args.overwrite, note=_note)
    total = len(res.image_names) + len(res.not_estimated)
    print(f"init: {len(res.image_names)} of {total} frames estimated by {args.initializer} "
          f"-> {args.output}")
    print(f"world: the camera of frame {res.image_names[0]} (first estimated), first-to-last "
          "camera distance = 1")
    if res.not_estimated:
        print(f"not estimated: {len(res.not_estimated)} frames ({_names(list(res.not_estimated))};"
              f" {res.report.reason or 'see report.json'})")
    return 0
