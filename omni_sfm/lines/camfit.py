"""Does the camera model fit the images? (docs/frontend.md, "Camera check").

A wrong camera file (a COLMAP ``PINHOLE`` on catadioptric frames, a mirror model on
equirectangular frames) still yields "lines" and poses, only wrong ones. Four figures, each
measured on a few frames, tell it; each has a limit far from what the right model gives on
every rendered sequence (docs/frontend.md gives the measurements):

- ``bent_lines``: of the long lines the extractor accepts (at least ``long_line_points``
  points), the fraction whose residual from their great circle has a smooth bow (the cubic
  fitted to the signed residual along the line) above ``bow_px`` RMS. Through the right
  model a straight edge lies on its great circle up to the edge noise; through a wrong one the
  extractor accepts conics that fit within its 1 px threshold only by bending across it.
- ``straight_in_image_curved_on_sphere``: of the long straight segments of the image itself
  (OpenCV's LSD), the fraction whose pixels lie more than ``curved_px`` RMS from a great
  circle through the model. Every camera model maps image-straight edges of a pinhole image,
  the radial edges of a mirror image and the vertical ones of a panorama to great circles.
- ``empty_valid``: the fraction of the model's valid pixels that are black in every frame
  (a model whose valid region is larger than the image's circle).
- ``moving_outside``: the fraction of the pixels that change between frames that lie outside
  the model's valid region (a model whose valid region misses part of the picture).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import to_gray
from omni_sfm.geometry import completion_towards, smallest_eigenvector
from omni_sfm.lines.extract import (
    ExtractedLines,
    ExtractionOptions,
    LineExtractor,
    angular_pixel_scale,
)


@dataclass(frozen=True, kw_only=True)
class CameraFitOptions:
    """Limits of :func:`check_camera_fit` (pixel units unless stated)."""

    long_line_points: int = 60
    """Lines with at least this many points are tested for a bow."""
    bow_px: float = 0.25
    """A line bows if the smooth part of its residual exceeds this RMS (px)."""
    max_bent_lines: float = 0.15
    """Most ``bent_lines`` the right model may give."""
    min_long_lines: int = 8
    """Fewest long lines (all frames together) for ``bent_lines`` to count."""
    segment_px: float = 40.0
    """Shortest LSD segment of the image tested for ``straight_in_image_curved_on_sphere``."""
    curved_px: float = 1.5
    """An image-straight segment is curved on the sphere beyond this RMS (px)."""
    max_curved_segments: float = 0.10
    """Most ``straight_in_image_curved_on_sphere`` the right model may give."""
    min_segments: int = 8
    """Fewest LSD segments (all frames together) for that figure to count."""
    black_grey: float = 12.0
    """A pixel is black if its smoothed grey level stays below this (or below a tenth of the
    frames' bright end, the 99th percentile of each pixel's brightest value, if that is less)
    in every frame; frames whose bright end is below 2/3 of it are too dark to tell."""
    max_empty_valid: float = 0.2
    """Most ``empty_valid`` the right model may give."""
    moving_grey: float = 4.0
    """A pixel changes between frames if its smoothed grey level's standard deviation over
    the frames exceeds this."""
    max_moving_outside: float = 0.35
    """Most ``moving_outside`` the right model may give."""


@dataclass(frozen=True)
class CameraFit:
    """The verdict of :func:`check_camera_fit`.

    Attributes:
        ok: False if any figure is beyond its limit.
        figures: the four figures (fractions, NaN where too few lines or segments to tell),
            ``median_residual_px`` (median RMS distance of the accepted lines from their great
            circles) and the counts they rest on.
        message: one line: the worst figure against its limit, or that the model fits.
    """

    ok: bool
    figures: dict[str, float]
    message: str


def _bows(lines: ExtractedLines, scale: np.ndarray, min_points: int) -> list[float]:
    """RMS (px) of the smooth part (a cubic in the arc parameter) of the signed great-circle
    residual of each line with at least ``min_points`` points."""
    out = []
    for k in range(lines.num_lines):
        a, b = int(lines.offsets[k]), int(lines.offsets[k + 1])
        if b - a < min_points:
            continue
        r = lines.point_rays[a:b]
        n = lines.normals[k]
        uv = np.rint(lines.points_uv[a:b]).astype(np.int64)
        d = (r @ n) / scale[uv[:, 1], uv[:, 0]].astype(np.float64)
        e1, e2 = completion_towards(n, r.mean(axis=0))
        t = np.arctan2(r @ e2, r @ e1)
        t = 2.0 * (t - t.min()) / max(float(np.ptp(t)), 1e-12) - 1.0
        basis = np.stack([np.ones_like(t), t, t * t, t ** 3], axis=1)
        coef = np.linalg.lstsq(basis, d, rcond=None)[0]
        smooth = basis @ coef
        out.append(float(np.sqrt(np.mean((smooth - smooth.mean()) ** 2))))
    return out


def _segment_curvatures(gray: np.ndarray, camera: CameraModel, usable: np.ndarray,
                        scale: np.ndarray, min_len: float) -> list[float]:
    """RMS distance (px) from the best great circle of the pixels along each long straight
    segment that OpenCV's LSD finds in the image (segments leaving ``usable`` are skipped)."""
    lsd = cv2.createLineSegmentDetector()
    found = lsd.detect(cv2.GaussianBlur(gray, (5, 5), 1.0))[0]
    if found is None:
        return []
    segs = found.reshape(-1, 4).astype(np.float64)
    segs = segs[np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]) >= min_len]
    h, w = gray.shape
    out = []
    for x0, y0, x1, y1 in segs:
        t = np.linspace(0.05, 0.95, int(np.hypot(x1 - x0, y1 - y0)))
        uv = np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], axis=1)
        iu = np.clip(np.rint(uv).astype(np.int64), 0, [w - 1, h - 1])
        if not usable[iu[:, 1], iu[:, 0]].all():
            continue
        r = camera.rays_from_pixels(uv)
        if not np.isfinite(r).all():
            continue
        n = smallest_eigenvector(r.T @ r)
        d = (r @ n) / scale[iu[:, 1], iu[:, 0]].astype(np.float64)
        out.append(float(np.sqrt(np.mean(d * d))))
    return out


def _coverage(grays: Sequence[np.ndarray], valid: np.ndarray, user: np.ndarray,
              o: CameraFitOptions) -> tuple[float, float]:
    """``(empty_valid, moving_outside)`` of the frames against the model's valid mask
    ``valid``, both counted only where the user's mask ``user`` allows (NaN where it allows
    nothing to count)."""
    sm = np.stack([cv2.GaussianBlur(g, (5, 5), 1.5).astype(np.float32) for g in grays])
    brightest = sm.max(axis=0)
    # dark footage: "black" is relative to the frames' bright end; frames with (almost) no
    # bright pixels at all are too dark to tell (the front end says so), not a misfit
    top = float(np.percentile(brightest, 99))
    if top < 2.0 * o.black_grey / 3.0:
        empty = float("nan")
    else:
        black = brightest < min(o.black_grey, 0.1 * top)
        inside = valid & user
        empty = float((black & inside).sum()) / int(inside.sum()) if inside.any() \
            else float("nan")
    if len(grays) < 2:
        return empty, float("nan")
    moving = (sm.std(axis=0) > o.moving_grey) & user
    outside = float((moving & ~valid).sum()) / int(moving.sum()) if moving.any() \
        else float("nan")
    return empty, outside


def check_camera_fit(frames: Sequence[np.ndarray], camera: CameraModel,
                     mask: np.ndarray | None = None,
                     extraction: ExtractionOptions | None = None,
                     options: CameraFitOptions | None = None) -> CameraFit:
    """Check that ``camera`` fits the frames (module docstring).

    Args:
        frames: a few ``(H, W)`` uint8 grey frames spread over the sequence (4-6 suffice;
            each costs one line extraction and one LSD pass).
        camera: the camera model to check; frames must be its size.
        mask: optional ``(H, W)`` array, nonzero where the image may be used.
        extraction: the line extraction's options (as the front end will use them).
        options: the limits (:class:`CameraFitOptions`).
    """
    o = options or CameraFitOptions()
    if len(frames) == 0:
        raise ValueError("check_camera_fit needs at least one frame")
    extractor = LineExtractor(camera, extraction, mask)
    grays = [to_gray(f) for f in frames]
    for g in grays:
        if g.shape != (camera.height, camera.width):
            raise OmniSfmError(f"image is {g.shape[1]}x{g.shape[0]} px but the camera is "
                               f"{camera.width}x{camera.height} px")
    scale = angular_pixel_scale(camera)
    usable = extractor.search_mask > 0
    bows: list[float] = []
    curv: list[float] = []
    resid: list[float] = []
    for g in grays:
        lines = extractor.extract(g)
        bows += _bows(lines, scale, o.long_line_points)
        resid += lines.residual_px.tolist()
        curv += _segment_curvatures(g, camera, usable, scale, o.segment_px)
    user = np.ones(camera.valid_mask().shape, bool) if mask is None else np.asarray(mask) > 0
    empty, outside = _coverage(grays, camera.valid_mask(), user, o)
    nan = float("nan")
    bent = float(np.mean(np.asarray(bows) > o.bow_px)) if len(bows) >= o.min_long_lines \
        else nan
    curved = float(np.mean(np.asarray(curv) > o.curved_px)) if len(curv) >= o.min_segments \
        else nan
    figures = {"bent_lines": bent, "straight_in_image_curved_on_sphere": curved,
               "empty_valid": empty, "moving_outside": outside,
               "median_residual_px": float(np.median(resid)) if resid else nan,
               "long_lines": float(len(bows)), "image_segments": float(len(curv))}
    tests = [
        ("bent_lines", o.max_bent_lines,
         f"of the long lines bow off their great circle by more than {o.bow_px:g} px"),
        ("straight_in_image_curved_on_sphere", o.max_curved_segments,
         "of the long edges straight in the image are curved on the sphere "
         f"(> {o.curved_px:g} px off a great circle)"),
        ("empty_valid", o.max_empty_valid,
         "of the model's valid pixels are black in every frame"),
        ("moving_outside", o.max_moving_outside,
         "of the changing pixels lie outside the model's valid region"),
    ]
    failed = [(figures[k] / lim, k, lim, text) for k, lim, text in tests
              if np.isfinite(figures[k]) and figures[k] > lim]
    if not failed:
        return CameraFit(True, figures,
                         f"the camera model fits the images ({len(bows)} long lines, "
                         f"{100 * bent:.0f} % bent; median line residual "
                         f"{figures['median_residual_px']:.2f} px)" if np.isfinite(bent)
                         else "the camera model fits the images as far as can be told "
                              f"({len(bows)} long lines)")
    _, key, lim, text = max(failed)
    return CameraFit(False, figures,
                     f"the camera model does not fit the images: {100 * figures[key]:.0f} % "
                     f"{text} (expected < {100 * lim:.0f} %); check the camera file")
