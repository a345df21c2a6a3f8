"""omni-sfm's initializer plugins (entry-point group ``omni_sfm.initializers``).

Each is a callable ``(sequence: omni_sfm.plugin_contract.SequenceInput, options: dict) ->
omni_sfm.plugin_contract.InitializerResult`` (contract: docs/plugins.md; results:
docs/comparison.md):

- ``lines``: omni-sfm's line front end and estimator (:mod:`.lines`);
- ``lines-refine``: ``lines`` then ``omni-sfm refine`` (COLMAP on the line-based poses;
  :mod:`.lines_refine`);
- ``five-point``: point rays, pycolmap's five-point LO-RANSAC, chained with scale carried by
  triangulated points (:mod:`.five_point`);
- ``colmap``: pycolmap's incremental mapper with the exact camera model (:mod:`.colmap`);
- ``upright-3pt``: PoseLib's upright three-point solver on point rays turned so that omni-sfm's
  vanishing direction is the solver's up axis (:mod:`.upright`).
"""
