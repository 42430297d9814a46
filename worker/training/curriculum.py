"""The three-stage training curriculum of appendix D.3, scaled for small models and CPU budgets.

Stage 1 warms up the 2DGS head alone (rest frozen, high rate, 1-4 frames); stage 2 unfreezes the decoders, the pose
head and the point-mean head at a low rate on 4 frames; stage 3 trains on longer clips (up to 32 frames) with
truncated backpropagation. A model trained from scratch (no CUT3R weights) first needs a stage 0 that trains every
parameter on the pose and geometry losses; `Curriculum.from_scratch` prepends it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch

# Parameter-name fragments of each trainable group (names follow CUT3R's checkpoint layout).
PARAMETER_GROUPS: dict[str, tuple[str, ...]] = {
    "gs_head": ("gs_head", "dpt_gs", "gs_adapter"),
    "decoder": ("dec_blocks", "decoder_embed", "dec_norm", "pose_retriever", "register_tokens", "pose_token"),
    "pose_head": ("pose_head",),
    "means_head": ("dpt_self", "dpt_cross", "final_transform"),
    "encoder": ("patch_embed", "enc_blocks", "enc_norm"),
}


@dataclass(frozen=True)
class Stage:
    """One curriculum stage."""

    name: str
    steps: int
    lr: float
    min_frames: int
    max_frames: int
    trainable: tuple[str, ...]  # group names of PARAMETER_GROUPS, or ("all",)
    tbptt_chunk: int = 4
    render_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.steps < 0 or self.lr <= 0 or not 1 <= self.min_frames <= self.max_frames:
            raise ValueError(f"invalid stage {self.name}: steps={self.steps} lr={self.lr} "
                             f"frames={self.min_frames}..{self.max_frames}")
        if self.tbptt_chunk < 1:
            raise ValueError(f"invalid stage {self.name}: tbptt_chunk must be at least 1, got {self.tbptt_chunk}")
        unknown = [g for g in self.trainable if g != "all" and g not in PARAMETER_GROUPS]
        if unknown:
            raise ValueError(f"unknown parameter groups {unknown}; known: {sorted(PARAMETER_GROUPS)} or 'all'")


@dataclass(frozen=True)
class Curriculum:
    """An ordered list of stages."""

    stages: tuple[Stage, ...] = field(default_factory=tuple)

    @classmethod
    def paper(cls) -> Curriculum:
        """Appendix D.3 as published (for a model initialised from CUT3R)."""
        return cls((
            Stage("gs_warmup", 5000, 2e-4, 1, 4, ("gs_head",)),
            Stage("adapt", 5000, 1e-5, 4, 4, ("gs_head", "decoder", "pose_head", "means_head")),
            Stage("long", 5000, 5e-6, 4, 32, ("gs_head", "decoder", "pose_head", "means_head")),
        ))

    @classmethod
    def from_scratch(cls, steps: int = 3000, lr: float = 1e-3, max_frames: int = 8,
                     fractions: tuple[float, float, float] = (0.5, 0.2, 0.2)) -> Curriculum:
        """For small models without CUT3R weights: a full-model stage 0, then D.3's stages with rates scaled up.

        `fractions` are the shares of `steps` of stage 0, the head warm-up and the 4-frame stage; the long-clip
        stage gets the rest.
        """
        if len(fractions) != 3 or min(fractions) < 0 or sum(fractions) > 1:
            raise ValueError(f"fractions must be 3 non-negative shares summing to at most 1, got {fractions}")
        n0, n1, n2 = (int(steps * f) for f in fractions)
        return cls((
            Stage("backbone", n0, lr, 2, 4, ("all",), render_weight=0.1),
            Stage("gs_warmup", n1, lr, 1, 4, ("gs_head",)),
            Stage("adapt", n2, lr * 0.2, 4, 4, ("gs_head", "decoder", "pose_head", "means_head")),
            Stage("long", steps - n0 - n1 - n2, lr * 0.1, 4, max_frames,
                  ("gs_head", "decoder", "pose_head", "means_head")),
        ))

    @classmethod
    def continued(cls, steps: int = 2000, lr: float = 3e-4, max_frames: int = 8,
                  clip_fraction: float = 0.6) -> Curriculum:
        """To continue a model trained from scratch: every parameter on 4-frame clips with the full rendering
        weight (the first `clip_fraction` of `steps`), then clips of 4 to `max_frames` frames with truncated
        backpropagation at half the rate. Unlike D.3's stages the encoder stays trainable: without CUT3R weights
        it is as undertrained as the rest."""
        if not 0 <= clip_fraction <= 1:
            raise ValueError(f"clip_fraction must be in [0, 1], got {clip_fraction}")
        n = int(steps * clip_fraction)
        return cls((
            Stage("clips4", n, lr, 4, 4, ("all",)),
            Stage("long", steps - n, lr * 0.5, 4, max(4, max_frames), ("all",)),
        ))

    def scaled(self, step_factor: float) -> Curriculum:
        """The same curriculum with every stage's step count multiplied by `step_factor`."""
        return Curriculum(tuple(replace(s, steps=max(1, round(s.steps * step_factor))) for s in self.stages))

    def with_long_chunk(self, tbptt_chunk: int) -> Curriculum:
        """The same curriculum with the last stage's truncated-backpropagation chunk set to `tbptt_chunk` frames."""
        *head, last = self.stages
        return Curriculum((*head, replace(last, tbptt_chunk=tbptt_chunk)))

    @property
    def total_steps(self) -> int:
        return sum(s.steps for s in self.stages)

    def stage_at(self, step: int) -> tuple[int, Stage]:
        """(index, stage) for a global step (the last stage for steps past the end)."""
        start = 0
        for i, stage in enumerate(self.stages):
            if step < start + stage.steps:
                return i, stage
            start += stage.steps
        return len(self.stages) - 1, self.stages[-1]


def parameter_group(name: str) -> str | None:
    """The group a parameter name belongs to (None when no group claims it)."""
    for group, fragments in PARAMETER_GROUPS.items():
        if any(f in name for f in fragments):
            return group
    return None


def set_trainable(model: torch.nn.Module, stage: Stage) -> list[torch.nn.Parameter]:
    """Freeze every parameter outside the stage's groups; return the trainable ones."""
    trainable = []
    for name, p in model.named_parameters():
        on = "all" in stage.trainable or parameter_group(name) in stage.trainable
        p.requires_grad_(on)
        if on:
            trainable.append(p)
    if not trainable:
        raise ValueError(f"stage {stage.name} selects no parameters of this model")
    return trainable
