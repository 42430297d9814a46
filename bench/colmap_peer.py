"""The RGB-only peer: COLMAP's incremental structure from motion (pycolmap, a bench extra: `pip install pycolmap`) on
every Nth frame of a sequence, with the sequence's pinhole camera held, SIFT on the CPU, sequential matching.

    python -m bench colmap_peer [--source DIR ...] [--size 320x240] [--stride 10]

Per sequence it records the share of images registered, the ATE of the registered frames (Sim(3)-aligned, against
the sequence's ground truth), the wall time and the machine's load, to bench/results/colmap_peer/ (scoreboard area
`rgb`, variant `pycolmap-every-Nth`). All of TUM fr1/xyz's 788 frames do not finish in 10 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.covisible_edges import DEFAULT_SOURCES
from bench.record import Recorder, loadavg


def run_colmap(source: Path, size: tuple[int, int], stride: int, work: Path) -> dict[str, Any]:
    """Write every `stride`-th frame, run pycolmap's extraction, sequential matching and incremental mapping, and
    score the largest model's registered frames."""
    import pycolmap

    from worker.data import open_source
    from worker.eval import absolute_trajectory_error

    src = open_source(str(source), resize=size, use_gt_depth=False, use_gt_poses=False)
    frames = [f for k, f in enumerate(src) if k % stride == 0]
    images = work / "images"
    images.mkdir()
    truth = {}
    for f in frames:
        name = f"{f.index:06d}.png"
        cv2.imwrite(str(images / name), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
        truth[name] = f.gt_pose
    K = src.intrinsics
    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{K.fx},{K.fy},{K.cx},{K.cy}"
    database = work / "database.db"
    pycolmap.extract_features(database, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              device=pycolmap.Device.cpu)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 10
    pycolmap.match_sequential(database, pairing_options=pairing, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = options.ba_refine_principal_point = options.ba_refine_extra_params = False
    models = pycolmap.incremental_mapping(database, images, work / "sparse", options=options)
    wall = time.perf_counter() - start
    if not models:
        return {"registered_share": 0.0, "images": len(frames), "wall_s": round(wall, 1), "ate_m": None}
    best = max(models.values(), key=lambda m: m.num_reg_images())
    estimated, reference = [], []
    for image in best.images.values():
        if image.has_pose and truth.get(image.name) is not None:
            estimated.append(np.vstack([image.cam_from_world().inverse().matrix(), [0, 0, 0, 1]]))
            reference.append(truth[image.name])
    ate = (absolute_trajectory_error(np.stack(estimated), np.stack(reference), "sim3").rmse
           if len(estimated) >= 3 else None)
    return {"ate_m": ate, "registered_share": best.num_reg_images() / len(frames), "images": len(frames),
            "models": len(models), "wall_s": round(wall, 1)}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench colmap_peer", description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, action="append", help="a sequence folder (repeatable)")
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--stride", type=int, default=10, help="every Nth frame")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    recorder = Recorder("colmap_peer", argv)
    for source in args.source or [s for s in DEFAULT_SOURCES if s.is_dir()]:
        load_start = loadavg()
        try:
            with tempfile.TemporaryDirectory(prefix="bench-colmap-") as tmp:
                values = run_colmap(source, size, args.stride, Path(tmp))
        except ImportError as error:
            values = {"error": f"not installed ({error})"}
        print(f"{source.name} pycolmap every {args.stride}th frame: {values}", flush=True)
        recorder.write({"area": "rgb", "sequence": source.name, "mode": "rgb", "size": args.size,
                        "variant": f"pycolmap-every-{args.stride}th"}, values, load_at_case_start=load_start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
