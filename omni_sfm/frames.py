"""Frames from an image folder or a video file, as 8-bit grey images, with one-line errors.

``read_frames(path, start, end, step)`` returns a :class:`FrameSource`: iterate it for
:class:`Frame` tuples ``(index, timestamp, image)``. Image folders: files sorted by name,
``timestamp`` = frame index. Video files (anything OpenCV's ``VideoCapture`` opens):
``timestamp`` = frame index / frame rate in seconds (the frame index if the file has no rate).
Frames that do not decode, or decode damaged, are skipped, listed in ``FrameSource.skipped``
with the reason in ``FrameSource.skip_reasons``: a truncated JPEG (no end-of-image marker; found
in the bytes, before libjpeg sees the file), a decoder that reports damage (its text, caught at
the file-descriptor level so that libjpeg's and FFmpeg's raw warnings never reach the terminal),
a frame whose bottom rows are the decoder's constant grey fill for missing data, a frame of
another size than the camera's in the middle of the sequence, and the frames a truncated video
no longer holds. A file that cannot be opened, a folder without images, or a sequence whose
first frames all have another size than the camera's is an :class:`OmniSfmError`.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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

SIZE_CHECK_FRAMES = 5
"""If none of the first this many readable frames has the camera's size, the camera file does
not match the images (an error); later frames of another size are skipped."""

GREY_FILL_ROWS = 16
"""A frame whose bottom rows (at least this many) are all one mid-grey value is damaged: that
is how libjpeg fills the rows of a truncated file."""

_DAMAGE = re.compile(r"premature end|corrupt(?! jpeg data: \d+ extraneous)|error|partial file|"
                     r"conceal|truncat", re.IGNORECASE)
_FFMPEG_PREFIX = re.compile(r"^\[[^]]*@ 0x[0-9a-f]+\]\s*", re.IGNORECASE)


@contextmanager
def captured_stderr() -> Iterator[list[str]]:
    """Catch what C libraries (libjpeg, libpng, FFmpeg, OpenCV's log) write to file descriptor
    2 inside the block; on exit the yielded list holds that text, cleaned by
    :func:`decoder_note`. Where descriptor 2 cannot be redirected, nothing is caught."""
    out: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield out
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield out
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            out.append(decoder_note(tmp.read().decode("utf-8", errors="replace")))


def decoder_note(text: str, most: int = 160) -> str:
    """A decoder's stderr text as one short line: FFmpeg's ``[codec @ 0x...]`` prefixes and
    repeated lines dropped, lines joined by ``; ``."""
    lines: list[str] = []
    for raw in text.splitlines():
        line = _FFMPEG_PREFIX.sub("", raw.strip())
        if line and line not in lines:
            lines.append(line)
    note = "; ".join(lines)
    return note if len(note) <= most else note[: most - 3] + "..."


def jpeg_is_truncated(data: bytes) -> bool:
    """Whether ``data``, a JPEG file (starts with the SOI marker), lacks its end-of-image
    marker (``FF D9``): at the end of the file (zero padding allowed) or, for files with
    appended data (motion photos), somewhere after the first start-of-scan marker."""
    if data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        return False
    sos = data.find(b"\xff\xda")
    return sos < 0 or data.find(b"\xff\xd9", sos) < 0


def grey_fill_rows(gray: np.ndarray) -> int:
    """Bottom rows of an ``(H, W)`` uint8 image that all hold one mid-grey value (120-136: a
    decoder's fill for missing data); 0 when the last row is not such a row."""
    last = gray[-1]
    v = last[0]
    if abs(int(v) - 128) > 8 or not bool(np.all(last == v)):
        return 0
    const = np.all(gray == v, axis=1)
    other = np.flatnonzero(~const)
    return int(gray.shape[0] - 1 - other[-1]) if len(other) else int(gray.shape[0])


def _damage(note: str) -> str | None:
    """The reason a frame that decoded is damaged, from its decoder's text; None if fine."""
    return f"damaged ({note})" if note and _DAMAGE.search(note) else None


def open_video(path: Path | str) -> cv2.VideoCapture:
    """OpenCV's capture of a video file, decoding in one thread where FFmpeg decodes it: with
    frame threads FFmpeg reports a frame's damage while it returns an earlier frame, so the
    decoder's messages (:func:`captured_stderr`) would blame the wrong frame."""
    try:
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_N_THREADS, 1])
    except (TypeError, cv2.error):  # OpenCV without open parameters (before 4.5.2)
        cap = None
    if cap is None or not cap.isOpened():
        cap = cv2.VideoCapture(str(path))
    return cap


def decode_image_file(path: Path) -> tuple[np.ndarray | None, str | None]:
    """An image file as OpenCV decodes it (``cv2.IMREAD_UNCHANGED``) and, for one that cannot be
    used, why: ``(image, None)`` or ``(None, reason)``. Truncated JPEGs are found in the bytes
    and never decoded; the decoder's own warnings are caught (:func:`captured_stderr`) and
    become the reason, never terminal output."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror})"
    if not data:
        return None, "empty file"
    if data[:2] == b"\xff\xd8" and jpeg_is_truncated(data):
        return None, "truncated JPEG"
    with captured_stderr() as log:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    note = log[0] if log else ""
    if img is None:
        return None, "does not decode" + (f" ({note})" if note else "")
    reason = _damage(note)
    return (None, reason) if reason else (img, None)


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


SEEK_GAP = 300
""":meth:`FrameSource.sample` decodes through gaps of up to this many video frames instead of
seeking (a seek decodes from the key frame before its target, which H.264 encoders place every
250 frames or so)."""


@dataclass
class FrameSource:
    """Iterable frames of an image folder or a video (see module docstring).

    ``size`` ``(width, height)``: the camera's image size. Frames of another size are skipped,
    unless none of the first :data:`SIZE_CHECK_FRAMES` readable frames has it: then the camera
    file does not match the images (an OmniSfmError names both sizes, or says what
    ``size_error(width, height)`` says, the camera's
    :meth:`~omni_sfm.cameras.CameraModel.frame_size_mismatch`). ``skipped`` lists the
    source indices of the frames skipped (in the order met), ``skip_reasons`` why, by index.
    """

    path: Path
    start: int = 0
    end: int | None = None
    step: int = 1
    size: tuple[int, int] | None = None
    size_error: Callable[[int, int], str | None] | None = None
    skipped: list[int] = field(default_factory=list)
    skip_reasons: dict[int, str] = field(default_factory=dict)
    is_video: bool = False
    stream: str | None = None
    """A camera device index (``"0"``) or a stream URL (:func:`read_stream`): read like a video,
    from ``stream`` instead of ``path``."""
    fps: float | None = None
    files: list[Path] = field(default_factory=list)
    frame_count: int | None = None
    _size_seen: bool = field(default=False, init=False, repr=False)
    _size_errors: list[str] = field(default_factory=list, init=False, repr=False)

    def __len__(self) -> int:
        """Number of frames the range selects (an estimate for videos without a frame count)."""
        total = len(self.files) if not self.is_video else (self.frame_count or 0)
        end = total if self.end is None else min(self.end, total)
        return max(0, -(-(end - self.start) // self.step))

    def __iter__(self) -> Iterator[Frame]:
        self._size_seen = False
        self._size_errors = []
        yield from self._iter_video() if self.is_video else self._iter_folder()
        if self._size_errors and not self._size_seen:
            raise OmniSfmError(self._size_errors[0])

    def sample(self, count: int) -> list[np.ndarray]:
        """Up to ``count`` grey frames spread evenly over the range, without reading the frames
        between them: a video seeks to each (when its container gives the frame count), an
        image folder decodes just those files. Frames that do not decode, are damaged or have
        another size are left out (the pass over all frames reports them)."""
        n = len(self)
        if count < 1 or n == 0:
            return []
        picks = sorted({self.start + self.step * int(k)
                        for k in np.linspace(0, n - 1, min(count, n)).round()})
        probe = FrameSource(path=self.path, size=self.size, size_error=self.size_error,
                            is_video=self.is_video,
                            fps=self.fps, files=self.files, frame_count=self.frame_count)
        out: list[np.ndarray] = []
        if not self.is_video:
            for i in picks:
                img, _ = decode_image_file(self.files[i])
                gray = None if img is None else probe._usable(img, i, str(self.files[i]))
                if gray is not None:
                    out.append(gray)
            return out
        with captured_stderr():
            cap = open_video(self.path)
        try:
            at = 0  # the next frame read() returns
            for i in picks:
                with captured_stderr() as log:
                    if 0 <= i - at <= SEEK_GAP:  # nearer than a seek's decoding from a key frame
                        ok = all(cap.grab() for _ in range(i - at))
                    else:
                        ok = cap.set(cv2.CAP_PROP_POS_FRAMES, float(i))
                    ok, img = cap.read() if ok else (False, None)
                at = i + 1
                if not ok or img is None or _damage(log[0] if log else ""):
                    continue
                gray = probe._usable(img, i, f"{self.path} frame {i}")
                if gray is not None:
                    out.append(gray)
        finally:
            cap.release()
        return out

    def _skip(self, number: int, reason: str) -> None:
        self.skipped.append(number)
        self.skip_reasons[number] = reason

    def _usable(self, img: np.ndarray, number: int, where: str) -> np.ndarray | None:
        """The grey frame, or None (recorded as skipped) for a grey-filled or wrongly sized one;
        an OmniSfmError once the first readable frames all had another size."""
        gray = to_gray(img)
        fill = grey_fill_rows(gray)
        if fill >= min(GREY_FILL_ROWS, gray.shape[0]):
            self._skip(number, f"damaged: the bottom {fill} rows are the decoder's grey fill")
            return None
        got = (gray.shape[1], gray.shape[0])
        if self.size is None or got == tuple(self.size):
            self._size_seen = True
            return gray
        if not self._size_seen:
            said = self.size_error(*got) if self.size_error is not None else None
            self._size_errors.append(
                f"{where}: {said}" if said else f"{where}: image is {got[0]}x{got[1]} px but the "
                f"camera file says {self.size[0]}x{self.size[1]} px")
            if len(self._size_errors) >= SIZE_CHECK_FRAMES:
                raise OmniSfmError(self._size_errors[0])
        self._skip(number, f"{got[0]}x{got[1]} px, the camera's is {self.size[0]}x{self.size[1]}")
        return None

    def _iter_folder(self) -> Iterator[Frame]:
        end = len(self.files) if self.end is None else min(self.end, len(self.files))
        for i in range(self.start, end, self.step):
            f = self.files[i]
            img, reason = decode_image_file(f)
            if img is None:
                self._skip(i, reason or "does not decode")
                continue
            gray = self._usable(img, i, str(f))
            if gray is not None:
                yield Frame(i, float(i), gray)

    def _iter_video(self) -> Iterator[Frame]:
        with captured_stderr() as log:
            cap = open_video(self.path) if self.stream is None else open_capture(self.stream)
        if not cap.isOpened():
            raise OmniSfmError(f"{self.stream or self.path}: OpenCV cannot open this video"
                               + (f" ({log[0]})" if log and log[0] else ""))
        try:
            i = 0
            # failed wanted frames and the decoder's text, reported once a later frame decodes
            pending: list[tuple[int, str]] = []
            fails = 0
            while self.end is None or i < self.end:
                if self.frame_count is not None and i >= self.frame_count:
                    break
                wanted = i >= self.start and (i - self.start) % self.step == 0
                with captured_stderr() as log:
                    ok = cap.grab()
                    img = None
                    if ok and wanted:
                        ok, img = cap.retrieve()
                        ok = ok and img is not None
                note = log[0] if log else ""
                i += 1
                if not ok:
                    fails += 1
                    if wanted:
                        pending.append((i - 1, note))
                    if fails >= MAX_CONSECUTIVE_FAILURES:
                        break
                    continue
                fails = 0
                for number, why in pending:
                    self._skip(number, "does not decode" + (f" ({why})" if why else ""))
                pending.clear()
                if img is None:
                    continue
                reason = _damage(note)
                if reason:
                    self._skip(i - 1, reason)
                    continue
                gray = self._usable(img, i - 1, f"{self.stream or self.path} frame {i - 1}")
                if gray is not None:
                    ts = (i - 1) / self.fps if self.fps else float(i - 1)
                    yield Frame(i - 1, ts, gray)
            self._report_tail(i, fails, pending)
        finally:
            cap.release()

    def _report_tail(self, i: int, fails: int, pending: list[tuple[int, str]]) -> None:
        """The last ``fails`` frames before frame ``i`` did not decode (``pending``: the wanted
        ones). Where the video stopped decoding before the frame count its container announces,
        every wanted frame from the first failure to the count is reported as cut off; failures
        at the end of the chosen range, as bad frames; without a count, after
        :data:`MAX_CONSECUTIVE_FAILURES`, the stream simply ended."""
        if fails == 0:
            return
        stopped = fails >= MAX_CONSECUTIVE_FAILURES
        if self.frame_count is None or not (stopped or i >= self.frame_count):
            if not stopped:
                for number, why in pending:
                    self._skip(number, "does not decode" + (f" ({why})" if why else ""))
            return
        first = i - fails
        why = (f"missing: the video stops decoding after frame {first - 1} of the "
               f"{self.frame_count} its container announces (a truncated file?)" if first > 0
               else "missing: no frame of the video decodes")
        end = self.frame_count if self.end is None else min(self.end, self.frame_count)
        for number in range(first, end):
            if number >= self.start and (number - self.start) % self.step == 0:
                self._skip(number, why)


def read_frames(path: Path | str, start: int = 0, end: int | None = None, step: int = 1,
                size: tuple[int, int] | None = None,
                size_error: Callable[[int, int], str | None] | None = None) -> FrameSource:
    """Frames ``start, start + step, ... < end`` of an image folder or a video file.

    ``size`` ``(width, height)``: the camera's image size, checked on every frame;
    ``size_error``: the camera's ``frame_size_mismatch`` (:class:`FrameSource`).
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
        return FrameSource(path=path, start=start, end=end, step=step, size=size,
                           size_error=size_error, files=files)
    with captured_stderr() as log:
        cap = open_video(path)
    try:
        if not cap.isOpened():
            note = log[0] if log else ""
            hint = (": the file has no index (moov atom), as when a recording is cut off "
                    "before it is finished; a repair tool (e.g. untrunc) may rebuild it"
                    if "moov atom not found" in note else f" ({note})" if note else "")
            raise OmniSfmError(f"{path}: not an image folder, and OpenCV cannot open it as a "
                               f"video{hint}")
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()
    return FrameSource(path=path, start=start, end=end, step=step, size=size,
                       size_error=size_error, is_video=True,
                       fps=fps if fps > 0 and np.isfinite(fps) else None,
                       frame_count=count if count > 0 else None)


def is_stream(spec: str) -> bool:
    """Whether an input names a camera device (an integer, ``"0"``) or a stream URL (anything
    with ``://``) rather than a file or folder."""
    return spec.strip().isdigit() or "://" in spec


def open_capture(spec: str) -> cv2.VideoCapture:
    """OpenCV's capture of a camera device index (``"0"``) or a stream URL; a file name or a
    URL goes through :func:`open_video`."""
    if spec.strip().isdigit():
        return cv2.VideoCapture(int(spec))
    return open_video(spec)


def read_stream(spec: str, size: tuple[int, int] | None = None,
                size_error: Callable[[int, int], str | None] | None = None) -> FrameSource:
    """Frames of a camera device (an integer index, ``"0"``) or a stream URL that OpenCV opens
    (``rtsp://...``, ``http://...``, ``file:///path/video.mp4``), until it ends: a
    :class:`FrameSource` read as a video file is (the same frame checks; timestamps: frame
    index / the rate the stream reports, else the index), without a frame count. One line
    :class:`OmniSfmError` if it does not open."""
    with captured_stderr() as log:
        cap = open_capture(spec)
    try:
        if not cap.isOpened():
            note = log[0] if log else ""
            what = "camera device" if spec.strip().isdigit() else "stream"
            raise OmniSfmError(f"{spec}: OpenCV cannot open this {what}"
                               + (f" ({note})" if note else ""))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
    finally:
        cap.release()
    return FrameSource(path=Path("."), size=size, size_error=size_error, is_video=True,
                       stream=spec,
                       fps=fps if fps > 0 and np.isfinite(fps) else None)


def first_frame_size(spec: Path | str) -> tuple[int, int]:
    """``(width, height)`` of the first readable frame of an image folder, a video file, a
    camera device index or a stream URL (decodes that one frame). One-line
    :class:`OmniSfmError` if none can be read."""
    text = str(spec)
    source = read_stream(text) if is_stream(text) else read_frames(Path(spec))
    frames = iter(source)
    try:
        first = next(frames, None)
    finally:
        close = getattr(frames, "close", None)
        if close is not None:
            close()  # releases the video
    if first is None:
        raise OmniSfmError(f"{text}: no frame could be read")
    return first.image.shape[1], first.image.shape[0]


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
        ``gray`` (converted as :func:`to_gray`, like the front end's frames). A frame that does
        not decode or decodes damaged (as :class:`FrameSource` judges it) is an OmniSfmError
        that says why."""
        if name not in self._cache:
            img, reason = self._read_video(name) if self.is_video else \
                decode_image_file(self.path / name)
            if img is None:
                raise OmniSfmError(f"{self.where(name)}: {reason or 'does not decode'}")
            fill = grey_fill_rows(to_gray(img))
            if fill >= min(GREY_FILL_ROWS, img.shape[0]):
                raise OmniSfmError(f"{self.where(name)}: damaged: the bottom {fill} rows are "
                                   "the decoder's grey fill")
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

    def _read_video(self, name: str) -> tuple[np.ndarray | None, str | None]:
        if name not in self._index:
            raise OmniSfmError(f"{self.path}: the video has no frame {name!r} (frames are named "
                               f"{video_frame_name(0)} to {self.names[-1]})")
        i = self._index[name]
        with captured_stderr():  # what earlier frames' decoding says is not about this one
            if self._cap is None or i < self._next:
                self.close()
                self._cap = open_video(self.path)
                self._next = 0
            ok = True
            while ok and self._next < i:
                ok = self._cap.grab()
                self._next += 1
        img = None
        with captured_stderr() as log:
            if ok:
                ok, img = self._cap.read()
                self._next += 1
        note = log[0] if log else ""
        if not ok or img is None:
            return None, "does not decode" + (f" ({note})" if note else "") + \
                " (damaged, or beyond the end of a truncated video)"
        reason = _damage(note)
        return (None, reason) if reason else (img, None)

    def close(self) -> None:
        """Release the video (reading again reopens it)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None
