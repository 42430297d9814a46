"""`flashmono train`: train the frontend on synthetic scenes and/or real RGB-D datasets (paper App. D)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train",
        help="train the frontend model (curriculum of appendix D.3)",
        description=(
            "Train the recurrent frontend on sequences with RGB, depth and poses: synthetic scenes "
            "(synthetic://seed=N?frames=F) and any dataset the frame sources read (ScanNet, Replica, TUM, ICL, "
            "folders with RGB, depth and poses). Writes model.safetensors, optimizer state, trainer.json and "
            "loss_curves.png to --out every --checkpoint-every steps; --resume continues from there."
        ),
    )
    p.add_argument("data", nargs="*", help="sources (default: synthetic training seeds)")
    p.add_argument("--out", type=Path, required=True, help="checkpoint directory")
    p.add_argument("--model", default="tiny", help="model config name (tiny, small, base, paper)")
    p.add_argument("--init", type=Path, help="initial weights (.safetensors, e.g. converted CUT3R)")
    p.add_argument("--curriculum", choices=("scratch", "paper", "continue"), default="scratch",
                   help="'paper': appendix D.3 for CUT3R-initialised models; 'scratch': full-model stage first; "
                        "'continue': every parameter on 4-frame clips, then long clips (for --init from a "
                        "model trained from scratch; the first --stage-fractions share is the 4-frame stage)")
    p.add_argument("--steps", type=int, default=2000, help="total steps of the curriculum")
    p.add_argument("--lr", type=float, default=1e-3, help="base learning rate of the 'scratch' curriculum")
    p.add_argument("--width", type=int, default=224)
    p.add_argument("--height", type=int, default=160)
    p.add_argument("--synthetic-sequences", type=int, default=16, help="synthetic training scenes when no data given")
    p.add_argument("--frames", type=int, default=48, help="frames per synthetic scene")
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--keep-every", type=int, default=0, help="also keep model_step<N>.safetensors every N steps")
    p.add_argument("--cache", type=Path, nargs="+", help="pre-rendered windows (python -m worker.training.cache)")
    p.add_argument("--max-frames", type=int, default=8, help="longest clip of the last ('long') stage")
    p.add_argument("--tbptt-chunk", type=int, default=4,
                   help="frames per truncated-backpropagation chunk in the long-clip stage")
    p.add_argument("--stage-fractions", type=float, nargs=3, default=(0.5, 0.2, 0.2),
                   metavar=("BACKBONE", "WARMUP", "ADAPT"), help="'scratch': shares of the steps (rest: long clips)")
    p.add_argument("--lr-warmup", type=int, default=0, help="linear warm-up steps at the start of each stage")
    p.add_argument("--cosine", action="store_true", help="cosine-decay each stage's rate to 10%%")
    p.add_argument("--render-downscale", type=int, default=2, help="rendering losses at 1/N of the model resolution")
    p.add_argument("--render-stride", type=int, default=2, help="render every N-th pixel's surfel")
    p.add_argument("--max-gap", type=int, default=2,
                   help="clips take every k-th frame, k drawn from 1..N (1: the sequences' own frame rate)")
    p.add_argument("--pose-weight", type=float, default=1.0, help="weight of the pose loss (eq. 8's lambda_pose)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint in --out")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: all cores)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging
    import os

    import torch
    from tqdm import tqdm

    from worker.training.session import build_trainer
    from worker.training.trainer import TrainConfig

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    try:
        trainer = build_trainer(
            model_name=args.model, data=args.data, out_dir=args.out, init=args.init, curriculum=args.curriculum,
            steps=args.steps, lr=args.lr, width=args.width, height=args.height,
            synthetic_sequences=args.synthetic_sequences, frames=args.frames,
            checkpoint_every=args.checkpoint_every, cache=args.cache, max_frames=args.max_frames,
            fractions=tuple(args.stage_fractions), tbptt_chunk=args.tbptt_chunk,
            config=TrainConfig(pose_weight=args.pose_weight, keep_every=args.keep_every, lr_warmup=args.lr_warmup,
                               lr_cosine=args.cosine, max_gap=args.max_gap,
                               render_downscale=args.render_downscale, render_stride=args.render_stride),
        )
    except (ValueError, FileNotFoundError) as err:
        print(f"flashmono train: {err}")
        return 2
    if args.resume and trainer.resume():
        print(f"resumed at step {trainer.step}")
    bar = tqdm(total=trainer.curriculum.total_steps, initial=trainer.step, unit="step")

    def show(record) -> None:
        bar.update(1)
        bar.set_postfix(stage=record.stage, loss=f"{record.total:.3f}")

    trainer.train(progress=show)
    bar.close()
    print(f"weights: {args.out / 'model.safetensors'}  curves: {args.out / 'loss_curves.png'}")
    return 0
