"""Loop closure end to end on the ICL living-room frames: tracker -> bag -> ORB detection -> hidden-state
relocalization -> verification -> Sim(3) pose graph. The frontend is the ground-truth model double with injected
rotation drift, so the true answer is known."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pytest
import torch

from worker.frontend.tracker import SubmapTracker
from worker.geometry import make_sim3, relative_transform, sim3_decompose, so3_exp, so3_log
from worker.loop.bag import HiddenStateBag
from worker.loop.descriptors import OrbDescriptor
from worker.loop.detector import LoopCandidate, LoopDetector
from worker.loop.oracle import OracleModel, ground_truth_overlap
from worker.loop.pose_graph import Sim3PoseGraph
from worker.loop.relocalize import HiddenStateRelocalizer, LoopConstraint
from worker.loop.synthetic import ate_rmse


@dataclass
class LoopRun:
    frames: list
    tracker: SubmapTracker
    relocalizer: HiddenStateRelocalizer
    candidates: list[LoopCandidate] = field(default_factory=list)
    constraints: list[LoopConstraint] = field(default_factory=list)


def run_loop_closure(frames, rotation_drift: float) -> LoopRun:
    model = OracleModel(frames, rotation_drift=rotation_drift)
    tracker, bag = SubmapTracker(model), HiddenStateBag()
    detector = LoopDetector(OrbDescriptor(n_features=500), exclusion_window=20, top_k=3, min_score=0.05)
    run = LoopRun(frames, tracker, HiddenStateRelocalizer(model, bag, tracker))
    for n, frame in enumerate(frames):
        tracked = tracker.track(n, frame.image, frame.intrinsics)
        bag.add_finished(tracker.pop_finished_submaps())
        if not tracked.is_keyframe:
            continue
        for candidate in detector.detect(n, frame.image):
            run.candidates.append(candidate)
            if bag.submap_of(candidate.match) is not None:
                run.constraints.append(run.relocalizer.relocalize(candidate.match, n, frame.image, frame.intrinsics))
    return run


@pytest.fixture(scope="module")
def drifting_run(icl_frames):
    torch.set_num_threads(1)
    return run_loop_closure(icl_frames, rotation_drift=0.006)


def test_detection_finds_the_revisit_of_the_start(drifting_run):
    accepted = [c for c in drifting_run.constraints if c.accepted]
    assert any(c.j >= 40 and c.i <= 10 for c in accepted), [(c.i, c.j) for c in accepted]
    # every late keyframe (the way back) is matched to some old keyframe
    late = sorted({c.query for c in drifting_run.candidates if c.query >= 50})
    late_keyframes = [k for k in drifting_run.tracker.keyframes if k >= 50]
    assert len(late) >= 0.75 * len(late_keyframes)


def test_no_loop_is_proposed_between_frames_that_do_not_overlap(drifting_run, icl_frames):
    for c in drifting_run.candidates:
        assert c.query - c.match > 20  # the temporal exclusion window
        assert ground_truth_overlap(icl_frames, c.match, c.query) > 0.2, c
    for c in drifting_run.constraints:
        assert c.accepted == (ground_truth_overlap(icl_frames, c.i, c.j) > 0.2)


def test_look_alike_place_without_overlap_is_rejected(icl_frames):
    """Perceptual aliasing: frames 0..20 shown again from a place 6 m away and turned around (every pair in the ICL
    subset overlaps, so the non-overlapping revisit is built). The detector proposes them (same appearance);
    verification must reject every candidate whose frames share no view, and keep the genuine ones."""
    far = make_sim3(so3_exp(torch.tensor([0.0, np.pi, 0.0], dtype=torch.float64)),
                    torch.tensor([6.0, 0.0, 0.0], dtype=torch.float64))
    aliased = []
    for f in icl_frames[:21]:
        image = f.image.clone()
        image[0, :, 0, 0] = 1.0 - image[0, :, 0, 0]  # a distinct image to the model double, same to ORB
        aliased.append(replace(f, image=image, pose=far @ f.pose))
    frames = icl_frames[:40] + aliased
    run = run_loop_closure(frames, rotation_drift=0.0)
    across = [c for c in run.constraints if c.i < 40 <= c.j]
    assert len(across) >= 5
    for c in run.constraints:
        overlap = ground_truth_overlap(frames, c.i, c.j)
        assert c.accepted == (overlap > 0.2), (c.i, c.j, overlap, c.reason)
    assert not any(c.accepted for c in across)


def test_pose_graph_with_verified_loops_reduces_drift(drifting_run, icl_frames):
    tracker = drifting_run.tracker
    keys = sorted(tracker.keyframes)
    gt = np.stack([icl_frames[k].pose.numpy() for k in keys])
    graph = Sim3PoseGraph()
    for k in keys:
        graph.add_node(k, tracker.keyframes[k].pose_world)
    for e in tracker.constraints:
        graph.add_edge(e.i, e.j, e.relative, e.kind)
    before = ate_rmse(np.stack([graph.nodes[k] for k in keys]), gt)
    loops = [c for c in drifting_run.constraints if c.accepted]
    for c in loops:
        graph.add_edge(c.i, c.j, c.relative, "loop")
    result = graph.optimize()
    after = ate_rmse(np.stack([result.poses[k] for k in keys]), gt)
    assert len(loops) >= 5
    assert after < 0.5 * before


def test_hidden_state_constraint_equals_the_true_relative_similarity(icl_frames):
    run = run_loop_closure(icl_frames[:50], rotation_drift=0.0)
    accepted = [c for c in run.constraints if c.accepted]
    assert accepted
    poses = run.tracker.keyframe_poses()
    for c in accepted:
        truth = relative_transform(poses[c.i], poses[c.j])  # drift-free tracking is globally consistent
        s_true, R_true, t_true = sim3_decompose(truth)
        s, R, t = sim3_decompose(torch.from_numpy(c.relative))
        assert float(s) == pytest.approx(float(s_true), rel=1e-3)
        assert float(so3_log(R_true.T @ R).norm()) < 1e-3
        assert float((t - t_true).norm()) < 1e-3 * max(1.0, float(t_true.norm()))
