"""Assemble a Trainer from names and paths (used by `flashmono train` and the default-model recipe)."""

from __future__ import annotations

import logging
from pathlib import Path

from .clips import SequenceBank
from .curriculum import Curriculum
from .trainer import TrainConfig, Trainer

log = logging.getLogger(__name__)

# Synthetic seeds below this bound are for training; held-out evaluation uses seeds >= HELD_OUT_SEED_START.
HELD_OUT_SEED_START = 10_000


def training_sources(data: list[str], synthetic_sequences: int, frames: int, width: int, height: int) -> list[str]:
    """The given sources, or synthetic training scenes when none are given."""
    if data:
        return list(data)
    return [f"synthetic://seed={seed}?frames={frames}&width={width}&height={height}"
            for seed in range(synthetic_sequences)]


def build_trainer(model_name: str, data: list[str], out_dir: Path, init: Path | None, curriculum: str,
                  steps: int, lr: float, width: int, height: int, synthetic_sequences: int, frames: int,
                  checkpoint_every: int) -> Trainer:
    """Model, data and curriculum ready to train."""
    from safetensors.torch import load_file

    from worker.data import open_source
    from worker.frontend import build_model

    if width % 16 or height % 16:
        raise ValueError(f"--width and --height must be multiples of 16, got {width}x{height}")
    model = build_model(model_name)
    if init is not None:
        missing, unexpected = model.load_state_dict(load_file(str(init)), strict=False)
        log.info("initialised from %s (%d missing, %d unexpected keys)", init, len(missing), len(unexpected))
    bank = SequenceBank(width, height)
    for source in training_sources(data, synthetic_sequences, frames, width, height):
        bank.add(open_source(source, use_gt_depth=True))
        log.info("loaded %s", source)
    plan = Curriculum.paper().scaled(steps / Curriculum.paper().total_steps) if curriculum == "paper" \
        else Curriculum.from_scratch(steps=steps, lr=lr)
    return Trainer(model, bank, plan, out_dir, TrainConfig(checkpoint_every=checkpoint_every))
