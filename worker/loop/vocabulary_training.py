"""Training the ORB vocabulary (worker.loop.vocabulary) on synthetic rooms:
`python -m worker.loop.vocabulary_training`."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .descriptors import OrbDescriptor
from .vocabulary import DEFAULT_PATH, train_vocabulary


def _synthetic_training_descriptors(scenes: int, frames: int) -> list[np.ndarray]:
    """ORB descriptors of frames along synthetic rooms' paths (seeds 5000+, apart from training and held-out)."""
    import torch

    from worker.data.synthetic import SyntheticScene, default_intrinsics


    orb = OrbDescriptor()
    intrinsics = default_intrinsics(320, 240)
    out = []
    for seed in range(5000, 5000 + scenes):
        scene = SyntheticScene(seed)
        for pose in scene.camera_path(frames):
            rgb, _ = scene.render(pose, intrinsics)
            image = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255.0
            out.append(orb.describe(image).descriptors)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m worker.loop.vocabulary_training",
                                     description="Train the ORB vocabulary on synthetic rooms.")
    parser.add_argument("--out", default=str(DEFAULT_PATH))
    parser.add_argument("--scenes", type=int, default=40)
    parser.add_argument("--frames", type=int, default=10, help="frames per scene")
    parser.add_argument("--branching", type=int, default=10)
    parser.add_argument("--levels", type=int, default=3)
    args = parser.parse_args(argv)
    descriptors = _synthetic_training_descriptors(args.scenes, args.frames)
    vocabulary = train_vocabulary(descriptors, args.branching, args.levels)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    vocabulary.save(args.out)
    print(f"{vocabulary.size} words from {sum(map(len, descriptors))} descriptors of {len(descriptors)} images "
          f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
