"""Dense mapping from known poses (docs/dense.md): rectified virtual pinhole views of the
omnidirectional frames, OpenCV semi-global matching, a 3-view check and Open3D TSDF fusion."""

from omni_sfm.dense.pipeline import (
    DenseInput,
    DenseOptions,
    DenseResult,
    KeyframeStats,
    dense_map,
    read_dense_input,
    run_dense,
    write_dense,
)
from omni_sfm.dense.stereo import StereoOptions

__all__ = [
    "DenseInput",
    "DenseOptions",
    "DenseResult",
    "KeyframeStats",
    "StereoOptions",
    "dense_map",
    "read_dense_input",
    "run_dense",
    "write_dense",
]
