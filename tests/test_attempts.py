"""The estimator's attempts: named strategies, each recorded with its outcome
(omni_sfm.estimate.attempts, report.json ``attempts``)."""

from __future__ import annotations

import contextlib
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers import WINDOWS

from omni_sfm.estimate import pipeline
from omni_sfm.estimate.attempts import STRATEGIES, Attempt, Outcome, RunLog, failed
from omni_sfm.estimate.pipeline import estimate_poses
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
    sub = run.at(100)
    sub.record(Attempt("paper window", (0, 39), object(), cost_deg=0.1234567891))
    sub.record(failed("paper window", (30, 69), "degenerate motion"))
    att = Attempt("bundle adjustment", None, object()).judged(Outcome.REJECTED, "higher cost")
    run.record(att, family=2)
    assert [e.to_json() for e in run.entries] == [
        {"strategy": "paper window", "frames": [100, 139], "result": "kept",
         "cost_rms_deg": 0.123457},
        {"strategy": "paper window", "frames": [130, 169], "result": "failed",
         "why": "degenerate motion"},
        {"strategy": "bundle adjustment", "result": "rejected", "why": "higher cost",
         "family": 2},
    ]
    # a sub-run on a stretch keeps its own timings unless it shares them
    with sub.timed("x"):
        pass
    assert "x" in sub.timings and "x" not in run.timings
    with run.at(5, share_timings=True).timed("y"):
        pass
    assert "y" in run.timings


def test_a_sequence_with_outliers_records_the_restart_and_its_verdict() -> None:
    # 15 % of the tracks switch to another line part-way: the adjustment rejects them, the
    # estimator starts again without them, and the report says which solution it kept
    sim = simulate(SimulationOptions(num_views=20, num_parallel=10, num_other=10,
                                     noise_deg=0.1, outlier_fraction=0.15, seed=1))
    res = estimate_poses(sim.tracks, WINDOWS)
    att = (res.report.attempts or [])
    names = [a.strategy for a in att]
    assert set(names) <= set(STRATEGIES)
    assert names[0] == "paper window" and "bundle adjustment" in names
    (restart,) = [a for a in att if a.strategy == "restart without outliers"]
    assert restart.result in ("kept", "rejected") and "without" in restart.why
    # the kept solution's cost is the reported final residual (the restart's own attempts come
    # before it, in the order they ran)
    first = next(a for a in att if a.strategy == "bundle adjustment")
    kept = restart if restart.result == "kept" else first
    assert np.isclose(kept.cost_rms_deg, res.residual_rms_final_deg, rtol=1e-5)


class _Bar:
    """Stands in for tqdm: what the estimate's progress bar was told."""

    def __init__(self) -> None:
        self.n = 0
        self.stages: list[str] = []

    def update(self, k: int) -> None:
        self.n += k

    def set_postfix_str(self, text: str, refresh: bool = True) -> None:
        self.stages.append(text)


def test_progress_shows_the_furthest_frame_reached_and_the_stage(monkeypatch) -> None:
    bar = _Bar()
    run = RunLog(progress=bar)
    run.reached(9)
    run.at(100).reached(4)  # a sub-run on frames 100.. reached frame 104
    assert bar.n == 105
    run.reached(50)  # an earlier frame: the bar does not go back
    assert bar.n == 105
    with run.at(3).timed("chaining"):
        pass
    assert bar.stages == ["chaining"]
    # a whole estimate: the windows and the registration move it to the last frame posed
    sim = simulate(SimulationOptions(num_views=60, num_parallel=10, num_other=10,
                                     noise_deg=0.1, visible_frames=30, seed=2))
    bars: list[_Bar] = []

    def fake_tqdm(*args: object, **kwargs: object) -> contextlib.nullcontext[_Bar]:
        bars.append(_Bar())
        return contextlib.nullcontext(bars[-1])

    monkeypatch.setattr(pipeline, "tqdm", fake_tqdm)
    res = estimate_poses(sim.tracks, replace(WINDOWS, progress=True))
    assert len(bars) == 1 and bars[0].n == int(np.flatnonzero(res.estimated).max()) + 1
    assert "refinement" in bars[0].stages


def test_second_start_is_skipped_where_one_window_covers_the_sequence() -> None:
    """200 frames that see every line: one window of the paper's method, no chain that could
    drift, so the short bootstrap (docs/estimator.md stage 9) is recorded as skipped."""
    sim = simulate(SimulationOptions(num_views=200, num_parallel=10, num_other=5,
                                     noise_deg=0.1, seed=0))
    res = estimate_poses(sim.tracks, WINDOWS)
    assert res.estimated.all()
    short = [a for a in (res.report.attempts or []) if a.strategy == "short bootstrap"]
    assert [(a.result, a.why) for a in short] == \
        [("skipped", "one window covers the sequence")]


def test_a_reversed_run_records_its_frames_in_the_sequence_order() -> None:
    run = RunLog()
    back = run.reversed(100)
    back.record(failed("bootstrap stretch", (0, 9), "x"))
    back.at(10).record(failed("new start", (0, 4), "y"))
    run.record(failed("join", (3, 5), "z"))
    first, second, third = run.entries
    assert first.frames == [90, 99] and first.reversed is True
    assert second.frames == [85, 89] and second.reversed is True
    assert third.frames == [3, 5] and third.reversed is None
    assert "reversed" not in third.to_json()


def test_frames_reversed_twice_are_the_tracks_again() -> None:
    sim = simulate(SimulationOptions(num_views=30, num_parallel=5, num_other=5,
                                     visible_frames=12, seed=1))
    tr = sim.tracks
    back = pipeline.reversed_frames(tr)
    assert back.num_frames == tr.num_frames
    vis, vis_back = tr.visibility(), back.visibility()
    assert np.array_equal(vis_back, vis[:, ::-1])
    # each track's first and last frame, reversed with it; a track left without observations
    first, last = tr.frame_spans()
    assert np.array_equal(first, vis.argmax(1)) and np.array_equal(
        last, tr.num_frames - 1 - vis[:, ::-1].argmax(1))
    assert np.array_equal(back.frame_spans()[0], tr.num_frames - 1 - last)
    first0, last0 = tr.frame_spans(tr.obs_track != 0)
    assert (first0[0], last0[0]) == (tr.num_frames, -1) and np.array_equal(first0[1:], first[1:])
    again = pipeline.reversed_frames(back)
    for name in ("obs_track", "obs_frame", "obs_normal"):
        assert np.array_equal(getattr(again, name), getattr(tr, name)), name
