"""Entry points above the stages: the programs that wire the stages together.

- :mod:`omni_sfm.pipelines.init`: ``omni-sfm init`` on images or video (frames -> line tracks
  -> poses -> artifacts), and the poses of a registered initializer;
- :mod:`omni_sfm.pipelines.track`: ``omni-sfm track``, frames in and poses out one at a time
  (:mod:`omni_sfm.pipelines.track_output` writes its folder as the poses come);
- :mod:`omni_sfm.pipelines.demo`: the built-in example, a rendered corridor.

The work is in the stages; a stage never imports a pipeline.
"""
