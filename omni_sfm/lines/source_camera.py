"""The camera of a sequence: a camera file, ``equirectangular`` built from the frame size, or
the spherical-video metadata of an MP4 given without a camera (docs/cameras.md, "360 video
without a camera file").

:func:`camera_for_frames` is the one place every command that takes ``--camera`` (``init``,
``track``, ``compare``, ``dense``, ``camera show`` / ``convert``) turns its value into a
:class:`~omni_sfm.cameras.CameraModel`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from omni_sfm.cameras import CameraModel, EquirectangularCamera, load_camera
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import first_frame_size, is_stream
from omni_sfm.lines.spherical import spherical_metadata

EQUIRECTANGULAR = "equirectangular"
"""The ``--camera`` value that needs no file: an equirectangular camera of the frames' size."""


def is_keyword(camera: Path | str | None) -> bool:
    """Whether ``camera`` names the built-in equirectangular camera rather than a file (it does
    when no file or folder of that name exists)."""
    return camera is not None and str(camera).strip().lower() == EQUIRECTANGULAR \
        and not Path(camera).exists()


def camera_for_frames(camera: Path | str | CameraModel | None, images: Path | str | None, *,
                      note: Callable[[str], None] | None = None) -> CameraModel:
    """The camera of the frames ``images`` (an image folder, a video, a device or stream).

    ``camera``: a :class:`CameraModel` (returned as is); a camera file (any format
    :func:`~omni_sfm.cameras.load_camera` reads); ``"equirectangular"``: an equirectangular
    camera of the first frame's size (360 deg across the width, 180 deg down the height, so a
    2:1 frame or one squeezed to 16:9 alike); None: an MP4 whose spherical-video metadata
    (V2 ``sv3d`` or V1 XMP) says one whole equirectangular sphere and whose frame is 2:1 is read
    as equirectangular, with a line to ``note`` saying so.

    Raises:
        OmniSfmError: (one line) a camera file that is missing or invalid, no camera and no
            usable metadata, or frames that cannot be read.
    """
    if isinstance(camera, CameraModel):
        return camera
    if camera is not None and not is_keyword(camera):
        path = Path(camera)
        if not path.exists():
            raise OmniSfmError(f"{path}: camera file not found (give a camera file, "
                               f"docs/cameras.md, or '{EQUIRECTANGULAR}' for 360 video)")
        return load_camera(path)
    if images is None:
        raise OmniSfmError(f"{EQUIRECTANGULAR}: the camera is built from the frame size: "
                           "give the frames too (--images PATH, a folder or a video)")
    if camera is not None:
        width, height = first_frame_size(images)
        return EquirectangularCamera(width=width, height=height)
    src = str(images)
    meta = None if is_stream(src) or not Path(src).is_file() else spherical_metadata(src)
    if meta is None:
        raise OmniSfmError(f"no camera: give --camera CAMERA_FILE (docs/cameras.md), or --camera "
                           f"{EQUIRECTANGULAR} for 360 video ({src} carries no spherical-video "
                           "metadata)")
    if not meta.full_equirectangular:
        raise OmniSfmError(f"{src}: {meta.describe()}: omni-sfm reads one whole equirectangular "
                           "sphere; give --camera CAMERA_FILE")
    width, height = first_frame_size(images)
    if width != 2 * height:
        raise OmniSfmError(f"{src}: {meta.describe()}, but the frame is {width}x{height} px, not "
                           f"2:1; give --camera {EQUIRECTANGULAR} if it spans 360x180 deg anyway")
    if note is not None:
        note(f"{src}: read as equirectangular {width}x{height} (its {meta.scheme} metadata; "
             "--camera to override)")
    return EquirectangularCamera(width=width, height=height)
