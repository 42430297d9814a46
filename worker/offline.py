"""Offline runs for researchers: a sequence through the SlamSystem, then the paper's metrics and files.

`run_sequence` writes into `out_dir`: trajectory_all.tum and trajectory_keyframes.tum (SE(3) part of the poses),
intrinsics.json (given or estimated), map.ply, renders/NNNNN.png (rendered | ground truth side by side, for
evaluated non-keyframes) and metrics.json (ate_rmse, psnr, ssim, lpips or its unavailability, depth_l1, fps,
num_gaussians, ...), and returns the metrics dict.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from worker.config import SlamConfig
from worker.data.frame import Frame
from worker.events import Initialized, Relocalized
from worker.geometry import se3_part
from worker.pipeline.drift import PoseDrift

MAX_SAVED_RENDERS = 12
# Frames whose image and depth are held for the rendering metrics: every k-th, k chosen to hold at most this many
# (a long session's frames would otherwise fill the memory; 211 ICL frames are all held).
MAX_HELD_FRAMES = 400
# Held-out frames scored at most (three renders each): a 1,000-frame run's scores cost seconds, not a minute.
MAX_EVAL_FRAMES = 200
# Keyframes an offline run lets the mapping stage fall behind before the next frame waits (complete pacing): poses
# stream out at tracking's rate while mapping works through its backlog in order, every keyframe fully refined.
OFFLINE_MAPPING_BACKLOG = 256


def _write_trajectory(path: Path, entries: list[tuple[int, float, np.ndarray]]) -> None:
    from worker.eval import Trajectory, write_tum

    if entries:
        write_tum(path, Trajectory(np.array([t for _, t, _ in entries]), np.stack([se3_part(p)
                                                                                    for _, _, p in entries])))
    else:
        path.write_text("# timestamp tx ty tz qx qy qz qw\n")


def run_sequence(
    source: str | Path,
    out_dir: str | Path,
    config: SlamConfig,
    use_gt_depth: bool = False,
    use_gt_poses: bool = False,
    max_frames: int | None = None,
    stride: int = 1,
    resize: tuple[int, int] | None = None,
    drift: PoseDrift | None = None,
    eval_every: int = 1,
    progress: Callable[[int, int | None], None] | None = None,
    unknown_intrinsics: bool = False,
    pingpong: int = 1,
    live_pacing: bool = False,
    scale: float = 1.0,
    finish_progress: Callable[[dict[str, Any]], None] | None = None,
    max_eval_frames: int = MAX_EVAL_FRAMES,
    device_poses: Callable[[Frame], np.ndarray | None] | None = None,
) -> dict[str, Any]:
    """Run one sequence end to end and evaluate it (see the module docstring).

    Recorded frames can wait for the map, so by default the mapping stage sheds nothing: it refines every keyframe
    as it comes (in order, behind tracking by up to OFFLINE_MAPPING_BACKLOG keyframes) and the map, hence PSNR, does
    not depend on the machine's load; and visual odometry may spend seconds on LighterGlue (`learned_glue`) where
    XFeat places a lost frame nowhere. `live_pacing` keeps a live session's load shedding (fewer refinement
    iterations, then merge only, when mapping falls behind) and its tracking budget, to study what a live stream
    gets. `scale` multiplies every pose and depth of the source (the same scene in other length units).
    `finish_progress` is called twice a second while the run finishes, with `FinishStatus.as_dict()`. The rendering
    scores use at most `max_eval_frames` held-out frames, evenly spread (0: every one). `device_poses` replaces each
    frame's device pose (a benchmark's copy of the ground truth with a clock offset, bench/device_clock.py)."""
    from worker.data import open_source
    from worker.pipeline.session_stats import device_clock, final_adjustment, pose_strategy
    from worker.slam import SlamSystem

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # Depth is always read when the dataset has it (the evaluation needs it); the engine uses it only when asked.
    config = config.model_copy(update={"input": config.input.model_copy(update={"use_depth": use_gt_depth})})
    if not live_pacing:
        config = complete_pacing(config)
    src = open_source(str(source), stride=stride, max_frames=max_frames, resize=resize, use_gt_depth=True,
                      use_gt_poses=use_gt_poses, pingpong=pingpong, scale=scale)
    try:
        total = len(src)
    except TypeError:
        total = None
    given_intrinsics = None if unknown_intrinsics else src.intrinsics
    system = SlamSystem(config, intrinsics=given_intrinsics)
    try:  # the stages' threads stop on an error too (else the process aborts at exit)
        frames: list[Frame] = []  # every frame; the image and depth only of every `hold_every`-th (see MAX_HELD_FRAMES)
        hold_every = 1 if total is None else max(1, -(-total // MAX_HELD_FRAMES))
        results = []
        injector = None if drift is None else drift.injector()
        start = time.perf_counter()
        for k, frame in enumerate(src):
            if device_poses is not None:
                frame.pose = device_poses(frame)
            if injector is not None and frame.pose is not None:
                frame.pose = injector.apply(frame.pose)
            if unknown_intrinsics:
                frame.intrinsics = None
            results.append(system.push(frame))
            _wait_for_mapping(system, config.queue_size // 2)
            frames.append(frame if k % hold_every == 0 else _without_pixels(frame))
            if progress is not None:
                progress(k + 1, total)
        tracked_s = time.perf_counter() - start
        lag_at_last_pose = system.live_stats()
        with _reporting(system.finish_status, finish_progress):
            system.finish()
        runtime = time.perf_counter() - start
        if not frames:
            raise ValueError(f"{source} yielded no frames")

        all_poses = system.trajectory("all")
        _write_trajectory(out / "trajectory_all.tum", all_poses)
        _write_trajectory(out / "trajectory_keyframes.tum", system.trajectory("keyframes"))
        intrinsics = system.estimated_intrinsics()
        (out / "intrinsics.json").write_text(json.dumps(
            {**(intrinsics.to_dict() if intrinsics else {}), "estimated": given_intrinsics is None}, indent=1))
        metrics: dict[str, Any] = {
            "sequence": src.name, "dataset": _dataset_name(source), "method": "Flash-Mono",
            "mode": system.mode, "preset": config.name, "num_frames": len(frames),
            "num_keyframes": len(system.trajectory("keyframes")), "loops": int(system.counters["loops"]),
            "frames_tracked": int(system.counters["frames_tracked"]),
            "events": _event_counts(results),
            "revision": system.revision, "runtime_s": runtime, "fps": len(frames) / runtime,
            # the rate poses come out while the frames stream (mapping runs behind, and with live pacing sheds work
            # when it must: what it shed and how far it lagged at the last pose are below; finish() then drains it
            # and refines)
            "fps_streaming": len(frames) / max(1e-9, tracked_s),
            "finish_s": runtime - tracked_s,
            "mapping_lag_at_last_pose": {"keyframes": lag_at_last_pose["mapping_lag_keyframes"],
                                         "seconds": lag_at_last_pose["mapping_lag_s"]},
            "keyframes_shed": system.live_stats()["keyframes_shed"], "live_pacing": live_pacing,
            "threaded": config.threaded,
            "use_gt_depth": use_gt_depth, "use_gt_poses": use_gt_poses, "scale": scale, "tracking": system.tracking,
            "pose_strategy": pose_strategy(system), "depth_source": system.depth_source, **system.pose_source_choice(),
            "device_clock": device_clock(system), "final_adjustment": final_adjustment(system),
            "intrinsics": intrinsics.to_dict() if intrinsics else None,
            "intrinsics_estimated": given_intrinsics is None,
            "drift": None if drift is None else drift.to_dict(),
            "runtime_breakdown": system.timings.breakdown(len(frames)),
            "eval_frames_held_every": hold_every,
        }
        registered = {int(i) for r in results for e in r.events if isinstance(e, (Initialized, Relocalized))
                      for i in e.registered_frames or []}  # lost frames posed later (a new map, photo registration)
        metrics["frames_registered"] = int(sum(r.tracked or r.index in registered for r in results))
        metrics.update(_trajectory_metrics(frames, all_poses, drift, [r.tracked for r in results],
                                           [r.tracked or r.index in registered for r in results]))
        if system.mapping_stage is not None:
            (out / "map.ply").write_bytes(system.export_ply())
            metrics["num_gaussians"] = system.num_gaussians
            metrics.update(_render_metrics(system, frames, results, all_poses, intrinsics, out, eval_every, hold_every,
                                           max_eval_frames))
            metrics["keyframe_depth"] = _keyframe_depth_metrics(system, frames)
        else:
            metrics.update({"num_gaussians": 0, "psnr": None, "ssim": None, "lpips": None, "depth_l1": None,
                            "lpips_note": "mapping disabled"})
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    finally:
        system.close()
    return metrics


@contextlib.contextmanager
def _reporting(status, report: Callable[[dict[str, Any]], None] | None, every_s: float = 0.5) -> Iterator[None]:
    """Call `report(status.as_dict())` every `every_s` seconds from a thread while the block runs, and once after."""
    if report is None:
        yield
        return
    stop = threading.Event()

    def loop() -> None:
        while not stop.wait(every_s):
            report(status.as_dict())

    thread = threading.Thread(target=loop, name="finish-progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        report(status.as_dict())


def complete_pacing(config: SlamConfig) -> SlamConfig:
    """An offline run's settings: mapping sheds nothing (a backlog of up to OFFLINE_MAPPING_BACKLOG keyframes) and
    visual odometry may try LighterGlue where XFeat places a lost frame nowhere, unless `config` set it."""
    visual = config.tracking.visual
    if "learned_glue" not in visual.model_fields_set:
        visual = visual.model_copy(update={"learned_glue": True})
    return config.model_copy(update={
        "queue_size": max(config.queue_size, OFFLINE_MAPPING_BACKLOG),
        "mapping": config.mapping.model_copy(update={"shed_backlog": 0}),
        "tracking": config.tracking.model_copy(update={"visual": visual})})


def _event_counts(results: list) -> dict[str, int]:
    """How many events of each type (tracking_lost, relocalized, new_map, loop_closed, ...) the frames carried."""
    counts: dict[str, int] = {}
    for result in results:
        for event in result.events:
            counts[event.TYPE] = counts.get(event.TYPE, 0) + 1
    return dict(sorted(counts.items()))


def _without_pixels(frame: Frame) -> Frame:
    """The frame's poses only (for the trajectory metrics), without its image and depth."""
    return Frame(frame.index, frame.timestamp, np.zeros((1, 1, 3), np.uint8), pose=frame.pose, gt_pose=frame.gt_pose)


def _wait_for_mapping(system, backlog: int) -> None:
    """Recorded frames can wait: hold the next frame while mapping has more than `backlog` keyframes waiting, so an
    offline run never makes the mapping stage drop keyframes as a live stream would (sources that outrun any
    mapping, such as given poses, would otherwise leave holes in the map)."""
    while system.live_stats()["mapping_lag_keyframes"] > backlog:
        time.sleep(0.005)


def _dataset_name(source: str | Path) -> str:
    text = str(source)
    return text.split("://", 1)[0] if "://" in text else Path(text).resolve().parent.name or "data"


def _trajectory_metrics(frames: list[Frame], poses: list, drift: PoseDrift | None, tracked: list[bool],
                        registered: list[bool] | None = None) -> dict[str, Any]:
    """ATE over every frame (a lost frame counts with the pose it held), over the tracked frames alone and over
    the registered ones (tracked, or posed later by the map begun after their loss)."""
    from worker.eval import absolute_trajectory_error

    pairs = [(p, f.gt_pose, t) for (_, _, p), f, t in zip(poses, frames, tracked) if f.gt_pose is not None]
    if len(pairs) < 3:
        return {"ate_rmse": None, "ate_note": "no ground-truth poses"}
    est = np.stack([p for p, _, _ in pairs])
    gt = np.stack([np.asarray(g, np.float64) for _, g, _ in pairs])
    out = {"ate_rmse": absolute_trajectory_error(est, gt, "sim3").rmse}
    kept = np.array([t for _, _, t in pairs])
    if 3 <= kept.sum() < len(kept):
        out["ate_rmse_tracked"] = absolute_trajectory_error(est[kept], gt[kept], "sim3").rmse
    if registered is not None:
        posed = np.array([r for (_, f), r in zip(zip(poses, frames), registered) if f.gt_pose is not None])
        if 3 <= posed.sum() < len(posed) and not np.array_equal(posed, kept):
            out["ate_rmse_registered"] = absolute_trajectory_error(est[posed], gt[posed], "sim3").rmse
    if drift is not None:  # the drifted poses the system was given, before any loop closure
        given = np.stack([np.asarray(f.pose, np.float64) for f in frames if f.gt_pose is not None])
        out["ate_rmse_drift_only"] = absolute_trajectory_error(given, gt, "sim3").rmse
    return out


def _keyframe_depth_metrics(system, frames: list[Frame]) -> dict[str, Any] | None:
    """The depth the keyframes were mapped from against the recording's sensor depth, for sessions mapped without
    it (worker.eval.keyframe_depth; keyframes whose frame was held with its depth); None otherwise."""
    from worker.eval.keyframe_depth import keyframe_depth_scores

    if system.config.input.use_depth:
        return None
    sensor = {f.index: f.depth for f in frames if f.depth is not None}
    if not sensor:
        return None
    scores = keyframe_depth_scores(system.mapping_stage.map.keyframe_depths(), sensor,
                                   metric=system.tracking == "device")
    return None if scores is None else scores.to_dict()


def renderer_as_captured(system, K: np.ndarray, width: int, height: int, frame_indices: list[int]):
    """A render callable for `evaluate_renders` whose n-th call renders under the exposure the camera had at frame
    `frame_indices[n]` (`SlamSystem.render_view(as_captured_at=)`): evaluate_renders renders its frames once each,
    in order."""
    captured_at = iter(frame_indices)

    def render(pose: np.ndarray, _intrinsics) -> tuple[np.ndarray, np.ndarray]:
        return system.render_view(pose, K, width, height, as_captured_at=next(captured_at))

    return render


def _render_metrics(system, frames: list[Frame], results, poses, intrinsics, out: Path, every: int,
                    hold_every: int = 1, max_frames: int = 0) -> dict[str, Any]:
    """PSNR/SSIM/LPIPS and depth L1 on non-keyframes rendered from their estimated poses (those held: every
    `hold_every`-th frame), under the exposure the camera had at each (interpolated between the keyframes around
    it: the photo's own exposure is never fitted); `psnr_normalised` / `ssim_normalised` score the map's
    exposure-normalised colours (the first keyframe's exposure) against the same photos. At most `max_frames` of
    them (evenly spread; 0: all) are scored: each costs three renders."""
    import cv2
    import torch

    from worker.eval import evaluate_renders, non_keyframe_indices
    from worker.eval.metrics import hole_shares

    if intrinsics is None:
        return {"psnr": None, "ssim": None, "lpips": None, "depth_l1": None, "lpips_note": "no intrinsics"}
    # the keyframes as the trajectory holds them (frames judged before a pose source was chosen became keyframes
    # after their results were returned); the final view is mapped too
    keyframes = {index for index, _, _ in system.trajectory("keyframes")}
    mapped = [r.index in keyframes or r.index == system.last_frame_mapped for r in results]
    chosen = [i for i in non_keyframe_indices(mapped, every) if i % hold_every == 0] or list(
        range(0, len(frames), hold_every))
    if max_frames and len(chosen) > max_frames:
        chosen = chosen[::-(-len(chosen) // max_frames)]
    metric_depth = system.config.input.use_depth
    K = intrinsics.matrix().numpy()
    (out / "renders").mkdir(exist_ok=True)
    saved = {i for i in chosen[:: max(1, len(chosen) // MAX_SAVED_RENDERS)]}

    def render(pose: np.ndarray, _intr) -> tuple[np.ndarray, np.ndarray]:
        return system.render_view(pose, K, intrinsics.width, intrinsics.height)

    eval_frames = [frames[i] for i in chosen]
    eval_poses = [se3_part(poses[i][2]) for i in chosen]
    render_as_captured = renderer_as_captured(system, K, intrinsics.width, intrinsics.height,
                                              [frame.index for frame in eval_frames])
    for i, frame, pose in zip(chosen, eval_frames, eval_poses):
        if i in saved:
            rgb, _ = system.render_view(pose, K, intrinsics.width, intrinsics.height, as_captured_at=frame.index)
            side = np.concatenate([rgb, frame.image], axis=1)
            cv2.imwrite(str(out / "renders" / f"{frame.index:05d}.png"), cv2.cvtColor(side, cv2.COLOR_RGB2BGR))
    depth_scaling = "none" if metric_depth else "median"
    scores = evaluate_renders(render_as_captured, eval_frames, eval_poses, depth_scaling=depth_scaling)
    normalised = evaluate_renders(render, eval_frames, eval_poses, depth_scaling=depth_scaling)
    holes = [hole_shares(system.mapping_stage.render(pose, torch.as_tensor(K, dtype=torch.float32), intrinsics.width,
                                               intrinsics.height).alpha.cpu().numpy()) for pose in eval_poses]
    return {"psnr": scores.psnr, "ssim": scores.ssim, "lpips": scores.lpips, "lpips_note": scores.lpips_note,
            "psnr_normalised": normalised.psnr, "ssim_normalised": normalised.ssim,
            "depth_l1": scores.depth_l1, "depth_scaling": "none" if metric_depth else "median",
            "eval_frames": scores.num_frames,
            # per held-out frame, so that runs of different modes can be compared on the frames both held out
            "held_out": {"index": [frame.index for frame in eval_frames], "psnr": list(scores.psnr_per_frame),
                         "psnr_normalised": list(normalised.psnr_per_frame)},
            "uncovered_share": float(np.mean([h[0] for h in holes])) if holes else None,
            "largest_hole_share": float(max(h[1] for h in holes)) if holes else None}
