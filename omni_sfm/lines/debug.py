"""Debug view: the frames with their tracked lines drawn on them, coloured by group.

Each observation is drawn as the great-circle arc between its two end rays, projected through
the camera model (so curved line images are drawn curved). Colours come from a per-track group
label that the caller passes (e.g. the parallel families of :mod:`omni_sfm.vanishing`; -1 =
no group, drawn grey). Output: a folder of PNGs, or a video when the path ends in ``.mp4``
(OpenCV's ``mp4v``) or ``.avi`` (``MJPG``).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import BackgroundWrites
from omni_sfm.frames import to_gray
from omni_sfm.geometry import FloatArray
from omni_sfm.lines.frontend import FrontEndResult

# BGR, matplotlib's tab10 order: blue, orange, green, red, purple, brown, pink, olive, cyan
PALETTE = np.array([[180, 119, 31], [14, 127, 255], [44, 160, 44], [40, 39, 214],
                    [189, 103, 148], [75, 86, 140], [194, 119, 227], [34, 189, 188],
                    [207, 190, 23]], dtype=np.int64)
UNGROUPED = (150, 150, 150)

VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}
KEPT_JPEG_QUALITY = 95
"""Quality of the frames :class:`KeptFrames` holds (JPEG in memory, for drawing on)."""


class KeptFrames:
    """Frames kept from the front end's pass for the debug view drawn after the estimate (a
    :data:`~omni_sfm.lines.frontend.FrameTap`): those whose source index is in ``numbers``,
    held as JPEG in memory, so the input is decoded once and the memory is bounded by the
    number kept. Iterate it for ``(index, timestamp, grey image)`` in order, as
    :func:`write_debug_view` takes them."""

    def __init__(self, numbers: Iterable[int]) -> None:
        self.numbers = {int(n) for n in numbers}
        self._kept: list[tuple[int, float, bytes]] = []

    def __call__(self, number: int, stamp: float, gray: np.ndarray) -> None:
        if int(number) in self.numbers:
            ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, KEPT_JPEG_QUALITY])
            if not ok:
                raise OmniSfmError(f"frame {number}: cannot encode it for the debug view")
            self._kept.append((int(number), float(stamp), buf.tobytes()))

    def __len__(self) -> int:
        return len(self._kept)

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        for number, stamp, data in self._kept:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise OmniSfmError(f"frame {number}: the kept copy does not decode")
            yield number, stamp, np.asarray(img)


def group_colour(group: int) -> tuple[int, int, int]:
    """BGR colour of a group label (-1: grey)."""
    if group < 0:
        return UNGROUPED
    c = PALETTE[group % len(PALETTE)]
    return int(c[0]), int(c[1]), int(c[2])


def arc_polylines(camera: CameraModel, endpoint_rays: FloatArray,
                  step_deg: float = 0.5) -> list[list[np.ndarray]]:
    """Pixel polylines of the great-circle arcs between ``(K, 2, 3)`` end rays.

    Returns, per arc, a list of ``(n, 2)`` float pixel arrays (an arc is cut where the camera
    does not image it or where it jumps, e.g. across the equirectangular seam).
    """
    a, b = endpoint_rays[:, 0], endpoint_rays[:, 1]
    theta = np.arccos(np.clip(np.einsum("kc,kc->k", a, b), -1.0, 1.0))
    n = np.clip(np.ceil(np.degrees(theta) / step_deg).astype(np.int64) + 1, 2, 2000)
    arc = np.repeat(np.arange(len(a)), n)
    s = (np.arange(len(arc)) - np.repeat(np.cumsum(n) - n, n)) / (n[arc] - 1)
    th = theta[arc]
    with np.errstate(invalid="ignore", divide="ignore"):
        sin_t = np.sin(th)
        wa = np.where(sin_t > 1e-9, np.sin((1 - s) * th) / sin_t, 1 - s)
        wb = np.where(sin_t > 1e-9, np.sin(s * th) / sin_t, s)
    rays = wa[:, None] * a[arc] + wb[:, None] * b[arc]
    uv = camera.pixels_from_rays(rays) if len(rays) else np.zeros((0, 2))
    jump = 0.25 * max(camera.width, camera.height)
    out: list[list[np.ndarray]] = []
    starts = np.concatenate([[0], np.cumsum(n)])
    for k in range(len(a)):
        p = uv[starts[k] : starts[k + 1]]
        bad = ~np.isfinite(p).all(axis=1)
        step = np.zeros(len(p), bool)
        step[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > jump
        piece = np.cumsum(bad | step)
        pieces = [p[(piece == q) & ~bad] for q in np.unique(piece)]
        out.append([q for q in pieces if len(q) >= 2])
    return out


def draw_lines(image: np.ndarray, camera: CameraModel, endpoint_rays: FloatArray,
               colours: list[tuple[int, int, int]], labels: list[str] | None = None,
               thickness: int = 2) -> np.ndarray:
    """A BGR copy of ``image`` with the arcs of ``(K, 2, 3)`` end rays drawn in ``colours``."""
    img = image if image.ndim == 3 else cv2.cvtColor(to_gray(image), cv2.COLOR_GRAY2BGR)
    img = np.ascontiguousarray(img.copy())
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    for k, pieces in enumerate(arc_polylines(camera, endpoint_rays)):
        pts = [np.round(q * (1 << shift)).astype(np.int32).reshape(-1, 1, 2) for q in pieces]
        if pts:
            cv2.polylines(img, pts, False, colours[k], thickness, cv2.LINE_AA, shift)
            if labels is not None:
                m = pieces[0][len(pieces[0]) // 2]
                cv2.putText(img, labels[k], (int(m[0]) + 3, int(m[1]) - 3),
                            cv2.FONT_HERSHEY_PLAIN, 0.9, colours[k], 1, cv2.LINE_AA)
    return img


def write_debug_view(frames: Iterable[tuple[int, float, np.ndarray]], camera: CameraModel,
                     result: FrontEndResult, output: Path | str,
                     groups: np.ndarray | None = None, fps: float = 15.0,
                     label_tracks: bool = False, progress: bool = False) -> Path:
    """Draw every frame of ``result`` with its tracked lines and write PNGs or a video.

    Args:
        frames: the frames ``result`` was computed from (matched by their source index).
        groups: ``(M,)`` int group label per track (-1: none); None draws all grey.
        output: a folder (PNGs ``NNNNNN.png``, named by source index) or a ``.mp4``/``.avi``
            file.
        label_tracks: write each track's id next to its line.
        progress: a progress bar on stderr.
    Returns the path written.
    """
    output = Path(output)
    tr = result.tracks
    g = np.full(tr.num_tracks, -1, np.int64) if groups is None else np.asarray(groups)
    if g.shape != (tr.num_tracks,):
        raise ValueError(f"groups must have shape ({tr.num_tracks},), got {g.shape}")
    frame_of = {int(n): f for f, n in enumerate(result.frame_numbers)}
    suffix = output.suffix.lower()
    writer = None
    if suffix in VIDEO_CODECS:
        output.parent.mkdir(parents=True, exist_ok=True)
        writer = cv2.VideoWriter(str(output), cv2.VideoWriter.fourcc(*VIDEO_CODECS[suffix]),
                                 float(fps), (camera.width, camera.height))
        if not writer.isOpened():
            raise OmniSfmError(f"{output}: OpenCV cannot write a {VIDEO_CODECS[suffix]} video "
                               "here; give a folder for PNGs instead")
    elif suffix:
        raise OmniSfmError(f"{output}: debug view must be a folder, a .mp4 or an .avi file")
    else:
        output.mkdir(parents=True, exist_ok=True)
    total = len(frames) if hasattr(frames, "__len__") else None  # type: ignore[arg-type]

    def drawn(image: np.ndarray, f: int) -> np.ndarray:
        sel = np.flatnonzero(tr.obs_frame == f)
        tid = tr.obs_track[sel]
        colours = [group_colour(int(g[t])) for t in tid]
        labels = [str(int(tr.track_ids[t])) for t in tid] if label_tracks else None
        return draw_lines(image, camera, result.obs_endpoint_rays[sel], colours, labels)

    def png(number: int, image: np.ndarray, f: int) -> None:
        if not cv2.imwrite(str(output / f"{int(number):06d}.png"), drawn(image, f),
                           [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OmniSfmError(f"{output}: could not write frame {number}")

    # PNGs: drawn and written in threads (OpenCV's drawing and encoding release the GIL)
    threads = 1 if writer is not None else min(2, os.cpu_count() or 1)
    try:
        with BackgroundWrites(threads, pending=2 * threads) as writes:
            for number, _, image in tqdm(frames, total=total, desc="debug view", unit="frame",
                                         leave=False, disable=None if progress else True):
                f = frame_of.get(int(number))
                if f is None:
                    continue
                if writer is not None:
                    writer.write(drawn(image, f))
                else:
                    writes.submit(png, number, image, f)
    finally:
        if writer is not None:
            writer.release()
    return output
