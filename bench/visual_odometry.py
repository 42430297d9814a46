"""Monocular visual odometry (worker.tracking.visual_odometry) on ICL living room 1 (211 frames at 320x240), the
bundled every-third-frame ICL subset, a synthetic forward drive (street) and a synthetic room.

Measures ATE RMSE after Sim(3) alignment (also as a share of the path length), how many frames were tracked, the loss
/ relocalisation events, and the time per frame (single process; this machine's other load is printed with the
figures). The peer in the same run is COLMAP's incremental mapping (pycolmap, bench extra: SIFT, sequential matching,
fixed intrinsics) of the ICL frames: its ATE over the frames it registered and its time per frame. Targets: ICL ATE
<= 3 cm, street ATE <= 2 % of the path, every frame tracked or relocalised and reported, >= 8 frames/s on 2 cores.

    python -m bench visual_odometry [--data PATH] [--frames N] [--cases icl,icl_mini,street,room] [--no-colmap]
                                    [--uncalibrated]

More cases: room10004, room10005 (fast turns), icl_gaps6 / icl_gaps16 (icl_mini's first 20 frames, then every 6th
or 16th: gaps the optical flow cannot bridge), room_gap (room 10003 without frames 30-33: the map restarts at a wrong
scale and is joined to the old one when the camera comes back to its start; `maps_merged` corrections are applied to
the restarted map's frames as the engine's pose graph does), icl_jump (icl_mini's first 40 frames, then a jump back
to frames 5-7, no restart from the last tracked frame: relocalised by XFeat against an older keyframe),
icl_jump_join (the same with a jump to frames 2-4 and ORB descriptor matching off: the map restarted at the jump is
joined to the old one by XFeat). Each run also prints what XFeat cost (network passes, ms per pass): it runs only
while lost or while a restarted map is not joined yet.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from worker.data import open_source
from worker.data.frame import Frame
from worker.eval import absolute_trajectory_error
from worker.events import Initialized, MapsMerged
from worker.tracking.map_join import moved_pose
from worker.tracking.visual_odometry import VisualOdometry
from worker.tracking.vo_config import VisualOdometryConfig

DEFAULT_DATA = Path("/work/shared/data/icl_livingroom1_micro")
MINI_DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "icl_mini"
SYNTHETIC = {"street": "synthetic://seed=1?frames=120&scene=street&fps=10", "room": "synthetic://seed=10003?frames=90",
             # fast turns (up to 7-10 degrees per frame) through low-texture rooms (issue 20)
             "room10004": "synthetic://seed=10004?frames=90", "room10005": "synthetic://seed=10005?frames=90"}


def _load(path: Path, frames: int) -> list:
    source = open_source(path, resize=(320, 240), use_gt_depth=False, use_gt_poses=False, max_frames=frames)
    return list(source)


def _cases(names: list[str], data: Path, frames: int) -> list[tuple[str, list, str]]:
    """(label, frames, case name) of each named case whose data is at hand."""
    out: list = []
    for name in names:
        before = len(out)
        if name == "icl" and data.exists():
            out.append((f"{data.name} ({frames} frames)", _load(data, frames)))
        elif name == "icl_mini":
            out.append(("tests/data/icl_mini", list(open_source(MINI_DATA, use_gt_depth=False, use_gt_poses=False))))
        elif name.startswith("icl_gaps"):
            step = int(name.removeprefix("icl_gaps"))
            mini = list(open_source(MINI_DATA, use_gt_depth=False, use_gt_poses=False))
            picked = mini[:20] + mini[20::step]
            out.append((f"tests/data/icl_mini, 20 frames then every {step}th",
                        [Frame(n, n / 10.0, f.image, f.intrinsics, gt_pose=f.gt_pose) for n, f in enumerate(picked)]))
        elif name.startswith("icl_jump"):
            mini = list(open_source(MINI_DATA, use_gt_depth=False, use_gt_poses=False))
            back = 2 if name == "icl_jump_join" else 5
            picked = mini[:40] + mini[back:back + 3]
            out.append((f"tests/data/icl_mini, 40 frames then frames {back}-{back + 2} again",
                        [Frame(n, n / 10.0, f.image, f.intrinsics, gt_pose=f.gt_pose) for n, f in enumerate(picked)]))
        elif name == "room_gap":
            room = list(open_source(SYNTHETIC["room"], use_gt_depth=False))
            picked = room[:30] + room[34:]
            out.append((f"{SYNTHETIC['room']} without frames 30-33",
                        [Frame(n, n / 30.0, f.image, f.intrinsics, gt_pose=f.gt_pose) for n, f in enumerate(picked)]))
        elif name in SYNTHETIC:
            out.append((SYNTHETIC[name], list(open_source(SYNTHETIC[name], use_gt_depth=False))))
        elif name == "icl":
            print(f"no data at {data}: ICL skipped")
        else:
            raise SystemExit(f"unknown case {name!r}")
        if len(out) > before:
            out[-1] = (*out[-1], name)
    return out


def path_length(frames: list) -> float:
    """Length of the ground-truth camera path, metres."""
    return float(np.linalg.norm(np.diff(np.stack([f.gt_pose[:3, 3] for f in frames]), axis=0), axis=1).sum())


# icl_jump: no restart from the last tracked frame (only a remembered keyframe can place the jump); icl_jump_join:
# ORB descriptor matching off (only XFeat can join the maps)
CASE_CONFIG = {"icl_jump": {"reinit_after_loss": False}, "icl_jump_join": {"max_hamming": 1}}


def run_vo(frames: list, calibrated: bool = True, config: dict | None = None) -> dict:
    """VO over the frames: trajectory (rewritten by the initialisation event), ATE, events and timing."""
    vo = VisualOdometry(VisualOdometryConfig(**(config or {})))
    poses, seconds, tracked, events, flags = [], [], 0, [], []
    joins: list[tuple[int, np.ndarray]] = []  # (first frame of a restarted map, its correction), newest first
    for frame in frames:
        start = time.perf_counter()
        result = vo.track(frame, frame.intrinsics if calibrated else None)
        seconds.append(time.perf_counter() - start)
        poses.append(result.pose)
        tracked += bool(result.tracked)
        flags.append(bool(result.tracked))
        for event in result.events:
            if isinstance(event, Initialized):
                for index, pose in event.frames or []:
                    poses[index] = np.asarray(pose)
            if isinstance(event, MapsMerged):
                joins.insert(0, (int(event.since), np.asarray(event.correction)))
            method = getattr(event, "method", None)
            events.append((frame.index, event.TYPE if method is None else f"{event.TYPE} ({method})"))
    for since, correction in joins:
        poses[since:] = [moved_pose(correction, pose) for pose in poses[since:]]
    gt = np.stack([f.gt_pose for f in frames])
    ate = absolute_trajectory_error(np.stack(poses), gt, "sim3")
    on = [n for n, ok in enumerate(flags) if ok]
    ate_tracked = absolute_trajectory_error(np.stack(poses)[on], gt[on], "sim3").rmse if len(on) >= 3 else float("nan")
    return {"ate_m": ate.rmse, "ate_max_m": ate.max, "ate_tracked_m": ate_tracked, "tracked": tracked,
            "frames": len(frames), "events": events,
            "ms_per_frame": 1e3 * float(np.mean(seconds)), "ms_p95": 1e3 * float(np.percentile(seconds, 95)),
            "ms_median": 1e3 * float(np.median(seconds)), "ms_max": 1e3 * float(np.max(seconds)),
            "fps": 1.0 / float(np.mean(seconds)), "intrinsics": vo.estimated_intrinsics,
            "xfeat_passes": vo.learned.passes, "xfeat_ms": 1e3 * vo.learned.seconds / max(vo.learned.passes, 1),
            "glue_pairs": vo.learned.glue_pairs,
            "glue_ms": 1e3 * vo.learned.glue_seconds / max(vo.learned.glue_pairs, 1)}


def run_colmap(frames: list) -> dict | str:
    """pycolmap incremental mapping of the same frames (fixed pinhole intrinsics), or why it did not run."""
    try:
        import pycolmap
    except ImportError:
        return "pycolmap is not installed (pip install '.[bench]'): COLMAP peer skipped"
    k = frames[0].intrinsics
    with tempfile.TemporaryDirectory() as tmp:
        images, database, out = Path(tmp) / "images", Path(tmp) / "db.db", Path(tmp) / "sparse"
        images.mkdir()
        out.mkdir()
        for f in frames:
            cv2.imwrite(str(images / f"{f.index:05d}.png"), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
        start = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        # COLMAP puts pixel centres at +0.5 like this project, so the principal point carries over unchanged.
        reader.camera_params = f"{k.fx},{k.fy},{k.cx},{k.cy}"
        pycolmap.extract_features(database, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  device=pycolmap.Device.cpu)
        pycolmap.match_sequential(database, device=pycolmap.Device.cpu)
        options = pycolmap.IncrementalPipelineOptions()
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        maps = pycolmap.incremental_mapping(database, images, out, options)
        seconds = time.perf_counter() - start
    if not maps:
        return f"COLMAP registered no model ({seconds:.1f} s)"
    model = max(maps.values(), key=lambda r: r.num_reg_images())
    est, gt = [], []
    for image in model.images.values():
        if not image.has_pose:
            continue
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        est.append(np.linalg.inv(w2c))
        gt.append(frames[int(Path(image.name).stem)].gt_pose)
    ate = absolute_trajectory_error(np.stack(est), np.stack(gt), "sim3")
    return {"ate_m": ate.rmse, "registered": len(est), "frames": len(frames), "models": len(maps),
            "ms_per_frame": 1e3 * seconds / len(frames)}


def _report(name: str, r: dict, path_m: float) -> None:
    lost = [i for i, kind in r["events"] if kind == "tracking_lost"]
    back = [(i, kind.removeprefix("relocalized").strip(" ()") or "tracks") for i, kind in r["events"]
            if kind.startswith("relocalized")]
    back += [(i, kind.replace("_", " ")) for i, kind in r["events"] if kind.startswith("maps_merged")]
    print(f"  {name}: ATE {100 * r['ate_m']:.2f} cm = {100 * r['ate_m'] / path_m:.2f} % of the path "
          f"(max {100 * r['ate_max_m']:.2f} cm; tracked frames only {100 * r['ate_tracked_m']:.2f} cm), "
          f"tracked {r['tracked']}/{r['frames']}, lost at {lost}, relocalised at "
          f"{back}, {r['ms_per_frame']:.1f} ms/frame (median {r['ms_median']:.1f}, p95 {r['ms_p95']:.1f}, max "
          f"{r['ms_max']:.1f}: a keyframe) = {r['fps']:.1f} frames/s"
          + (f", intrinsics {r['intrinsics']}" if r["intrinsics"] is not None else "")
          + (f"; XFeat {r['xfeat_passes']} passes, {r['xfeat_ms']:.0f} ms each" if r["xfeat_passes"] else
             "; XFeat not run")
          + (f"; LighterGlue {r['glue_pairs']} pairs, {r['glue_ms']:.0f} ms each" if r["glue_pairs"] else ""))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench visual_odometry", description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--frames", type=int, default=211)
    parser.add_argument("--cases", default="icl,icl_mini,street,room")
    parser.add_argument("--no-colmap", action="store_true")
    parser.add_argument("--uncalibrated", action="store_true", help="also run VO without intrinsics")
    args = parser.parse_args(argv)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
          f"load before: {os.getloadavg()}")
    for label, frames, name in _cases(args.cases.split(","), args.data, args.frames):
        path_m = path_length(frames)
        print(f"{label}: {len(frames)} frames at {frames[0].width}x{frames[0].height}, path {path_m:.2f} m")
        _report("VO (given intrinsics)", run_vo(frames, config=CASE_CONFIG.get(name)), path_m)
        if args.uncalibrated:
            _report("VO (no intrinsics)", run_vo(frames, calibrated=False), path_m)
        if not args.no_colmap and label.startswith(args.data.name):
            peer = run_colmap(frames)
            if isinstance(peer, str):
                print(f"  {peer}")
            else:
                print(f"  COLMAP incremental (pycolmap): ATE {100 * peer['ate_m']:.2f} cm over {peer['registered']}/"
                      f"{peer['frames']} registered frames ({peer['models']} models), {peer['ms_per_frame']:.0f} "
                      "ms/frame")
    print(f"load after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
