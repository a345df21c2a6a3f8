"""Flags are honest (the real-footage issue): on walks with stretches the data do not fix, no
frame left trusted is more than 1 deg or 2 % of the path off, and few of the flagged frames are
right after all (omni_sfm.evaluate.flag_honesty counts both as a user reads trajectory.tum:
the trusted frames aligned on themselves)."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses
from omni_sfm.evaluate import flag_honesty
from omni_sfm.synth.simulate import SimulationOptions, simulate, weak_stretches


@pytest.mark.parametrize("seed", [0, 1])
def test_flags_are_honest_on_stretches_the_data_do_not_fix(seed: int) -> None:
    """Frames 120-169 see only lines along the walk, frames 260-289 two lines: the estimator
    flags what those stretches leave unfixed; every trusted frame is within 1 deg and 2 %, at
    most 10 % of the flagged frames are within 0.2 deg and 0.2 %, and a fifth of the walk at
    least is trusted (not everything flagged to be safe)."""
    sim = simulate(SimulationOptions(num_views=400, world="manhattan", path_length=0.05 * 399,
                                     noise_deg=0.1, seed=seed))
    tr = weak_stretches(sim, (120, 170), (260, 290))
    res = estimate_poses(tr, EstimationOptions(estimator="global"))
    g = sim.groundtruth
    flagged = g.timestamps[[int(k) for k in res.report.frames_uncertain or {}]]
    h = flag_honesty(res.trajectory, g, flagged)
    assert h.trusted_off == 0, h.as_dict()
    assert h.flagged_fine <= 0.1 * h.flagged, h.as_dict()
    assert h.trusted >= 80, h.as_dict()


def test_flag_honesty_aligns_the_trusted_frames_on_themselves() -> None:
    """A trajectory whose last 10 frames are 5 m off: flagged, they neither spoil the trusted
    frames' alignment (all exact) nor count as fine; trusted, they count as off, and the
    alignment they spoil puts other frames off too."""
    g = simulate(SimulationOptions(num_views=60, world="manhattan", path_length=0.05 * 59,
                                   seed=2)).groundtruth
    est = g.subset(np.arange(len(g)))
    est.positions[50:] += np.array([5.0, 0.0, 0.0])
    h = flag_honesty(est, g, g.timestamps[50:])
    assert (h.trusted, h.flagged, h.trusted_off, h.flagged_fine) == (50, 10, 0, 0)
    assert h.pos_rel[:50].max() < 1e-9 and h.rot_deg.max() < 1e-6
    h = flag_honesty(est, g, [])
    assert h.trusted == 60 and h.trusted_off > 10
