"""omni-sfm: camera motion from straight lines in omnidirectional video.

Pipeline stages, data flowing one way::

    cameras -> lines -> vanishing -> estimate -> export -> refine -> dense -> evaluate

plus ``synth`` (simulated observations, rendered video with ground truth) and a thin ``cli``.
Conventions used everywhere:

- Pixels follow OpenCV: the centre of the top-left pixel is ``(0, 0)``; ``u`` to the right,
  ``v`` down. (COLMAP puts that centre at ``(0.5, 0.5)``; exports convert.)
- Rays are unit 3-vectors in the camera frame of the model ("ray vectors", docs/method.md §1).
- Poses are named ``b_from_a``: ``world_from_cam`` maps camera coordinates to the world,
  ``x_world = R @ x_cam + t``; its translation is the camera centre in the world.
- The world frame is the first frame's camera unless a stage says otherwise.
"""

__version__ = "0.1.0"
