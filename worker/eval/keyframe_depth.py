"""The depth a map's keyframes were built from, scored against a depth sensor's (sessions mapped without depth).

A posed RGB or RGB-only session gives each keyframe a multi-view depth: the confident pixels its surfels start on
and its refinement's depth term sees. Where the recording carries a sensor's depth (a Kinect sequence played as
RGB), that depth scores them: L1 on the pixels both have, and coverage (those pixels over the pixels the sensor
has). Unlike the rendered depth of held-out frames, this sees what the map was built from, before refinement.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np

from worker.eval.metrics import depth_l1

# The targets a keyframe is counted against (issue 43: posed RGB keyframe depth <= 10 cm at >= 70 % coverage).
L1_TARGET_M = 0.10
COVERAGE_TARGET = 0.70


@dataclass
class KeyframeDepthScores:
    """Means over the scored keyframes; `l1_unscaled` only when the keyframes' depth is in metres (posed sessions)."""

    keyframes: int  # keyframes that had both a depth and a sensor depth
    l1: float  # metres, each keyframe's depth scaled as `scaling` says
    l1_median: float
    coverage: float  # share of the sensor's pixels with a keyframe depth
    coverage_median: float
    meeting_targets: float  # share of keyframes with L1 <= L1_TARGET_M and coverage >= COVERAGE_TARGET
    scaling: str
    l1_unscaled: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def keyframe_depth_scores(depths: Mapping[int, np.ndarray], sensor: Mapping[int, np.ndarray],
                          scaling: str = "median", metric: bool = False) -> KeyframeDepthScores | None:
    """Score keyframe depths (`depths`: frame index -> [H, W] world-unit depth, 0 = none) against the sensor's
    (`sensor`: frame index -> [H, W] metres, 0 = none) on the frames both have; None when none has both. `metric`:
    the keyframes' units are metres (a device's poses), so the unscaled L1 is reported too."""
    l1s, unscaled, coverages = [], [], []
    for index, depth in depths.items():
        truth = sensor.get(index)
        if truth is None or truth.shape != depth.shape:
            continue
        has_truth = np.isfinite(truth) & (truth > 0)
        both = has_truth & np.isfinite(depth) & (depth > 0)
        if has_truth.sum() == 0:
            continue
        coverages.append(float(both.sum() / has_truth.sum()))
        l1s.append(depth_l1(depth, truth, scaling).value if both.any() else float("inf"))
        if metric:
            unscaled.append(depth_l1(depth, truth, "none").value if both.any() else float("inf"))
    if not coverages:
        return None
    finite = [v for v in l1s if np.isfinite(v)] or [float("nan")]
    meeting = [l1 <= L1_TARGET_M and cov >= COVERAGE_TARGET for l1, cov in zip(l1s, coverages)]
    return KeyframeDepthScores(
        keyframes=len(coverages), l1=float(np.mean(finite)), l1_median=float(np.median(finite)),
        coverage=float(np.mean(coverages)), coverage_median=float(np.median(coverages)),
        meeting_targets=float(np.mean(meeting)), scaling=scaling,
        l1_unscaled=float(np.mean([v for v in unscaled if np.isfinite(v)] or [float("nan")])) if metric else None)
