"""Posed mode without depth (a phone giving device poses but no LiDAR): the poses are kept, the model predicts the
surfels, and those are brought from model units to the poses' units by the ratio of the two path lengths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from worker.config import SlamConfig
from worker.data import Frame, open_source
from worker.geometry import sim3_inverse
from worker.slam import SlamSystem

SIZE = (80, 60)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    frames = list(open_source(Path(__file__).parents[1] / "data" / "icl_mini", max_frames=6, resize=SIZE,
                              use_gt_poses=True, use_gt_depth=False))
    assert all(f.depth is None and f.pose is not None for f in frames)
    return frames


@pytest.fixture(scope="module")
def random_checkpoint(tmp_path_factory) -> str:
    """The untrained tiny model of seed 1 (its points lie in front of the camera; seed 0's lie behind it), saved so
    that it, not the shipped trained weights, runs: the median comparison below assumes its flat point maps."""
    from worker.frontend import build_model
    from worker.frontend.checkpoint import save_checkpoint

    path = tmp_path_factory.mktemp("weights") / "random_tiny_seed1.safetensors"
    with torch.random.fork_rng():
        torch.manual_seed(1)
        save_checkpoint(build_model("tiny"), path)
    return str(path)


@pytest.fixture(scope="module")
def run(frames: list[Frame], random_checkpoint: str) -> tuple[SlamSystem, list]:
    config = SlamConfig.preset("test", frontend={"keyframe_every": 3, "min_confidence": 1.0,
                                                 "checkpoint": random_checkpoint},
                               mapping={"refine_iterations": 0}, input={"depth_source": "model"})
    system = SlamSystem(config)
    results = [system.push(f) for f in frames]
    system.finish()
    return system, results


def test_poses_are_the_given_ones_and_the_model_runs_on_every_frame(frames, run) -> None:
    system, results = run
    assert system.mode == "posed" and system.tracker is not None
    assert system.loop_closer is None and system.depth_points is None  # no metric points to close loops with
    for frame, result in zip(frames, results):
        np.testing.assert_allclose(result.pose, frame.pose, atol=1e-9)
    # six frames: the device poses are still judged when the stream ends; finish() decides and maps them
    assert [index for index, _, _ in system.trajectory("keyframes")] == [frames[0].index, frames[3].index]
    breakdown = system.stats()["runtime_breakdown"]
    assert breakdown["frontend_inference"]["events"] == len(frames)
    assert breakdown["map_merge"]["events"] == 2


def test_model_surfels_are_scaled_to_the_given_poses(frames, run) -> None:
    system, _ = run
    assert system.num_gaussians > 100
    assert set(system.mapping_stage.map.surfels.keyframe_ids.tolist()) <= {0, 3}
    # Keyframe 0 waits for the first step of the path to learn the scale: with two frames, that is the final ratio.
    two = SlamSystem(system.config)
    for frame in frames[:2]:
        two.push(frame)
    two.finish()
    stats = two.stats()
    ratio = stats["path_given"] / stats["path_tracked"]
    assert np.isfinite(ratio) and ratio > 0
    w2c = sim3_inverse(torch.from_numpy(np.asarray(frames[0].pose, np.float64))).float()
    surfels = two.mapping_stage.map.surfels
    z_map = (surfels.means @ w2c[:3, :3].T + w2c[:3, 3])[:, 2]
    points, conf = two.tracker.keyframe_points(0)
    z_model = points[..., 2][conf >= two.config.frontend.min_confidence]
    assert float(z_map.median()) == pytest.approx(ratio * float(z_model.median()), rel=0.1)


def test_a_frame_without_pose_in_posed_mode_is_lost_not_an_error(frames) -> None:
    system = SlamSystem(SlamConfig.preset("test", mapping={"enabled": False}))
    first = system.push(frames[0])
    gap = system.push(Frame(1, 0.1, frames[1].image, frames[1].intrinsics))
    assert not gap.tracked and gap.events[0].reason == "the frame has no device pose"
    np.testing.assert_allclose(gap.pose, first.pose)
    back = system.push(frames[2])
    assert back.tracked and [e.TYPE for e in back.events] == ["relocalized"]
    system.close()
