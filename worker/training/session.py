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
                  checkpoint_every: int, cache: list[Path] | None = None, max_frames: int = 8,
                  fractions: tuple[float, float, float] = (0.5, 0.2, 0.2), config: TrainConfig | None = None,
                  tbptt_chunk: int = 4) -> Trainer:
    """Model, data and curriculum ready to train.

    `cache`: pre-rendered window files (worker.training.cache); when given, they are the training set together
    with any `data` sources (no synthetic scenes are rendered on the fly). `tbptt_chunk`: frames per truncated-
    backpropagation chunk of the long-clip stage.
    """
    from dataclasses import replace

    from safetensors.torch import load_file

    from worker.data import open_source
    from worker.frontend import build_model

    from .cache import load_windows

    if width % 16 or height % 16:
        raise ValueError(f"--width and --height must be multiples of 16, got {width}x{height}")
    model = build_model(model_name)
    if init is not None:
        missing, unexpected = model.load_state_dict(load_file(str(init)), strict=False)
        log.info("initialised from %s (%d missing, %d unexpected keys)", init, len(missing), len(unexpected))
    bank = SequenceBank(width, height)
    if cache:
        missing_files = [str(p) for p in cache if not Path(p).exists()]
        if missing_files:
            raise FileNotFoundError(f"cache files not found: {', '.join(missing_files)}")
        log.info("loaded %d pre-rendered windows from %d files", load_windows(list(cache), bank), len(cache))
    sources = list(data) if cache else training_sources(data, synthetic_sequences, frames, width, height)
    for source in sources:
        bank.add(open_source(source, use_gt_depth=True))
        log.info("loaded %s", source)
    if curriculum == "paper":
        plan = Curriculum.paper().scaled(steps / Curriculum.paper().total_steps)
    elif curriculum == "continue":
        plan = Curriculum.continued(steps=steps, lr=lr, max_frames=max_frames, clip_fraction=fractions[0])
    elif curriculum == "scratch":
        plan = Curriculum.from_scratch(steps=steps, lr=lr, max_frames=max_frames, fractions=fractions)
    else:
        raise ValueError(f"unknown curriculum {curriculum!r}; known: scratch, paper, continue")
    plan = plan.with_long_chunk(tbptt_chunk)
    log.info("perceptual term: LPIPS backbone weights are not available here, 1 - SSIM substitutes for it")
    config = replace(config or TrainConfig(), checkpoint_every=checkpoint_every)
    return Trainer(model, bank, plan, out_dir, config)
