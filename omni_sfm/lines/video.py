"""Frames from an image folder or a video file, as 8-bit grey images, with one-line errors.

``read_frames(path, start, end, step)`` returns a :class:`FrameSource`: iterate it for
:class:`Frame` tuples ``(index, timestamp, image)``. Image folders: files sorted by name,
``timestamp`` = frame index. Video files (anything OpenCV's ``VideoCapture`` opens):
``timestamp`` = frame index / frame rate in seconds (the frame index if the file has no rate).
Frames that fail to decode are skipped and listed in ``FrameSource.skipped``; a file that cannot
be opened, a folder without images or an image whose size differs from the camera's is an
:class:`OmniSfmError`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from omni_sfm.errors import OmniSfmError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
"""File name endings (case-insensitive) read from an image folder."""

MAX_CONSECUTIVE_FAILURES = 25
"""A video is taken to end after this many frames in a row fail to decode."""


class Frame(NamedTuple):
    """One frame: ``number`` (index in the source), ``timestamp`` (frame index or seconds),
    ``image`` ``(H, W)`` uint8 grey."""

    number: int
    timestamp: float
    image: np.ndarray


def to_gray(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 grey from a grey, BGR or BGRA image (8 or 16 bit)."""
    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2:
        raise ValueError(f"cannot make a grey image from an array of shape {img.shape}")
    return np.ascontiguousarray(img)


@dataclass
class FrameSource:
    """Iterable frames of an image folder or a video (see module docstring).

    ``size`` ``(width, height)``: if set, every frame must have it (an OmniSfmError names both
    sizes). ``skipped`` lists the source indices of frames that could not be decoded.
    """

    path: Path
    start: int = 0
    end: int | None = None
    step: int = 1
    size: tuple[int, int] | None = None
    skipped: list[int] = field(default_factory=list)
    is_video: bool = False
    fps: float | None = None
    files: list[Path] = field(default_factory=list)
    frame_count: int | None = None

    def __len__(self) -> int:
        """Number of frames the range selects (an estimate for videos without a frame count)."""
        total = len(self.files) if not self.is_video else (self.frame_count or 0)
        end = total if self.end is None else min(self.end, total)
        return max(0, -(-(end - self.start) // self.step))

    def __iter__(self) -> Iterator[Frame]:
        return self._iter_video() if self.is_video else self._iter_folder()

    def _check_size(self, img: np.ndarray, where: str) -> None:
        if self.size is not None and (img.shape[1], img.shape[0]) != self.size:
            raise OmniSfmError(
                f"{where}: image is {img.shape[1]}x{img.shape[0]} px but the camera file says "
                f"{self.size[0]}x{self.size[1]} px")

    def _iter_folder(self) -> Iterator[Frame]:
        end = len(self.files) if self.end is None else min(self.end, len(self.files))
        for i in range(self.start, end, self.step):
            f = self.files[i]
            img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if img is None:
                self.skipped.append(i)
                continue
            gray = to_gray(img)
            self._check_size(gray, str(f))
            yield Frame(i, float(i), gray)

    def _iter_video(self) -> Iterator[Frame]:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise OmniSfmError(f"{self.path}: OpenCV cannot open this video")
        try:
            i = 0
            pending: list[int] = []  # failed wanted frames, reported once a later frame decodes
            fails = 0
            while self.end is None or i < self.end:
                if self.frame_count is not None and i >= self.frame_count:
                    break
                wanted = i >= self.start and (i - self.start) % self.step == 0
                ok = cap.grab()
                img = None
                if ok and wanted:
                    ok, img = cap.retrieve()
                    ok = ok and img is not None
                i += 1
                if not ok:
                    fails += 1
                    if wanted:
                        pending.append(i - 1)
                    if fails >= MAX_CONSECUTIVE_FAILURES:
                        pending.clear()  # the stream ended early (a wrong frame count)
                        break
                    continue
                fails = 0
                self.skipped.extend(pending)
                pending.clear()
                if img is not None:
                    gray = to_gray(img)
                    self._check_size(gray, f"{self.path} frame {i - 1}")
                    ts = (i - 1) / self.fps if self.fps else float(i - 1)
                    yield Frame(i - 1, ts, gray)
            if self.frame_count is not None:
                # failures before the announced end are bad frames, not the end of the stream
                self.skipped.extend(pending)
        finally:
            cap.release()


def read_frames(path: Path | str, start: int = 0, end: int | None = None, step: int = 1,
                size: tuple[int, int] | None = None) -> FrameSource:
    """Frames ``start, start + step, ... < end`` of an image folder or a video file.

    ``size`` ``(width, height)``: the camera's image size, checked on every frame.
    """
    path = Path(path)
    for name, val in (("start", start), ("step", step)):
        if isinstance(val, bool) or not isinstance(val, int | np.integer):
            raise OmniSfmError(f"{name} must be an integer, got {val!r}")
    if start < 0:
        raise OmniSfmError(f"start must be >= 0, got {start}")
    if step < 1:
        raise OmniSfmError(f"step must be >= 1, got {step}")
    if end is not None and end <= start:
        raise OmniSfmError(f"end ({end}) must be greater than start ({start})")
    if not path.exists():
        raise OmniSfmError(f"{path}: no such file or folder")
    if path.is_dir():
        files = sorted(p for p in path.iterdir()
                       if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise OmniSfmError(f"{path}: folder holds no images "
                               f"({', '.join(IMAGE_SUFFIXES)})")
        if start >= len(files):
            raise OmniSfmError(f"{path}: start {start} is beyond the last of {len(files)} "
                               "images")
        return FrameSource(path=path, start=start, end=end, step=step, size=size, files=files)
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise OmniSfmError(f"{path}: not an image folder, and OpenCV cannot open it as a "
                               "video")
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()
    return FrameSource(path=path, start=start, end=end, step=step, size=size, is_video=True,
                       fps=fps if fps > 0 and np.isfinite(fps) else None,
                       frame_count=count if count > 0 else None)


def read_mask(path: Path | str, size: tuple[int, int]) -> np.ndarray:
    """A mask image (nonzero = use the pixel) as ``(H, W)`` bool; its size must be ``size``
    ``(width, height)``."""
    path = Path(path)
    if not path.is_file():
        raise OmniSfmError(f"{path}: mask file not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise OmniSfmError(f"{path}: OpenCV cannot read this mask image")
    gray = to_gray(img)
    if (gray.shape[1], gray.shape[0]) != tuple(size):
        raise OmniSfmError(f"{path}: mask is {gray.shape[1]}x{gray.shape[0]} px but the camera "
                           f"file says {size[0]}x{size[1]} px")
    return np.asarray(gray > 0)


def write_mask(path: Path | str, mask: np.ndarray) -> None:
    """Write a ``(H, W)`` bool mask as an 8-bit PNG (255 = use the pixel) that
    :func:`read_mask` reads back."""
    if not cv2.imwrite(str(path), np.where(mask, 255, 0).astype(np.uint8)):
        raise OmniSfmError(f"{path}: OpenCV cannot write the mask image")


def video_frame_name(index: int) -> str:
    """The name of video frame ``index`` wherever omni-sfm names frames (``000012.png``): in
    trajectories' image lists, the COLMAP model and ``images_colmap/``."""
    return f"{int(index):06d}.png"


class FrameStore:
    """The frames of an image folder or a video, by name, for the stages after ``init``.

    Names are those ``init`` gives the frames: an image folder's file names (sorted), a video's
    :func:`video_frame_name` of each frame index. ``timestamps`` are ``init``'s too: the index
    in the folder, or seconds in the video (the index where the video has no frame rate).
    Reading a video by name decodes forward from the last frame read (reopening only to go
    back), so reading in frame order decodes the file once. Every failure is a one-line
    :class:`OmniSfmError`.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._cache: dict[str, np.ndarray] = {}
        self._cap: cv2.VideoCapture | None = None
        self._next = 0
        if not self.path.exists():
            raise OmniSfmError(f"{self.path}: no such image folder or video file")
        # the folder listing, or the video's frame rate and count, as init reads them
        src = read_frames(self.path)
        self.is_video = src.is_video
        if not src.is_video:
            self.names: tuple[str, ...] = tuple(f.name for f in src.files)
            self.timestamps = np.arange(len(self.names), dtype=np.float64)
            return
        count = src.frame_count
        if count is None:  # the container does not say: count what decodes
            count = 1 + max((f.number for f in src), default=-1)
        self.names = tuple(video_frame_name(i) for i in range(count))
        idx = np.arange(count, dtype=np.float64)
        self.timestamps = idx / src.fps if src.fps else idx
        self._index = {n: i for i, n in enumerate(self.names)}

    def __len__(self) -> int:
        return len(self.names)

    def __getstate__(self) -> dict[str, object]:
        # worker processes get the names and paths; each opens the video itself
        return {**self.__dict__, "_cap": None, "_next": 0, "_cache": {}}

    def read(self, name: str, *, gray: bool = False) -> np.ndarray:
        """Frame ``name`` as OpenCV reads it: BGR ``(H, W, 3)`` uint8, or grey ``(H, W)`` with
        ``gray`` (converted as :func:`to_gray`, like the front end's frames)."""
        if name not in self._cache:
            img = self._read_video(name) if self.is_video else \
                cv2.imread(str(self.path / name), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise OmniSfmError(f"{self.where(name)}: OpenCV cannot read this frame")
            if len(self._cache) >= 8:
                self._cache.pop(next(iter(self._cache)))
            self._cache[name] = img
        img = self._cache[name]
        if gray:
            return to_gray(img)
        if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
            return img
        if img.ndim == 3 and img.shape[2] == 4 and img.dtype == np.uint8:
            return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        return cv2.cvtColor(to_gray(img), cv2.COLOR_GRAY2BGR)

    def where(self, name: str) -> str:
        """The frame's file, or the video and frame index, for messages."""
        if self.is_video:
            return f"{self.path} frame {self._index.get(name, name)}"
        return str(self.path / name)

    def _read_video(self, name: str) -> np.ndarray | None:
        if name not in self._index:
            raise OmniSfmError(f"{self.path}: the video has no frame {name!r} (frames are named "
                               f"{video_frame_name(0)} to {self.names[-1]})")
        i = self._index[name]
        if self._cap is None or i < self._next:
            self.close()
            self._cap = cv2.VideoCapture(str(self.path))
            self._next = 0
        while self._next < i:
            if not self._cap.grab():
                return None
            self._next += 1
        ok, img = self._cap.read()
        self._next += 1
        return img if ok else None

    def close(self) -> None:
        """Release the video (reading again reopens it)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None
