"""Weight surgery: switch a trained model to the colour skip (FrontendConfig.color_skip) without losing its training.

With the skip, a surfel's colour is sigmoid(logit(pixel colour) + raw colour). Zeroing the Gaussian DPT's final
colour rows makes the raw residual 0, so every per-pixel surfel starts exactly at its own pixel's colour; everything
else (geometry, opacity, rotation, scale, pose) is unchanged.

`python -m worker.training.color_skip IN.safetensors OUT.safetensors`
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import torch

from worker.frontend.model import FeedForwardModel

COLOR_CHANNELS = slice(0, 3)  # the first three output channels of dpt_gs are the colour (configs.GAUSSIAN_CHANNELS)


def with_color_skip(model: FeedForwardModel) -> FeedForwardModel:
    """A copy of `model` with color_skip on and the Gaussian DPT's colour output rows zeroed (residual 0)."""
    config = replace(model.config, color_skip=True)
    skip = FeedForwardModel(config)
    skip.load_state_dict(model.state_dict())
    final = skip.downstream_head.dpt_gs.head[-1]
    with torch.no_grad():
        final.weight[COLOR_CHANNELS].zero_()
        final.bias[COLOR_CHANNELS].zero_()
    skip.precision = model.precision
    return skip.train(model.training)


def main(argv: list[str] | None = None) -> int:
    from worker.frontend.checkpoint import load_checkpoint, save_checkpoint

    p = argparse.ArgumentParser(prog="python -m worker.training.color_skip", description=__doc__.split("\n\n")[0])
    p.add_argument("source", type=Path, help="checkpoint to convert (.safetensors)")
    p.add_argument("target", type=Path, help="where to write the converted checkpoint")
    args = p.parse_args(argv)
    model = load_checkpoint(args.source)
    metadata = dict(getattr(model, "checkpoint_metadata", {}) or {})
    metadata["color_skip_surgery"] = f"from {args.source.name}: colour rows of dpt_gs zeroed"
    save_checkpoint(with_color_skip(model), args.target, metadata)
    print(f"wrote {args.target}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
