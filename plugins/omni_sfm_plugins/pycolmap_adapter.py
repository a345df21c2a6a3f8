"""pycolmap adapter: the line-based poses as a seeded ``pycolmap.Reconstruction``.

For people who run pycolmap themselves: after their own feature extraction and matching, this
returns the init directory's camera and poses as a Reconstruction whose camera, rig, frame and
image ids are those of *their* database, ready for ``pycolmap.triangulate_points`` or for
``pycolmap.incremental_mapping(..., input_path=...)``. Registered as ``pycolmap-seed`` in the
``omni_sfm.adapters`` entry-point group::

    from omni_sfm.registry import ADAPTERS, load
    seeded_reconstruction = load(ADAPTERS, "pycolmap-seed")

The image folder must hold the images as COLMAP must see them (``INIT_DIR/images_colmap/``
when ``omni-sfm init`` wrote it: by default for runs of at most 1,000 frames, with
``--colmap-images`` for longer ones; the hyperboloid camera's images are mirrored left-right,
see docs/cameras.md). :func:`reader_options` gives pycolmap's ImageReaderOptions for extracting
features with the exact camera and its valid mask. Full example: docs/colmap.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap import (
    read_init_model,
    seed_for_database,
    write_colmap_mask,
)
from omni_sfm.folders import InitFolder


def reader_options(init_dir: Path | str) -> Any:
    """``pycolmap.ImageReaderOptions`` for the init directory's camera: its exact COLMAP model
    and parameters (one shared camera: use ``camera_mode=pycolmap.CameraMode.SINGLE``) and the
    camera's valid mask (``INIT_DIR/camera_mask.png``, written if missing)."""
    import pycolmap

    init = read_init_model(Path(init_dir))
    cam = init.camera.colmap_export().camera
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = cam.model_name
    opts.camera_params = ",".join(repr(float(x)) for x in cam.params)
    mask = Path(init_dir) / InitFolder.COLMAP_MASK
    if not mask.is_file():
        write_colmap_mask(mask, init.camera)
    opts.camera_mask_path = str(mask)
    return opts


def seeded_reconstruction(database_path: Path | str, image_path: Path | str,
                          init_dir: Path | str) -> Any:
    """The init directory's poses as a ``pycolmap.Reconstruction`` consistent with a database.

    Args:
        database_path: a COLMAP database holding (at least) the images of the init model, all
            of one camera of the exact COLMAP model and size (features may or may not exist).
        image_path: the folder COLMAP reads the images from; every image of the model must be
            there.
        init_dir: an init directory (``sparse/``, ``camera.yaml``, ``trajectory.tum``).

    Returns:
        A Reconstruction with the exact camera (the database's camera id, exact parameters), the
        database's rigs and frames, and one registered image per pose (the database's image ids,
        the init's names and poses), no 3D points.

    Raises OmniSfmError (one line) naming what does not match.
    """
    init = read_init_model(Path(init_dir))
    image_path = Path(image_path)
    if not image_path.is_dir():
        raise OmniSfmError(f"{image_path}: image folder not found")
    missing = [n for n in init.image_names if not (image_path / n).is_file()]
    if missing:
        raise OmniSfmError(f"{image_path}: {len(missing)} images of the init model are missing "
                           f"(first: {missing[0]!r})")
    seed = seed_for_database(init.camera, init.trajectory, init.image_names,
                             Path(database_path))
    return seed.reconstruction
