"""The end of a session: every stage drained, the last loops applied, the final refinement, in phases a user sees.

Phases (worker.pipeline.finish_status): `mapping` (the newest view joins the map; the depth source's last jobs and the
backlog are mapped), `loop_closing` (every loop query answered; the corrections applied to the trajectory and the
map), `refining` (the final refinement of the whole map, within `final_refine_budget_s`; with
`final_refine_poses` the keyframes' cameras too, which the trajectory then follows), `done`. Last, the frames the
pose source measured against an earlier keyframe it came back to are put on that keyframe's final pose
(`Trajectory.anchor_frames`); one `poses_refined` event reports the keyframes and frames moved.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from worker.events import PosesRefined
from worker.pipeline.session_parts import SessionParts
from worker.pipeline.session_stats import pose_source_choice


def finish_session(system: SessionParts) -> None:
    """Drain `system`'s stages and run its final refinement; its finish events go to `system.finish_events`."""
    started = time.perf_counter()
    stage, mapping, status = system.tracking_stage, system.mapping_stage, system.finish_status
    system.finish_events += system.judged_start.conclude()  # the stream ended while the device poses were judged
    clock = getattr(stage.pose_source, "device_clock", None)
    if clock is not None:  # a stream shorter than the clock's window: measured on what came, for the report
        clock.finish_measuring()
    stage.begin_source_adjustment()  # visual odometry's final bundle adjustment, while the stages drain
    if mapping is not None:
        stage.map_last_frame()
        stage.hand_to_mapping(force=True)
        backlog = mapping.pending
        status.begin("mapping", backlog, done=lambda: backlog - mapping.pending)
        mapping.wait_idle()
    status.begin("loop_closing", system.loop_stage.pending)
    system.loop_stage.wait_idle()
    system.finish_events += stage.apply_loop_corrections()  # loops the stage closed after the last frame
    system.finish_events += stage.apply_source_refinement()  # photo registration's last bundle adjustment
    if mapping is None:
        _anchor_frames(system, None)
        status.begin("done", 0)
        return
    if system.finish_events:
        mapping.wait_idle()
    cfg = system.config.mapping
    refined = None
    if cfg.final_refine_passes:
        budget = cfg.final_refine_budget_s  # from the start of finish() (the drain too) where the config says so
        since = started if cfg.final_refine_budget_counts_drain else time.perf_counter()
        left = None if not budget else max(0.0, budget - (time.perf_counter() - since))
        status.begin("refining", cfg.final_refine_passes * mapping.held_images,
                     deadline=None if left is None else time.perf_counter() + left)
        moved = mapping.refine_all(cfg.final_refine_passes, budget_s=left, seed=cfg.final_refine_seed,
                                   train_poses=_refines_keyframe_poses(system), on_step=status.step)
        if moved:
            refined = _follow_refined_keyframes(system, moved)
    _anchor_frames(system, refined)
    status.begin("done", 0)


def _anchor_frames(system: SessionParts, refined: PosesRefined | None) -> None:
    """Put the anchored frames on their anchors' final poses; `refined` (the final refinement's event, if any)
    then carries the count and the newest revision, else an event of its own does when any frame moved."""
    trajectory = system.tracking_stage.trajectory
    frames = trajectory.anchor_frames()
    if refined is not None:
        system.finish_events.append(dataclasses.replace(refined, frames=frames or None, revision=trajectory.revision))
    elif frames:
        system.finish_events.append(PosesRefined(keyframes=0, frames=frames, revision=trajectory.revision))


def _refines_keyframe_poses(system: SessionParts) -> bool:
    """Whether the final refinement refines the keyframes' cameras: asked for, and the poses are not the device's
    own to keep (pose_mode fixed)."""
    return system.config.mapping.final_refine_poses and pose_source_choice(system)["pose_source"] != "fixed"


def _follow_refined_keyframes(system: SessionParts, motions: dict[int, np.ndarray]) -> PosesRefined:
    """Move the trajectory's keyframes by the final refinement's world-frame motions (keyframes the map did not
    hold follow the newest refined one before them) and each frame with the keyframes before and after it.
    Returns the event."""
    stage = system.tracking_stage
    trajectory = stage.trajectory
    old = {k: pose.copy() for k, pose in trajectory.keyframe_poses.items()}
    _, changed = stage.apply_correction({k: motion @ old[k] for k, motion in motions.items() if k in old})
    revision = trajectory.spread_keyframe_moves(old)
    return PosesRefined(keyframes=len(changed), revision=revision)
