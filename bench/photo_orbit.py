"""Photo orbits: every photo of a capture around an object registered by the session's photo registration
(worker.tracking.photos, the pose source RGB-only sessions get for photos), against COLMAP on the same photos.

    python -m bench photo_orbit [--source DIR ...] [--size WxH] [--no-peer]
    python -m bench photo_orbit --from-middlebury templeRing/ --source /data/temple   # convert, then measure

A source is a photo capture with its poses (`transforms.json`, instant-ngp / nerfstudio layout). Per photo, the
error is its camera centre's distance from the truth after one Sim(3) alignment of all photos, as a share of the
camera's distance to the object (the point nearest every optical axis). Recorded per source: photos registered, the
ATE, the worst photo's share, how many are within 5 %, the wall time of the registration (features included, photo
after photo as a session gets them, and the final bundle adjustment the session's finish runs) and the load; the
peer (pycolmap, a bench extra: SIFT, sequential matching, incremental mapping, the camera held) the same. Records go to
bench/results/photo_orbit/ (scoreboard area `photo_orbit`).

`--from-middlebury` converts Middlebury's templeRing or dinoRing (Seitz et al., CVPR 2006: 47-48 photos on a ring
with calibrated cameras, `*_par.txt`) into that layout: photos in ring order, the upside-down half (positive
latitudes, taken with the gantry the other way round) turned upright, one pinhole camera.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.record import Recorder, loadavg

TARGET_SHARE = 0.05  # issue 43 point 5: every photo within 5 % of the camera-object distance


def orbit_centre(poses: np.ndarray) -> np.ndarray:
    """The point nearest every camera's optical axis (least squares), poses [N, 4, 4] camera-to-world."""
    centres, axes = poses[:, :3, 3], poses[:, :3, 2]
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    return np.linalg.solve(projectors.sum(0), (projectors @ centres[:, :, None]).sum(0)[:, 0])


def score(estimated: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> dict[str, Any]:
    """Registered photos, ATE (Sim(3)) and each photo's error as a share of its distance to the object."""
    from worker.eval import absolute_trajectory_error

    every = np.stack([truth[i] for i in sorted(truth)])
    distance = dict(zip(sorted(truth), np.linalg.norm(every[:, :3, 3] - orbit_centre(every), axis=1)))
    posed = sorted(i for i in estimated if i in truth)
    out: dict[str, Any] = {"photos": len(truth), "registered": len(posed),
                           "registered_share": round(len(posed) / len(truth), 4),
                           "median_distance": round(float(np.median(list(distance.values()))), 4)}
    if len(posed) < 3:
        return out | {"ate_units": None, "worst_share": None, "within_5_percent": 0}
    result = absolute_trajectory_error(np.stack([estimated[i] for i in posed]), np.stack([truth[i] for i in posed]),
                                       "sim3")
    share = result.errors / np.array([distance[i] for i in posed])
    return out | {"ate_units": round(result.rmse, 5), "ate_share": round(result.rmse / out["median_distance"], 5),
                  "worst_share": round(float(share.max()), 4), "worst_photo": int(posed[int(share.argmax())]),
                  "within_5_percent": int((share <= TARGET_SHARE).sum())}


def run_registration(source: Path, size: tuple[int, int] | None) -> dict[str, Any]:
    """The photos through `PhotoRegistration` one after another, then its final adjustment, timed."""
    from worker.data import open_source
    from worker.tracking.photos import PhotoRegistration

    frames = list(open_source(str(source), resize=size, use_gt_depth=False, use_gt_poses=False))
    registration = PhotoRegistration()
    start = time.perf_counter()
    poses, lost = {}, 0
    for frame in frames:
        result = registration.track(frame, frame.intrinsics)
        lost += not result.tracked
    poses = registration.refined_poses()
    wall = time.perf_counter() - start
    values = score(poses, {f.index: f.gt_pose for f in frames})
    return values | {"reported_lost": lost, "wall_s": round(wall, 1), "s_per_photo": round(wall / len(frames), 3),
                     "size": f"{frames[0].width}x{frames[0].height}"}


def run_peer(source: Path, size: tuple[int, int] | None) -> dict[str, Any]:
    """COLMAP on the same photos (bench.colmap_peer, every photo); its ATE as a share of the median distance too."""
    from bench.colmap_peer import run_colmap
    from worker.data import open_source

    frames = list(open_source(str(source), resize=size, use_gt_depth=False))
    truth = np.stack([f.gt_pose for f in frames])
    distance = float(np.median(np.linalg.norm(truth[:, :3, 3] - orbit_centre(truth), axis=1)))
    with tempfile.TemporaryDirectory(prefix="bench-orbit-colmap-") as tmp:
        values = run_colmap(source, (frames[0].width, frames[0].height), 1, Path(tmp))
    ate = values.pop("ate_m", None)  # in the capture's units
    return values | {"ate_units": ate, "ate_share": None if ate is None else round(ate / distance, 5)}


def middlebury_ring_to_transforms(src: Path, dst: Path) -> int:
    """Middlebury's ring (`*_par.txt`, `*_ang.txt`, PNGs) as a `transforms.json` capture in ring order, upright;
    returns the number of photos."""
    par = next(src.glob("*_par.txt"))
    angles = {}
    for line in next(src.glob("*_ang.txt")).read_text().splitlines():
        if line.strip():
            lat, lon, name = line.split()
            angles[name] = (float(lat), float(lon))
    photos = []
    for line in par.read_text().splitlines()[1:]:
        if not line.strip():
            continue
        name, *numbers = line.split()
        values = np.array(numbers, np.float64)
        K, R, t = values[:9].reshape(3, 3), values[9:18].reshape(3, 3), values[18:21]
        lat, lon = angles[name]
        upside_down = lat > 0  # (lat, lon) is the view (-lat, lon + 180) turned half round
        photos.append(((lon + 180.0 if upside_down else lon) % 360.0, name, K, R, t, upside_down))
    photos.sort(key=lambda p: p[0])
    K = photos[0][2]
    (dst / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for n, (_, name, _, R, t, upside_down) in enumerate(photos):
        image = cv2.imread(str(src / name))
        height, width = image.shape[:2]
        if upside_down:  # turned upright about the principal point, which stays where the camera says it is
            image = cv2.rotate(image, cv2.ROTATE_180)
            shift = np.float32([[1, 0, 2 * K[0, 2] - (width - 1)], [0, 1, 2 * K[1, 2] - (height - 1)]])
            image = cv2.warpAffine(image, shift, (width, height), flags=cv2.INTER_LINEAR)
            half_turn = np.diag([-1.0, -1.0, 1.0])
            R, t = half_turn @ R, half_turn @ t
        path = f"images/{n:03d}.png"
        cv2.imwrite(str(dst / path), image)
        camera_to_world = np.eye(4)
        camera_to_world[:3, :3], camera_to_world[:3, 3] = R.T, -R.T @ t
        frames.append({"file_path": path, "source": name,
                       "transform_matrix": (camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])).tolist()})
    (dst / "transforms.json").write_text(json.dumps(
        {"w": width, "h": height, "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "frames": frames},
        indent=1))
    return len(frames)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench photo_orbit", description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, action="append", help="a photo capture folder (repeatable)")
    parser.add_argument("--size", default=None, help="resize photos to WxH (default: as they are)")
    parser.add_argument("--no-peer", action="store_true", help="skip COLMAP")
    parser.add_argument("--from-middlebury", type=Path, help="convert this Middlebury ring into the (first) --source")
    args = parser.parse_args(argv)
    if not args.source:
        print("photo_orbit: no --source given (photo captures are not bundled); skipped")
        return 0
    if args.from_middlebury:
        print(f"{args.source[0]}: {middlebury_ring_to_transforms(args.from_middlebury, args.source[0])} photos")
    size = tuple(int(v) for v in args.size.split("x")) if args.size else None
    recorder = Recorder("photo_orbit", argv)
    for source in args.source:
        runs = [("photo-registration", run_registration)] + ([] if args.no_peer else [("pycolmap", run_peer)])
        for variant, run in runs:
            load_start = loadavg()
            try:
                values = run(source, size)
            except ImportError as error:
                values = {"error": f"not installed ({error})"}
            print(f"{source.name} {variant}: {values}", flush=True)
            case = {"area": "photo_orbit", "sequence": source.name, "mode": "rgb", "size": args.size or "native",
                    "variant": variant}
            recorder.write(case, values, load_at_case_start=load_start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
