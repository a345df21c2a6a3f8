"""The compiled part of omni-sfm (everything else is in pyproject.toml).

The line bundle adjustment's per-observation loops, omni_sfm/estimate/_lines.c
(omni_sfm.estimate.kernels), and the line extractor's per-edge-point loops,
omni_sfm/lines/_edges.c (omni_sfm.lines.edge_kernels): built by the project's install (``make
setup``, ``pip install -e .``) with any C compiler and Python's headers. ``-ffp-contract=off``:
no fused multiply-add, so that processors with and without it round alike.
"""

from setuptools import Extension, setup

ARGS = ["-O3", "-ffp-contract=off"]
HEADERS = ["omni_sfm/_buffers.h"]  # the argument arrays' checks, shared by both

setup(ext_modules=[Extension("omni_sfm.estimate._lines", ["omni_sfm/estimate/_lines.c"],
                             extra_compile_args=ARGS, depends=HEADERS),
                   Extension("omni_sfm.lines._edges", ["omni_sfm/lines/_edges.c"],
                             extra_compile_args=ARGS, depends=HEADERS)])
