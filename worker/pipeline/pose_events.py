"""What tracking does with its pose source's events, beyond passing them to the client.

- `initialized` (monocular odometry) carries the re-estimated poses of the frames it waited for: they replace their
  placeholders as a new trajectory revision; for a restarted map (`map` > 1) they are tied to its first keyframe
  once it exists, so that a loop or a join that moves the map moves them too;
- a new camera estimate in `initialized` remakes the loop-closing stage's keyframe points (`CameraUpdate`);
- `relocalized` by reinitialising makes the next keyframe's odometry edge a `restart` seam;
- `maps_merged` (a restarted map recognised an older one) becomes a Sim(3) edge between keyframes (`MapJoin`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from worker.geometry import Intrinsics, sim3_inverse
from worker.pipeline.loop_stage import CameraUpdate, MapJoin
from worker.pipeline.trajectory import Trajectory


class PoseEvents:
    """The tracking stage's handling of pose-source events (see the module docstring)."""

    def __init__(self, trajectory: Trajectory, to_loop_closing: Callable[[Any], None],
                 counters: dict[str, float]) -> None:
        self.trajectory = trajectory
        self.to_loop_closing = to_loop_closing
        self.counters = counters
        self.reprojects_points = False  # the loop-closing stage keeps keyframe points made with the camera
        self.restart_seam = False  # the next keyframe's odometry edge crosses the seam of a restarted map
        # (the `initialized` event of a new map, its frames' poses): applied once the map's first keyframe is in
        self._revise_on_keyframe: tuple[dict[str, Any], dict[int, np.ndarray]] | None = None

    def on_tracked(self, events: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """Act on a frame's events (all but `maps_merged`, which waits for the keyframe decision); returns them as
        clients get them."""
        self.restart_seam |= any(e.get("type") == "relocalized" and e.get("method") == "reinitialized"
                                 for e in events)
        return [self._initialized(event) for event in events if event.get("type") != "maps_merged"]

    def after_keyframe_decision(self, events: list[dict[str, Any]], keyframe: int | None, submap_id: int,
                                pose: np.ndarray, last_keyframe: int | None) -> None:
        """Once the frame is (or is not) keyframe `keyframe`: revise a new map's waiting frames, send map joins."""
        if self._revise_on_keyframe is not None:
            self._revise_new_map_frames(keyframe, submap_id)
        for event in events:
            if event.get("type") == "maps_merged" and last_keyframe is not None:
                self._submit_map_join(pose, event, last_keyframe)

    def _initialized(self, event: dict[str, Any]) -> dict[str, Any]:
        if event.get("type") != "initialized" or not event.get("frames"):
            return dict(event)
        poses = {int(i): np.asarray(p, np.float64) for i, p in event["frames"]}
        revised = {i: p for i, p in poses.items() if np.all(np.isfinite(p))}
        if event.get("intrinsics") and self.reprojects_points:  # keyframe points made with the old camera
            self.to_loop_closing(CameraUpdate(Intrinsics.from_dict(event["intrinsics"]).matrix()))
        out = {k: v for k, v in event.items() if k != "frames"}
        if int(event.get("map", 1)) > 1:  # a new map's waiting frames: tied to its first keyframe
            self._revise_on_keyframe = (out, revised)
            return out
        out["revision"] = self.trajectory.revise_frames(revised)
        out["frames_revised"] = len(revised)
        return out

    def _revise_new_map_frames(self, keyframe: int | None, submap_id: int) -> None:
        """The frames a new map waited for (reported lost), posed by its initialisation: tied to the map's first
        keyframe (a new revision, said in the `initialized` event with the frames' indices)."""
        out, revised = self._revise_on_keyframe
        self._revise_on_keyframe = None
        out["revision"] = self.trajectory.revise_frames(revised, keyframe=keyframe, submap_id=submap_id)
        out["frames_revised"] = len(revised)
        out["registered_frames"] = sorted(revised)
        self.counters["frames_registered_later"] += len(revised)

    def _submit_map_join(self, pose: np.ndarray, event: dict[str, Any], last_keyframe: int) -> None:
        """The Sim(3) edge of a `maps_merged` event (`relative`: this frame, tracked at `pose`, in the frame of the
        older frame `place`), moved onto the keyframes those frames follow; its pose-graph solve comes back as a
        correction with the `maps_merged` event."""
        traj, place = self.trajectory, int(event["place"])
        if place in traj.tracked_keyframe_poses:
            i, before = place, np.eye(4)
        else:
            record = next((r for r in reversed(traj.frames) if r.index == place), None)
            if record is None:
                return
            i, before = record.keyframe, record.relative  # T_i^-1 T_place, as tracked
        j = last_keyframe
        after = sim3_inverse(torch.from_numpy(traj.tracked_keyframe_poses[j])).numpy() @ pose  # T_j^-1 T_frame
        relative = before @ np.asarray(event["relative"], np.float64) @ sim3_inverse(torch.from_numpy(after)).numpy()
        self.to_loop_closing(MapJoin(i, j, relative, event))
