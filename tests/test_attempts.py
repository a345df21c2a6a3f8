"""The paper estimator's attempts: named strategies, each recorded with its outcome
(omni_sfm.estimate.attempts, report.json ``attempts``)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from omni_sfm.estimate.attempts import STRATEGIES, Attempt, Outcome, RunLog, failed
from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses
from omni_sfm.synth.simulate import SimulationOptions, simulate

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_every_strategy_is_documented() -> None:
    text = (DOCS / "estimator.md").read_text()
    table = set(re.findall(r"^\| `([^`]+)` \|", text, flags=re.M))
    assert set(STRATEGIES) <= table, set(STRATEGIES) - table


def test_an_attempt_names_a_known_strategy_and_records_its_verdict() -> None:
    with pytest.raises(ValueError, match="unknown strategy"):
        Attempt("guess", None, None)
    run = RunLog()
    run.record(Attempt("paper window", (0, 39), object(), cost_deg=0.1234567891))
    run.record(failed("paper window", (0, 39), "degenerate motion"))
    att = Attempt("bundle adjustment", None, object()).judged(Outcome.REJECTED, "higher cost")
    run.record(att, family=2)
    assert [e.to_json() for e in run.entries] == [
        {"strategy": "paper window", "frames": [0, 39], "result": "kept",
         "cost_rms_deg": 0.123457},
        {"strategy": "paper window", "frames": [0, 39], "result": "failed",
         "why": "degenerate motion"},
        {"strategy": "bundle adjustment", "result": "rejected", "why": "higher cost",
         "family": 2},
    ]
    with run.timed("x"):
        pass
    run.add_times({"x": 1.0})
    assert run.timings["x"] >= 1.0


def test_the_paper_estimators_attempts_are_recorded_in_order() -> None:
    # 15 % of the tracks switch to another line part-way: the paper's method on the window,
    # the adjustment from it (which rejects them), its alternative starts judged by their cost
    sim = simulate(SimulationOptions(num_views=20, num_parallel=10, num_other=10,
                                     noise_deg=0.1, outlier_fraction=0.15, seed=1))
    res = estimate_poses(sim.tracks, EstimationOptions(estimator="paper"))
    att = res.report.attempts or []
    names = [a.strategy for a in att]
    assert set(names) <= set(STRATEGIES)
    assert names[0] == "paper window" and att[0].frames == [0, 19]
    kept = [a for a in att if a.strategy.startswith("bundle adjustment") and a.result == "kept"]
    assert len(kept) == 1
    # the kept adjustment's cost is the reported final residual
    assert np.isclose(kept[0].cost_rms_deg, res.residual_rms_final_deg, rtol=1e-5)
    assert res.report.rejected_tracks
