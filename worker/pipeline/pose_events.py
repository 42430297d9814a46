"""What tracking does with its pose source's events, beyond passing them to the client.

- `initialized` (monocular odometry) carries the re-estimated poses of the frames it waited for: they replace their
  placeholders as a new trajectory revision; for a restarted map (`map` > 1) they are tied to its first keyframe
  once it exists, so that a loop or a join that moves the map moves them too (the event waits for it);
- a new camera estimate in `initialized` remakes the loop-closing stage's keyframe points (`CameraUpdate`);
- `relocalized` by reinitialising makes the next keyframe's odometry edge a `restart` seam; one with frames (photo
  registration placed photos it had reported lost) revises their poses as a new trajectory revision;
- `maps_merged` (a restarted map recognised an older one) becomes a Sim(3) edge between keyframes (`MapJoin`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from worker.events import EngineEvent, Initialized, MapsMerged, Relocalized
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
        self._revise_on_keyframe: tuple[Initialized, dict[int, np.ndarray]] | None = None

    def on_tracked(self, events: list[EngineEvent]) -> list[EngineEvent]:
        """Act on a frame's events; returns them as clients get them, but for `maps_merged`, which waits for the
        keyframe decision, and a new map's `initialized`, which `after_keyframe_decision` returns."""
        self.restart_seam |= any(isinstance(e, Relocalized) and e.method == "reinitialized" for e in events)
        out = []
        for event in events:
            if isinstance(event, Initialized) and event.frames:
                event = self._initialized(event)
            elif isinstance(event, Relocalized) and event.frames:
                event = self._registered_later(event)
            if event is not None and not isinstance(event, MapsMerged):
                out.append(event)
        return out

    def after_keyframe_decision(self, events: list[EngineEvent], keyframe: int | None, submap_id: int,
                                pose: np.ndarray, last_keyframe: int | None) -> list[EngineEvent]:
        """Once the frame is (or is not) keyframe `keyframe`: revise a new map's waiting frames (returns its
        `initialized` event, for the clients), send map joins."""
        revised = [] if self._revise_on_keyframe is None else [self._revise_new_map_frames(keyframe, submap_id)]
        for event in events:
            if isinstance(event, MapsMerged) and last_keyframe is not None:
                self._submit_map_join(pose, event, last_keyframe)
        return revised

    def _initialized(self, event: Initialized) -> Initialized | None:
        """The event with the trajectory revised by its frames' poses; None for a new map's (it waits)."""
        poses = {int(i): np.asarray(p, np.float64) for i, p in event.frames}
        revised = {i: p for i, p in poses.items() if np.all(np.isfinite(p))}
        if event.intrinsics and self.reprojects_points:  # keyframe points made with the old camera
            self.to_loop_closing(CameraUpdate(Intrinsics.from_dict(event.intrinsics).matrix()))
        out = replace(event, frames=None)
        if (event.map or 1) > 1:  # a new map's waiting frames: tied to its first keyframe
            self._revise_on_keyframe = (out, revised)
            return None
        return replace(out, revision=self.trajectory.revise_frames(revised), frames_revised=len(revised))

    def _registered_later(self, event: Relocalized) -> Relocalized:
        """The event with the trajectory revised by the poses of the frames it placed late."""
        revised = {int(i): np.asarray(p, np.float64) for i, p in event.frames}
        revised = {i: p for i, p in revised.items() if np.all(np.isfinite(p))}
        self.counters["frames_registered_later"] += len(revised)
        return replace(event, frames=None, revision=self.trajectory.revise_frames(revised),
                       registered_frames=sorted(revised))

    def _revise_new_map_frames(self, keyframe: int | None, submap_id: int) -> Initialized:
        """The frames a new map waited for (reported lost), posed by its initialisation: tied to the map's first
        keyframe (a new revision, said in the `initialized` event with the frames' indices)."""
        out, revised = self._revise_on_keyframe
        self._revise_on_keyframe = None
        self.counters["frames_registered_later"] += len(revised)
        return replace(out, revision=self.trajectory.revise_frames(revised, keyframe=keyframe, submap_id=submap_id),
                       frames_revised=len(revised), registered_frames=sorted(revised))

    def _submit_map_join(self, pose: np.ndarray, event: MapsMerged, last_keyframe: int) -> None:
        """The Sim(3) edge of a `maps_merged` event (`relative`: this frame, tracked at `pose`, in the frame of the
        older frame `place`), moved onto the keyframes those frames follow; its pose-graph solve comes back as a
        correction with the `maps_merged` event."""
        traj, place = self.trajectory, int(event.place)
        if place in traj.tracked_keyframe_poses:
            i, before = place, np.eye(4)
        else:
            record = next((r for r in reversed(traj.frames) if r.index == place), None)
            if record is None:
                return
            i, before = record.keyframe, record.relative  # T_i^-1 T_place, as tracked
        j = last_keyframe
        after = sim3_inverse(torch.from_numpy(traj.tracked_keyframe_poses[j])).numpy() @ pose  # T_j^-1 T_frame
        relative = before @ np.asarray(event.relative, np.float64) @ sim3_inverse(torch.from_numpy(after)).numpy()
        self.to_loop_closing(MapJoin(i, j, relative, event))
