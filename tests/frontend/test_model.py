"""The recurrent feed-forward model: RoPE, attention, decoder exchange, step contract, state handling, precision."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from frontend_test_config import TEST_CONFIG, single_torch_thread  # noqa: F401

from worker.frontend import FeedForwardModel, HiddenState, build_model
from worker.frontend.blocks import SelfAttention, apply_rope_2d
from worker.frontend.decoders import run_interleaved_decoders
from worker.frontend.encoder import state_positions


@pytest.fixture(scope="module")
def model() -> FeedForwardModel:
    torch.manual_seed(0)
    return build_model(TEST_CONFIG)


def _image(batch: int = 1, h: int = 48, w: int = 64, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 3, h, w, generator=g)


# ---------------------------------------------------------------- RoPE and attention
def test_rope_rotates_row_half_then_column_half_with_rotate_half_pairing() -> None:
    # head dim 8: rows rotate channels (0,2),(1,3); columns rotate (4,6),(5,7); base 100 over 4 channels per axis.
    x = torch.arange(1.0, 9.0).reshape(1, 1, 1, 8)
    pos = torch.tensor([[[2, -3]]])
    out = apply_rope_2d(x, pos, base=100.0)[0, 0, 0]
    expected = []
    for axis_pos, part in ((2.0, x[0, 0, 0, :4]), (-3.0, x[0, 0, 0, 4:])):
        angles = [axis_pos * 100.0 ** (-0.0), axis_pos * 100.0 ** (-2.0 / 4)]
        u, v = part[:2], part[2:]
        cos = torch.tensor([math.cos(a) for a in angles])
        sin = torch.tensor([math.sin(a) for a in angles])
        expected.append(torch.cat((u * cos - v * sin, v * cos + u * sin)))
    assert torch.allclose(out, torch.cat(expected), atol=1e-5)


def test_rope_scores_depend_only_on_relative_signed_positions() -> None:
    q, k = torch.randn(1, 1, 1, 16), torch.randn(1, 1, 1, 16)

    def score(pq, pk):
        rq = apply_rope_2d(q, torch.tensor([[pq]]))
        rk = apply_rope_2d(k, torch.tensor([[pk]]))
        return float((rq * rk).sum())

    assert score((-1, -1), (3, 5)) == pytest.approx(score((9, 2), (13, 8)), abs=1e-4)
    assert score((-1, -1), (3, 5)) != pytest.approx(score((-1, -1), (5, 3)), abs=1e-4)


def test_self_attention_matches_explicit_softmax() -> None:
    attn = SelfAttention(32, heads=4)
    x, pos = torch.randn(2, 7, 32), torch.randint(-1, 5, (2, 7, 2))
    B, N, C = x.shape
    q, k, v = attn.qkv(x).reshape(B, N, 3, 4, 8).permute(2, 0, 3, 1, 4)
    q, k = apply_rope_2d(q, pos), apply_rope_2d(k, pos)
    weights = F.softmax(q @ k.transpose(-1, -2) / math.sqrt(8), dim=-1)
    expected = attn.proj((weights @ v).transpose(1, 2).reshape(B, N, C))
    assert torch.allclose(attn(x, pos), expected, atol=1e-5)


def test_decoders_exchange_previous_layer_outputs_simultaneously() -> None:
    seen = []

    class Recorder(torch.nn.Module):
        def __init__(self, tag: str) -> None:
            super().__init__()
            self.tag = tag

        def forward(self, x, y, x_pos, y_pos):
            seen.append((self.tag, float(x[0, 0, 0]), float(y[0, 0, 0])))
            return x + (1.0 if self.tag == "img" else 100.0)

    image_blocks = torch.nn.ModuleList(Recorder("img") for _ in range(3))
    state_blocks = torch.nn.ModuleList(Recorder("state") for _ in range(3))
    x, s = torch.zeros(1, 2, 4), torch.zeros(1, 3, 4)
    outs, final_state = run_interleaved_decoders(image_blocks, state_blocks, x, torch.zeros(1, 2, 2), s,
                                                 torch.zeros(1, 3, 2))
    # Layer l: state block reads image stream l-1 and image block reads state stream l-1.
    assert seen == [("state", 0.0, 0.0), ("img", 0.0, 0.0), ("state", 100.0, 1.0), ("img", 1.0, 100.0),
                    ("state", 200.0, 2.0), ("img", 2.0, 200.0)]
    assert [float(o[0, 0, 0]) for o in outs] == [1.0, 2.0, 3.0]
    assert float(final_state[0, 0, 0]) == 300.0


def test_state_positions_follow_an_even_width_grid() -> None:
    pos = state_positions(768)[0]
    assert pos.shape == (768, 2)
    assert pos[27].tolist() == [0, 27] and pos[28].tolist() == [1, 0] and pos[-1].tolist() == [27, 11]


def test_paper_head_counts() -> None:
    m = build_model("paper", device="meta")
    assert m.dec_blocks[0].attn.heads == 12 and m.dec_blocks[0].cross_attn.heads == 12
    assert m.dec_blocks_state[0].attn.heads == 16 and m.dec_blocks_state[0].cross_attn.heads == 16
    assert m.pose_retriever.read_blocks[0].attn.heads == 12
    assert m.pose_retriever.mem.shape == (1, 256, 1536)
    assert m.enc_blocks[0].attn.heads == 16


# ---------------------------------------------------------------- step contract
def test_step_outputs_have_the_contract_shapes_and_ranges(model: FeedForwardModel) -> None:
    image = _image(batch=2)
    state = model.init_state(batch=2)
    with torch.no_grad():
        out = model.step(image, state)
    assert out.pose_c2w.shape == (2, 4, 4)
    R = out.pose_c2w[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(2, 3, 3), atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(2), atol=1e-5)
    assert torch.equal(out.pose_c2w[:, 3], torch.tensor([[0.0, 0, 0, 1]] * 2))
    for name in ("points_cam", "points_world", "colors"):
        assert getattr(out, name).shape == (2, 48, 64, 3)
    assert out.conf.shape == out.conf_world.shape == out.opacity.shape == (2, 48, 64)
    assert (out.conf >= 1).all() and (out.conf_world >= 1).all()
    assert ((out.opacity > 0) & (out.opacity < 1)).all()
    assert ((out.colors >= 0) & (out.colors <= 1)).all()
    assert out.quats.shape == (2, 48, 64, 4)
    assert torch.allclose(out.quats.norm(dim=-1), torch.ones(2, 48, 64), atol=1e-5)
    assert (out.quats[..., 0] >= 0).all()
    assert out.scales.shape == (2, 48, 64, 2) and (out.scales > 0).all()
    assert out.state.state_tokens.shape == (2, TEST_CONFIG.state_size, TEST_CONFIG.dec_dim)
    assert out.state.pose_memory.shape == (2, TEST_CONFIG.memory_size, 2 * TEST_CONFIG.dec_dim)
    assert out.state.frames_seen == 1


def test_batch_elements_are_independent(model: FeedForwardModel) -> None:
    images = _image(batch=2)
    with torch.no_grad():
        both = model.step(images, model.init_state(2))
        second = model.step(images[1:], model.init_state(1))
    assert torch.allclose(both.points_cam[1], second.points_cam[0], atol=1e-5)
    assert torch.allclose(both.pose_c2w[1], second.pose_c2w[0], atol=1e-5)


def test_init_state_is_learned_and_image_independent(model: FeedForwardModel) -> None:
    a, b = model.init_state(), model.init_state()
    expected = model.decoder_embed_state(model.register_tokens.weight)
    assert torch.allclose(a.state_tokens[0], expected) and torch.equal(a.state_tokens, b.state_tokens)
    assert torch.equal(a.pose_memory[0], model.pose_retriever.mem[0]) and a.frames_seen == 0


def test_update_false_reads_without_writing_and_is_repeatable(model: FeedForwardModel) -> None:
    with torch.no_grad():
        state = model.step(_image(seed=1), model.init_state()).state
        before = state.clone()
        r1 = model.step(_image(seed=2), state, update=False)
        r2 = model.step(_image(seed=2), state, update=False)
        written = model.step(_image(seed=2), state, update=True)
    assert r1.state is state
    assert torch.equal(state.state_tokens, before.state_tokens) and torch.equal(state.pose_memory, before.pose_memory)
    assert torch.equal(r1.points_cam, r2.points_cam) and torch.equal(r1.pose_c2w, r2.pose_c2w)
    # update=True produces the same readout but a new state.
    assert torch.allclose(written.points_cam, r1.points_cam)
    assert not torch.allclose(written.state.state_tokens, state.state_tokens)
    assert not torch.allclose(written.state.pose_memory, state.pose_memory)
    assert written.state.frames_seen == state.frames_seen + 1


def test_the_state_conditions_the_prediction(model: FeedForwardModel) -> None:
    image = _image(seed=3)
    with torch.no_grad():
        fresh = model.step(image, model.init_state())
        later = model.step(image, model.step(_image(seed=4), model.init_state()).state)
    assert not torch.allclose(fresh.points_world, later.points_world)
    assert not torch.allclose(fresh.pose_c2w, later.pose_c2w)  # pose token read from the written pose memory


def test_restored_hidden_state_relocalizes_identically(model: FeedForwardModel) -> None:
    with torch.no_grad():
        state = model.step(_image(seed=5), model.init_state()).state
        restored = HiddenState.from_bytes(state.to_bytes(torch.float32))
        a = model.step(_image(seed=6), state, update=False)
        b = model.step(_image(seed=6), restored, update=False)
    assert torch.equal(a.points_cam, b.points_cam) and torch.equal(a.pose_c2w, b.pose_c2w)


def test_encode_image_gives_tokens_and_positions(model: FeedForwardModel) -> None:
    with torch.no_grad():
        tokens, pos = model.encode_image(_image(h=32, w=80))
    assert tokens.shape == (1, 2 * 5, TEST_CONFIG.enc_dim)
    assert pos.shape == (1, 10, 2) and pos[0, 6].tolist() == [1, 1]


def test_ray_map_input_changes_the_tokens(model: FeedForwardModel) -> None:
    image = _image()
    ray_map = torch.randn(1, 48, 64, 6)
    with torch.no_grad():
        plain = model.step(image, model.init_state())
        with_rays = model.step(image, model.init_state(), ray_map=ray_map)
    assert not torch.allclose(plain.points_cam, with_rays.points_cam)


def test_bad_inputs_are_rejected(model: FeedForwardModel) -> None:
    state = model.init_state()
    with pytest.raises(ValueError, match="multiples of 16"):
        model.step(torch.rand(1, 3, 50, 64), state)
    with pytest.raises(ValueError, match=r"\[B, 3, H, W\]"):
        model.step(torch.rand(1, 4, 48, 64), state)
    with pytest.raises(ValueError, match="batch"):
        model.step(torch.rand(2, 3, 48, 64), state)
    with pytest.raises(ValueError, match="precision"):
        model.set_precision("int8")
    with pytest.raises(ValueError, match="unknown frontend config"):
        build_model("huge")


def test_gradients_reach_encoder_decoders_memory_and_heads() -> None:
    model = build_model(TEST_CONFIG).train()
    state = model.init_state()
    out1 = model.step(_image(seed=7), state)
    out2 = model.step(_image(seed=8), out1.state)
    loss = sum(o.points_cam.abs().mean() + o.pose_c2w[:, :3, 3].abs().sum() + o.colors.mean() + o.scales.mean()
               for o in (out1, out2))
    loss.backward()
    for name in ("patch_embed.proj.weight", "enc_blocks.0.attn.qkv.weight", "dec_blocks.0.cross_attn.projq.weight",
                 "dec_blocks_state.0.mlp.fc1.weight", "pose_retriever.read_blocks.0.cross_attn.projk.weight",
                 "downstream_head.dpt_self.head.4.weight", "downstream_head.dpt_gs.head.4.weight",
                 "downstream_head.pose_head.mlp.fc2.weight", "register_tokens.weight",
                 "downstream_head.gs_adapter.fc2.weight"):
        grad = dict(model.named_parameters())[name].grad
        assert grad is not None and grad.abs().sum() > 0, name


def test_bf16_autocast_runs_the_decoders_in_reduced_precision_and_heads_in_fp32() -> None:
    model = build_model(TEST_CONFIG)
    image, state = _image(), model.init_state()
    with torch.no_grad():
        ref = model.step(image, state)
        model.set_precision("bf16")
        low = model.step(image, state)
        tokens, _ = model.encode_image(image)
    assert tokens.dtype == torch.bfloat16
    assert low.points_cam.dtype == torch.float32 and low.state.state_tokens.dtype == torch.float32
    assert torch.isfinite(low.points_cam).all()
    assert (low.points_cam - ref.points_cam).abs().mean() < 0.1 * ref.points_cam.abs().mean() + 1e-3


def test_accelerated_stepper_falls_back_to_step_on_cpu(model: FeedForwardModel) -> None:
    stepper = build_model(TEST_CONFIG).compile_step(48, 64, precision="fp32")
    assert not stepper.enabled
    out = stepper(_image(), stepper.model.init_state())
    assert out.state.frames_seen == 1


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_graph_replay_matches_eager_step() -> None:
    model = build_model("tiny", device="cuda")
    stepper = model.compile_step(160, 224, precision="fp32")
    images = [torch.rand(1, 3, 160, 224, device="cuda") for _ in range(3)]
    state_g, state_e = model.init_state(), model.init_state()
    for image in images:
        with torch.inference_mode():
            eager = model.step(image, state_e)
        graphed = stepper(image, state_g)
        assert torch.allclose(graphed.points_cam, eager.points_cam, atol=1e-3)
        assert torch.allclose(graphed.pose_c2w, eager.pose_c2w, atol=1e-4)
        state_g, state_e = graphed.state, eager.state
