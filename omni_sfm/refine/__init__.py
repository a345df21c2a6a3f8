"""Refinement of the line-based poses by COLMAP (pycolmap), never worse than its input."""

from omni_sfm.refine.pipeline import RefineOptions, RefineResult, model_statistics, refine

__all__ = ["RefineOptions", "RefineResult", "model_statistics", "refine"]
