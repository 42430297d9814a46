"""Training: losses, curriculum freezing, clip sampling, a real optimisation run, checkpoint and resume."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from worker.data.frame import Frame
from worker.frontend import build_model
from worker.frontend.configs import get_config
from worker.geometry import Intrinsics, sim3_from_quat, unproject_depth
from worker.training.clips import SequenceBank, fit_frame
from worker.training.curriculum import Curriculum, Stage, set_trainable
from worker.training.losses import geometry_loss, pose_loss, render_loss, ssim
from worker.training.trainer import TrainConfig, Trainer, clip_losses

MICRO = replace(get_config("tiny"), name="micro", enc_dim=48, enc_depth=2, enc_heads=2, dec_dim=32, dec_heads=2,
                state_dec_heads=2, state_size=16, memory_size=4, memory_heads=2, dpt_layer_dims=(8, 8, 16, 16),
                dpt_feature_dim=16, dpt_last_dim=8, gs_adapter_hidden=32, image_long_side=64)


def test_pose_loss_is_zero_for_equal_poses_and_grows_with_error():
    q = torch.tensor([[0.9, 0.1, -0.2, 0.3]])
    T = sim3_from_quat(q, torch.tensor([[0.1, 0.2, 0.3]]))
    assert pose_loss(T, T) < 1e-6
    moved = T.clone()
    moved[:, 0, 3] += 0.5
    assert pose_loss(moved, T) == pytest.approx(0.5, abs=1e-5)
    flipped = sim3_from_quat(-q, torch.tensor([[0.1, 0.2, 0.3]]))  # same rotation, other quaternion sign
    assert pose_loss(flipped, T) < 1e-5


def test_geometry_loss_prefers_accurate_confident_points():
    gt = torch.rand(1, 4, 5, 3)
    valid = torch.ones(1, 4, 5, dtype=torch.bool)
    conf = torch.full((1, 4, 5), 2.0)
    exact = geometry_loss(gt, conf, gt, valid)
    off = geometry_loss(gt + 0.1, conf, gt, valid)
    assert exact == pytest.approx(-0.2 * np.log(2.0), abs=1e-6)
    assert off > exact
    valid[..., :2] = False
    assert geometry_loss(torch.where(valid[..., None], gt, gt + 5), conf, gt, valid) == pytest.approx(float(exact))


def test_ssim_and_render_loss():
    img = torch.rand(1, 32, 32, 3)
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-5)
    assert float(ssim(img, torch.rand(1, 32, 32, 3))) < 0.5
    depth = torch.rand(1, 32, 32) + 1
    assert float(render_loss(img, depth, img, depth)) == pytest.approx(0.0, abs=1e-5)
    assert float(render_loss(img * 0.5, depth, img, depth)) > 0.01


def test_curriculum_stages_and_freezing():
    plan = Curriculum.paper()
    assert [s.lr for s in plan.stages] == [2e-4, 1e-5, 5e-6]
    assert plan.stages[2].max_frames == 32 and plan.stages[1].min_frames == plan.stages[1].max_frames == 4
    assert plan.stage_at(0)[1].name == "gs_warmup" and plan.stage_at(5000)[1].name == "adapt"
    assert plan.scaled(0.01).total_steps == 150
    model = build_model(MICRO)
    trainable = set_trainable(model, plan.stages[0])
    names = {n for n, p in model.named_parameters() if p.requires_grad}
    assert trainable and all("gs" in n for n in names)
    assert not any(p.requires_grad for n, p in model.named_parameters() if n.startswith("enc_blocks"))
    with pytest.raises(ValueError, match="unknown parameter groups"):
        Stage("bad", 1, 1e-3, 1, 2, ("nonsense",))


def test_continued_curriculum_trains_everything_then_long_clips():
    plan = Curriculum.continued(steps=100, lr=3e-4, max_frames=8, clip_fraction=0.6)
    assert [(s.name, s.steps, s.lr, s.min_frames, s.max_frames) for s in plan.stages] == [
        ("clips4", 60, 3e-4, 4, 4), ("long", 40, 1.5e-4, 4, 8)]
    assert all(s.trainable == ("all",) and s.render_weight == 1.0 for s in plan.stages)
    assert plan.stage_at(59)[1].name == "clips4" and plan.stage_at(60)[1].name == "long"
    model = build_model(MICRO)
    set_trainable(model, plan.stages[1])
    assert all(p.requires_grad for p in model.parameters())
    with pytest.raises(ValueError, match="clip_fraction"):
        Curriculum.continued(clip_fraction=1.5)


def test_long_chunk_sets_the_last_stage_only_and_changes_the_gradient_not_the_loss():
    plan = Curriculum.continued(steps=100, max_frames=8, clip_fraction=0.6).with_long_chunk(8)
    assert [s.tbptt_chunk for s in plan.stages] == [4, 8]
    with pytest.raises(ValueError, match="tbptt_chunk"):
        plan.with_long_chunk(0)
    with pytest.raises(ValueError, match="tbptt_chunk"):
        Stage("long", 1, 1e-4, 4, 8, ("all",), tbptt_chunk=0)
    bank = SequenceBank(64, 48, seed=3)
    bank.add(synthetic_frames(6))
    clip = bank.sample(4, max_gap=1)
    grads, totals = [], []
    for chunk in (1, 4):
        torch.manual_seed(0)
        model = build_model(MICRO)
        stage = Stage("long", 1, 1e-4, 4, 4, ("all",), tbptt_chunk=chunk, render_weight=0.0)
        totals.append(clip_losses(model, clip, stage, TrainConfig())["total"])
        grads.append(torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1)
                                for p in model.parameters()]))
    # the forward pass is the same; only the truncation of the backward pass differs
    assert totals[0] == pytest.approx(totals[1], rel=1e-5)
    assert not torch.allclose(grads[0], grads[1], rtol=1e-3, atol=1e-7)


def synthetic_frames(n: int, width: int = 80, height: int = 60) -> list[Frame]:
    """A camera sliding past a slanted textured plane (exact depth), enough for a real optimisation signal."""
    intr = Intrinsics(70.0, 70.0, width / 2, height / 2, width, height)
    gen = np.random.default_rng(0)
    texture = gen.integers(0, 255, size=(height, width + 4 * n, 3), dtype=np.uint8)
    frames = []
    for i in range(n):
        depth = np.tile(np.linspace(1.5, 2.5, width, dtype=np.float32), (height, 1))
        pose = np.eye(4)
        pose[0, 3] = 0.05 * i
        frames.append(Frame(i, i / 30, np.ascontiguousarray(texture[:, 4 * i:4 * i + width]), intr, depth,
                            gt_pose=pose))
    return frames


def test_fit_frame_resizes_and_crops_consistently():
    frame = synthetic_frames(1)[0]
    image, depth, intr = fit_frame(frame, 64, 48)
    assert image.shape == (48, 64, 3) and depth.shape == (48, 64)
    assert intr.width == 64 and intr.fx == pytest.approx(70.0 * 0.8)
    with pytest.raises(ValueError, match="needs depth"):
        fit_frame(Frame(0, 0.0, frame.image), 64, 48)


def test_sequence_bank_clips_are_relative_to_their_first_frame():
    bank = SequenceBank(64, 48)
    bank.add(synthetic_frames(6))
    clip = bank.sample(4)
    assert clip.images.shape == (4, 1, 48, 64, 3) and clip.chw(0).shape == (1, 3, 48, 64)
    assert torch.allclose(clip.c2w[0, 0], torch.eye(4), atol=1e-6)
    pts = unproject_depth(clip.depths[0, 0], clip.K)
    assert pts[..., 2].min() > 1.0


def test_sequence_bank_max_gap_sets_the_frame_stride():
    bank = SequenceBank(64, 48, seed=1)
    bank.add(synthetic_frames(10))  # the camera moves 0.05 m along x per frame
    steps = {round(float(bank.sample(3, max_gap=1).c2w[1, 0, 0, 3]), 3) for _ in range(20)}
    assert steps == {0.05}
    steps = {round(float(bank.sample(3, max_gap=3).c2w[1, 0, 0, 3]), 3) for _ in range(40)}
    assert steps == {0.05, 0.1, 0.15}
    with pytest.raises(ValueError, match="max_gap"):
        bank.sample(3, max_gap=0)
    with pytest.raises(ValueError, match="max_gap"):
        TrainConfig(max_gap=0)


def test_training_reduces_the_loss_and_resumes(tmp_path):
    torch.manual_seed(0)
    bank = SequenceBank(64, 48)
    bank.add(synthetic_frames(2))  # one 2-frame sequence: every sampled clip is this one
    model = build_model(MICRO)
    stage = Stage("all", 30, 3e-3, 2, 2, ("all",), render_weight=0.2)
    fixed = bank.sample(2)
    before = clip_losses(model, fixed, stage, TrainConfig())["total"]
    model.zero_grad(set_to_none=True)
    trainer = Trainer(model, bank, Curriculum((stage,)), tmp_path, TrainConfig(checkpoint_every=4))
    trainer.train(steps=8)
    after = clip_losses(model, fixed, stage, TrainConfig())["total"]
    assert after < before
    assert (tmp_path / "model.safetensors").exists() and (tmp_path / "loss_curves.png").stat().st_size > 1000
    resumed = Trainer(build_model(MICRO), bank, Curriculum((stage,)), tmp_path, TrainConfig())
    assert resumed.resume() and resumed.step == 8 and len(resumed.history) == 8
    for (name, p), q in zip(model.named_parameters(), resumed.model.parameters()):
        assert torch.equal(p, q), name
    assert resumed.optimizer.state_dict()["state"], "optimizer state restored"
    resumed.train(steps=1)
    assert resumed.step == 9


def test_prerendered_windows_round_trip_into_a_bank(tmp_path):
    from worker.training.cache import load_windows, render_synthetic_windows, save_windows

    windows = render_synthetic_windows([3, 4], window=3, width=48, height=32)
    assert windows[0][0].shape == (3, 32, 48, 3) and windows[0][0].dtype == np.uint8
    assert windows[0][1].shape == (3, 32, 48) and windows[0][1].min() > 0
    assert not np.array_equal(windows[0][0], windows[1][0])
    save_windows(windows, 48, 32, tmp_path / "w.safetensors")
    bank = SequenceBank(48, 32)
    assert load_windows([tmp_path / "w.safetensors"], bank) == 2
    images, depths, c2w, K = bank.sequences[0]
    assert torch.equal(images, torch.from_numpy(windows[0][0]))
    assert torch.allclose(depths, torch.from_numpy(windows[0][1]), rtol=1e-3)  # stored as fp16
    assert torch.allclose(c2w, torch.from_numpy(windows[0][2]))
    assert float(K[0, 0]) == pytest.approx(0.8 * 48)
    clip = bank.sample(3)
    assert clip.images.dtype == torch.float32 and 0.0 <= float(clip.images.min()) and float(clip.images.max()) <= 1.0
    with pytest.raises(ValueError, match="64x48"):
        load_windows([tmp_path / "w.safetensors"], SequenceBank(64, 48))


def test_held_out_seeds_are_refused_for_training():
    from worker.training.cache import render_synthetic_windows
    from worker.training.session import HELD_OUT_SEED_START

    with pytest.raises(ValueError, match="held out"):
        render_synthetic_windows([1, HELD_OUT_SEED_START + 2], window=2, width=32, height=32)


def test_from_scratch_fractions_and_learning_rate_schedule(tmp_path):
    plan = Curriculum.from_scratch(steps=100, lr=1e-3, max_frames=6, fractions=(0.6, 0.1, 0.2))
    assert [s.steps for s in plan.stages] == [60, 10, 20, 10] and plan.stages[-1].max_frames == 6
    with pytest.raises(ValueError, match="fractions"):
        Curriculum.from_scratch(fractions=(0.8, 0.2, 0.2))
    bank = SequenceBank(64, 48)
    bank.add(synthetic_frames(2))
    trainer = Trainer(build_model(MICRO), bank, plan, tmp_path, TrainConfig(lr_warmup=10, lr_cosine=True))
    trainer._enter_stage(0, plan.stages[0])
    rates = []
    for step in range(60):
        trainer.step = step
        rates.append(trainer.learning_rate(plan.stages[0]))
    assert rates[0] == pytest.approx(1e-4) and rates[9] == pytest.approx(1e-3, rel=0.06)
    assert rates[-1] == pytest.approx(1e-4) and all(a >= b for a, b in zip(rates[9:], rates[10:]))


def test_keep_every_leaves_weight_snapshots(tmp_path):
    bank = SequenceBank(64, 48)
    bank.add(synthetic_frames(2))
    stage = Stage("all", 4, 1e-3, 2, 2, ("all",), render_weight=0.0)
    trainer = Trainer(build_model(MICRO), bank, Curriculum((stage,)), tmp_path,
                      TrainConfig(checkpoint_every=100, keep_every=2))
    trainer.train()
    assert sorted(p.name for p in tmp_path.glob("model_step*.safetensors")) == [
        "model_step2.safetensors", "model_step4.safetensors"]
