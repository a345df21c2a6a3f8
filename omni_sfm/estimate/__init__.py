"""Poses of all views from tracked line observations (docs/method.md §3-§5) and their refinement.

Modules: ``rotation``, ``translation``, ``search``, ``paper`` (the paper's method on one window
of fully visible tracks), ``bundle`` (line bundle adjustment and the ground-truth oracle),
``windows`` (the paper's window), ``global_estimator`` (rotations, positions, adjustment of all
frames at once), ``pipeline`` (which estimator runs, :func:`omni_sfm.estimate.pipeline.
estimate_poses`). Import from the modules; this package file
imports nothing so that each stage can be used alone.
"""
