"""The detector variants of bench/change_detector.py, on codes whose answer is known: a step
detector must report a step between subjects and not a slow wander, and the per-frame variance
fit must recover a variance that grows with a frame feature; and its replica of the node's default
detector gives, frame by frame, the statistic the node published on the sample recording."""

from __future__ import annotations

import sys
from pathlib import Path

import subprocess

import numpy as np
from node_paths import NODE, ROOT

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import change_detector  # noqa: E402


def reported(detector, codes):
    return [t for t, code in enumerate(codes) if detector.update(code, np.ones_like(code))[1]]


def test_step_detector_reports_a_step_and_not_a_slow_wander():
    noise = np.random.default_rng(1).normal(size=(200, 5))
    step = noise + np.where(np.arange(200) >= 120, 3.0, 0.0)[:, None]
    wander = noise + np.linspace(0.0, 6.0, 200)[:, None]  # twice the step, over 200 frames
    found = reported(change_detector.StepDetector(12.0, (5, 30)), step)
    assert len(found) == 1 and 120 <= found[0] <= 124, found
    assert reported(change_detector.StepDetector(12.0, (5, 30)), wander) == []
    # The CUSUM on a fixed reference is what the step detector is measured against: it does take
    # the wander for a change.
    assert reported(change_detector.ShapeFilter(20.0, 3.0), wander) != []


def test_frame_variances_recover_a_log_linear_variance():
    rng = np.random.default_rng(2)
    frames = []
    for subject in range(40):
        centre = rng.normal(size=2) * 5
        for _ in range(60):
            kept = rng.uniform(200, 2000)
            # Variance falls as 1 / kept along the first direction, and not at all along the second.
            scale = np.array([np.sqrt(400.0 / kept), 1.0])
            features = np.array([np.log(kept), 0.5, 0.1, -1.0, -2.0, np.log(20000.0)])
            frames.append(dict(family="f", subject=str(subject), x_c=centre + scale * rng.normal(size=2),
                               features=features + np.r_[0, rng.normal(size=5) * 0.01]))
    weights, centre, scale = change_detector.frame_variances([("s", frames, [])], np.eye(2), "x_c")
    # log variance = log 400 - log kept: a slope of -1 per unit of log kept, in standardised units.
    assert abs(weights[0, 0] / scale[0] * -1 - 1.0) < 0.15, weights
    assert abs(weights[1, 0] / scale[0]) < 0.15, weights


def test_the_replica_of_the_node_s_step_detector_is_the_node_s(tmp_path):
    states = tmp_path / "states.jsonl"
    subprocess.run([NODE, "evaluate", str(ROOT / "sim/samples/walk_switch.mcap"), "--config",
                    str(ROOT / "config/replay.toml"), "--states", str(states)],
                   check=True, capture_output=True, timeout=300)
    streams = change_detector.load(states)
    bundle = ROOT / "models/bundles/h200-fo-nodeid"
    (threshold, shape, step), figure = change_detector.node_detector("step", bundle)
    assert figure == "node_statistic"
    assert any(f["node_statistic"] > 1.0 for _, frames, _ in streams for f in frames)
    # Stops (SystemExit) at the first frame whose published statistic is not the replica's.
    change_detector.check_replica(streams, lambda: step(threshold, shape), figure)
    found, true, false, _ = change_detector.count(streams, threshold, shape, lambda f: (f["mean"], f["variance"]), step)
    assert (found, true, false) == (1, 1, 0), "the sample's one swap, as the node finds it"
