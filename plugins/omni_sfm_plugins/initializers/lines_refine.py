"""``lines-refine``: the README's chain ``omni-sfm init --lines`` then ``omni-sfm refine``.

The frames go through :func:`omni_sfm.pipelines.init.init_from_images` exactly as ``init`` runs
(the ``lines`` initializer's result) and the init folder through :func:`omni_sfm.refine.refine`
(COLMAP features, triangulation on the line-based poses, the mapper for the frames lines
missed, bundle adjustment, never worse than its input: docs/colmap.md). Refine does not seed
COLMAP with the poses init flags as not fixed by the data (the mapper registers those frames)
and stops where fewer than 3 are left: the result is then a failure with refine's reason, not
init's poses. Needs images; the work folders are temporary.

Options: ``threads`` (pycolmap threads, default 1 so that parallel comparisons stay
deterministic and do not oversubscribe), ``verbose`` (COLMAP's log).
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omni_sfm.plugin_contract import InitializerResult, SequenceInput, failed


def lines_refine(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    """The ``lines-refine`` initializer (module docstring)."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.pipelines.init import InitOptions, init_from_images
    from omni_sfm.refine import RefineOptions, refine

    if sequence.images is None:
        return failed("needs images (init and refine run on frames)")
    with tempfile.TemporaryDirectory(prefix="omni_sfm_lines_refine_") as tmp:
        work = Path(tmp)
        try:
            init = init_from_images(sequence.images.path, sequence.camera, work / "init",
                                    InitOptions(debug_view="none", progress=False))
        except OmniSfmError as exc:
            return failed(f"init: {exc}")
        ropts = RefineOptions(num_threads=int(options.get("threads", 1)))
        try:
            res = refine(work / "init", sequence.images.path, work / "refined", ropts,
                         progress=False, verbose=bool(options.get("verbose", False)))
        except OmniSfmError as exc:  # its temporary folders named as the chain's steps
            return failed("refine: " + str(exc).replace(f"{work / 'init'}", "init")
                          .replace(f"{work / 'refined'}", "refined"))
    r = res.report
    info: dict[str, Any] = {
        "init_frames": len(init.image_names),
        "refined_frames": r.refined_frames,
        "added_by_mapper": len(r.mapper_added),
    }
    if r.kept_input_for_all:
        info["kept_input_for_all"] = r.kept_input_for_all
    return InitializerResult(res.trajectory, "ok", info=info)
