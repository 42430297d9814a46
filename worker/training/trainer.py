"""The frontend trainer: curriculum stages, truncated backpropagation through time, checkpoints, loss curves."""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from worker.geometry import unproject_depth

from .clips import Clip, SequenceBank
from .curriculum import Curriculum, Stage, set_trainable
from .losses import RenderLossWeights, geometry_loss, pose_loss
from .render_terms import merged_render_loss, per_frame_render_loss

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Loss weights (eq. 8), optimisation and bookkeeping."""

    pose_weight: float = 1.0
    geo_weight: float = 1.0
    conf_alpha: float = 0.2
    render: RenderLossWeights = field(default_factory=RenderLossWeights)
    render_stride: int = 2  # every n-th pixel's surfel is rendered (scales multiplied by n)
    render_downscale: int = 2  # rendering losses at 1/n of the model resolution
    max_gap: int = 2  # clips take every k-th frame of a sequence, k drawn from 1..max_gap (faster apparent motion)
    grad_clip: float = 1.0
    weight_decay: float = 0.05
    checkpoint_every: int = 200
    keep_every: int = 0  # also keep a copy of the weights every n steps (model_step{n}.safetensors); 0 = never
    lr_warmup: int = 0  # steps of linear warm-up at the start of every stage
    lr_cosine: bool = False  # cosine decay to 10% of the stage's rate over the stage
    log_every: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_gap < 1:
            raise ValueError(f"max_gap must be at least 1, got {self.max_gap}")


@dataclass
class StepLosses:
    """The loss terms of one optimisation step."""

    step: int
    stage: str
    total: float
    pose: float
    geo: float
    render: float
    seconds: float


def downscaled(images: torch.Tensor, depths: torch.Tensor, K: torch.Tensor, factor: int
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images [L,B,H,W,3] area-averaged and depths [L,B,H,W] subsampled by `factor`, with K to match."""
    if factor == 1:
        return images, depths, K
    L, B, H, W, _ = images.shape
    small = torch.nn.functional.avg_pool2d(images.reshape(L * B, H, W, 3).permute(0, 3, 1, 2), factor)
    small = small.permute(0, 2, 3, 1).reshape(L, B, H // factor, W // factor, 3)
    start = factor // 2
    K_small = K.clone()
    K_small[:2] /= factor
    return small, depths[:, :, start::factor, start::factor].contiguous(), K_small


def clip_losses(model, clip: Clip, stage: Stage, cfg: TrainConfig, perceptual=None) -> dict[str, float]:
    """Run a clip through the model chunk by chunk (TBPTT): each chunk backpropagates on its own.

    Returns the mean loss terms. The caller steps the optimiser after this returns.
    """
    state = model.init_state(batch=1)
    L = len(clip)
    terms = {"pose": 0.0, "geo": 0.0, "render": 0.0, "total": 0.0}
    for start in range(0, L, stage.tbptt_chunk):
        end = min(L, start + stage.tbptt_chunk)
        outputs = []
        for t in range(start, end):
            out = model.step(clip.chw(t), state)
            outputs.append(out)
            state = out.state
        pose = sum(pose_loss(o.pose_c2w, clip.c2w[t]) for o, t in zip(outputs, range(start, end)))
        geo = clip.images.new_zeros(())
        for o, t in zip(outputs, range(start, end)):
            gt_cam = unproject_depth(clip.depths[t, 0], clip.K)[None]
            valid = clip.depths[t] > 0
            geo = geo + geometry_loss(o.points_cam, o.conf, gt_cam, valid, cfg.conf_alpha)
            gt_world = gt_cam @ clip.c2w[t, 0, :3, :3].T + clip.c2w[t, 0, :3, 3]
            geo = geo + geometry_loss(o.points_world, o.conf_world, gt_world, valid, cfg.conf_alpha)
        render = clip.images.new_zeros(())
        if stage.render_weight > 0:
            sl = slice(start, end)
            images, depths, K = downscaled(clip.images[sl], clip.depths[sl], clip.K, cfg.render_downscale)
            render = per_frame_render_loss(outputs, images, depths, K, cfg.render, perceptual,
                                           stride=cfg.render_stride)
            if end - start > 1:
                render = render + merged_render_loss(outputs, images, depths, clip.c2w[sl], K, cfg.render,
                                                     perceptual, stride=2 * cfg.render_stride)
        n = end - start
        total = (cfg.pose_weight * pose + cfg.geo_weight * geo + stage.render_weight * render) / n
        total.backward()
        state = state.clone()
        state.state_tokens = state.state_tokens.detach()
        state.pose_memory = state.pose_memory.detach()
        for key, value in (("pose", pose), ("geo", geo), ("render", render), ("total", total * n)):
            terms[key] += float(value.detach()) / L
    return terms


class Trainer:
    """Trains a FeedForwardModel on a SequenceBank through a Curriculum, with checkpoints and resume."""

    def __init__(self, model: torch.nn.Module, bank: SequenceBank, curriculum: Curriculum, out_dir: Path,
                 config: TrainConfig | None = None, perceptual: Callable | None = None) -> None:
        self.model = model
        self.bank = bank
        self.curriculum = curriculum
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.config = config or TrainConfig()
        self.perceptual = perceptual
        self.step = 0
        self.history: list[StepLosses] = []
        self._stage_index = -1
        self.optimizer: torch.optim.Optimizer | None = None
        torch.manual_seed(self.config.seed)

    def _enter_stage(self, index: int, stage: Stage) -> None:
        params = set_trainable(self.model, stage)
        self.optimizer = torch.optim.AdamW(params, lr=stage.lr, betas=(0.9, 0.95),
                                           weight_decay=self.config.weight_decay)
        self._stage_index = index
        log.info("stage %s: %d steps at lr %.1e, %d-%d frames, %d trainable tensors",
                 stage.name, stage.steps, stage.lr, stage.min_frames, stage.max_frames, len(params))

    def train(self, steps: int | None = None, progress: Callable[[StepLosses], None] | None = None) -> None:
        """Run until the curriculum ends (or `steps` more steps)."""
        end = self.curriculum.total_steps if steps is None else min(self.curriculum.total_steps, self.step + steps)
        self.model.train()
        while self.step < end:
            index, stage = self.curriculum.stage_at(self.step)
            if index != self._stage_index:
                self._enter_stage(index, stage)
            started = time.perf_counter()
            length = int(self.bank.rng.integers(stage.min_frames, stage.max_frames + 1))
            clip = self.bank.sample(length, max_gap=self.config.max_gap)
            self._set_learning_rate(stage)
            self.optimizer.zero_grad(set_to_none=True)
            terms = clip_losses(self.model, clip, stage, self.config, self.perceptual)
            if not math.isfinite(terms["total"]):
                raise FloatingPointError(f"loss became {terms['total']} at step {self.step}")
            torch.nn.utils.clip_grad_norm_([p for p in self.model.parameters() if p.requires_grad],
                                           self.config.grad_clip)
            self.optimizer.step()
            self.step += 1
            record = StepLosses(self.step, stage.name, terms["total"], terms["pose"], terms["geo"], terms["render"],
                                time.perf_counter() - started)
            self.history.append(record)
            if progress is not None:
                progress(record)
            keep = self.config.keep_every > 0 and self.step % self.config.keep_every == 0
            if keep or self.step % self.config.checkpoint_every == 0 or self.step == end:
                self.save_checkpoint()
            if keep:
                shutil.copyfile(self.out_dir / "model.safetensors", self.out_dir / f"model_step{self.step}.safetensors")
            if self.step % self.config.log_every == 0:
                recent = self.history[-self.config.log_every:]
                log.info("step %d %s lr %.2e loss %.4f pose %.4f geo %.4f render %.4f (%.2f s/step)", self.step,
                         stage.name, self.learning_rate(stage), *(sum(getattr(h, k) for h in recent) / len(recent)
                                                                  for k in ("total", "pose", "geo", "render",
                                                                            "seconds")))

    def learning_rate(self, stage: Stage) -> float:
        """The rate of the current step: the stage's rate, warmed up and cosine-decayed as configured."""
        start = sum(s.steps for s in self.curriculum.stages[:self._stage_index])
        local = self.step - start
        factor = 1.0
        if self.config.lr_warmup > 0:
            factor *= min(1.0, (local + 1) / self.config.lr_warmup)
        if self.config.lr_cosine and stage.steps > 1:
            progress = min(1.0, local / (stage.steps - 1))
            factor *= 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * progress))
        return stage.lr * factor

    def _set_learning_rate(self, stage: Stage) -> None:
        lr = self.learning_rate(stage)
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    # ---- checkpoints -------------------------------------------------------------------------------------
    def save_checkpoint(self) -> Path:
        """Model weights (safetensors), optimiser state (safetensors + JSON), history and loss curves."""
        from worker.frontend.checkpoint import save_checkpoint

        save_checkpoint(self.model, self.out_dir / "model.safetensors", {"step": str(self.step)})
        tensors, meta = _flatten_optimizer(self.optimizer)
        save_file(tensors, str(self.out_dir / "optimizer.safetensors"))
        state = {"step": self.step, "stage_index": self._stage_index, "optimizer": meta,
                 "history": [asdict(h) for h in self.history]}
        (self.out_dir / "trainer.json").write_text(json.dumps(state))
        write_loss_curves(self.history, self.out_dir / "loss_curves.png")
        return self.out_dir / "model.safetensors"

    def resume(self) -> bool:
        """Load the latest checkpoint of out_dir if there is one; True when resumed."""
        state_path = self.out_dir / "trainer.json"
        if not state_path.exists():
            return False
        state = json.loads(state_path.read_text())
        self.model.load_state_dict(load_file(str(self.out_dir / "model.safetensors")))
        self.step = int(state["step"])
        self.history = [StepLosses(**h) for h in state["history"]]
        index, stage = self.curriculum.stage_at(self.step)
        self._enter_stage(index, stage)
        if state["stage_index"] == index:
            _restore_optimizer(self.optimizer, load_file(str(self.out_dir / "optimizer.safetensors")),
                               state["optimizer"])
        return True


def _flatten_optimizer(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    sd = optimizer.state_dict()
    tensors, scalars = {}, {}
    for pid, pstate in sd["state"].items():
        for key, value in pstate.items():
            if torch.is_tensor(value):
                tensors[f"{pid}.{key}"] = value.contiguous()
            else:
                scalars[f"{pid}.{key}"] = value
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def _restore_optimizer(optimizer: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    state: dict[int, dict] = {}
    for name, value in tensors.items():
        pid, key = name.split(".", 1)
        state.setdefault(int(pid), {})[key] = value
    for name, value in meta["scalars"].items():
        pid, key = name.split(".", 1)
        state.setdefault(int(pid), {})[key] = value
    optimizer.load_state_dict({"state": state, "param_groups": meta["param_groups"]})


def write_loss_curves(history: list[StepLosses], path: Path) -> None:
    """Plot total / pose / geometry / render losses against the step (PNG)."""
    if not history:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h.step for h in history]
    window = max(1, min(25, len(history) // 10))
    changes = [b.step for a, b in zip(history, history[1:]) if a.stage != b.stage]
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.5))
    for ax, key in zip(axes, ("total", "pose", "geo", "render")):
        values = np.array([getattr(h, key) for h in history])
        ax.plot(steps, values, lw=0.5, alpha=0.4)
        if window > 1:
            smooth = np.convolve(values, np.ones(window) / window, mode="valid")
            ax.plot(steps[window - 1:], smooth, lw=1.5, label=f"mean of {window}")
        for step in changes:
            ax.axvline(step, color="grey", ls="--", lw=0.8)
        ax.set_title(key)
        ax.set_xlabel("step (dashed: stage change)" if changes else "step")
        ax.set_yscale("symlog" if values.min() <= 0 else "log")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
