"""Pre-rendered training sets: synthetic windows rendered once at the model resolution and stored as safetensors.

Rendering a synthetic frame costs far more than the data loading of a training step, so the default-model recipe
renders its training windows once (`render_synthetic_windows`), writes them with `save_windows`, and trains from
`load_windows` into a SequenceBank.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from worker.data.synthetic import SyntheticScene, default_intrinsics, is_held_out_seed

from .clips import SequenceBank


def render_synthetic_windows(seeds: list[int], window: int, width: int, height: int,
                             path_frames: tuple[int, int] = (40, 90), rng_seed: int = 0
                             ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """For each training seed, `window` consecutive frames of its camera path at width x height.

    The path is sampled with a random number of frames per loop in `path_frames` (so the motion per frame varies)
    and the window starts at a random frame. Returns (images uint8 [L,H,W,3], depths float32 [L,H,W],
    c2w float64 [L,4,4]) per seed. Held-out seeds are refused.
    """
    held_out = [s for s in seeds if is_held_out_seed(s)]
    if held_out:
        raise ValueError(f"seeds {held_out[:5]} are held out for evaluation and must not be used for training")
    rng = np.random.default_rng(rng_seed)
    windows = []
    for seed in seeds:
        n = int(rng.integers(path_frames[0], path_frames[1] + 1))
        windows.append(render_window(seed, n, int(rng.integers(0, n - window + 1)), window, width, height))
    return windows


def render_window(seed: int, path_frames: int, start: int, window: int, width: int, height: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames start..start+window-1 of scene `seed`'s camera path sampled at `path_frames` frames per loop:
    (images uint8 [L,H,W,3], depths float32 [L,H,W], c2w float64 [L,4,4])."""
    if not 0 <= start <= path_frames - window:
        raise ValueError(f"window {start}..{start + window} does not fit a {path_frames}-frame path")
    scene = SyntheticScene(seed)
    intrinsics = default_intrinsics(width, height)
    poses = scene.camera_path(path_frames)
    rendered = [scene.render(poses[i], intrinsics) for i in range(start, start + window)]
    return (np.stack([r[0] for r in rendered]), np.stack([r[1] for r in rendered]),
            poses[start:start + window].copy())


def save_windows(windows: list[tuple[np.ndarray, np.ndarray, np.ndarray]], width: int, height: int,
                 path: Path) -> None:
    """Write rendered windows (and the synthetic intrinsics of width x height) to one safetensors file."""
    tensors = {}
    for i, (images, depths, c2w) in enumerate(windows):
        tensors[f"{i}.images"] = torch.from_numpy(np.ascontiguousarray(images))
        tensors[f"{i}.depths"] = torch.from_numpy(np.ascontiguousarray(depths)).half()
        tensors[f"{i}.c2w"] = torch.from_numpy(np.ascontiguousarray(c2w))
    meta = {"count": str(len(windows)), "width": str(width), "height": str(height),
            "intrinsics": json.dumps(default_intrinsics(width, height).matrix().tolist())}
    save_file(tensors, str(path), metadata=meta)


def load_windows(paths: list[Path], bank: SequenceBank) -> int:
    """Add every window stored in `paths` to `bank` (which must have the same resolution); returns the count."""
    added = 0
    for path in paths:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata()
            if (int(meta["width"]), int(meta["height"])) != (bank.width, bank.height):
                raise ValueError(f"{path} holds {meta['width']}x{meta['height']} windows, the bank is "
                                 f"{bank.width}x{bank.height}")
            K = torch.tensor(json.loads(meta["intrinsics"]), dtype=torch.float32)
            for i in range(int(meta["count"])):
                bank.add_tensors(f.get_tensor(f"{i}.images"), f.get_tensor(f"{i}.depths").float(),
                                 f.get_tensor(f"{i}.c2w"), K)
                added += 1
    return added


def main(argv: list[str] | None = None) -> int:
    """`python -m worker.training.cache OUT.safetensors --seeds A B --window 16`: render one shard."""
    import argparse

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("out", type=Path)
    p.add_argument("--seeds", type=int, nargs=2, required=True, metavar=("FIRST", "END"))
    p.add_argument("--window", type=int, default=16)
    p.add_argument("--width", type=int, default=224)
    p.add_argument("--height", type=int, default=160)
    args = p.parse_args(argv)
    windows = render_synthetic_windows(list(range(*args.seeds)), args.window, args.width, args.height,
                                       rng_seed=args.seeds[0])
    save_windows(windows, args.width, args.height, args.out)
    print(f"{len(windows)} windows -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
