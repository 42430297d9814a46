"""The engine's trajectory: keyframe poses (what the pose graph optimises) and every frame tied to a keyframe.

Each frame stores its pose relative to its reference keyframe (the latest keyframe at or before it) as tracking
measured it; its world pose is the keyframe's current pose times that relative pose. A pose-graph update therefore
moves every frame with its keyframe (paper 4.2) and bumps the revision, so clients know the past was rewritten.
A frame the pose source measured against an earlier keyframe it came back to also keeps that `anchor` and its pose
relative to it; `anchor_frames` (at the session's end) puts such frames on the anchor's corrected pose, which the
loops and the graph have freed of the drift the newest keyframe still carries.

The per-frame records are the only part that grows with the session. A chunked state (`chunked_state`) keeps them
out of the snapshot: full runs of `chunk_frames` records are sealed into chunks written once (`ChunkWrite.new`,
stored beside the snapshot), and the state holds the keyframe poses, the unsealed tail and a manifest of the chunks
it needs. A loop correction moves keyframe poses only (frames keep their relative poses), so it touches no chunk;
`revise_frames` on sealed records bumps those chunks' versions, and the next chunked state writes them again.
`joined_state(state, chunks)` turns a chunked state back into the full one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from protocol.codec import pack, unpack
from worker.geometry import nearest_sim3, sim3_blend, sim3_inverse
from worker.pipeline.snapshot_chunks import ChunkWrite, chunk_versions

CHUNK_FRAMES = 256  # frame records per sealed chunk
FRAME_COLUMNS = ("index", "timestamp", "keyframe", "relative", "is_keyframe", "submap_id", "anchor", "anchored")
NO_ANCHOR = -1


def _inv(T: np.ndarray) -> np.ndarray:
    return sim3_inverse(torch.from_numpy(np.asarray(T, np.float64))).numpy()


@dataclass
class FrameRecord:
    index: int
    timestamp: float
    keyframe: int  # reference keyframe id
    relative: np.ndarray  # T_kf^-1 T_frame, from tracking
    is_keyframe: bool
    submap_id: int
    anchor: int = NO_ANCHOR  # an earlier keyframe the source measured this frame against (come back to)
    anchored: np.ndarray | None = None  # T_anchor^-1 T_frame, as the source measured it


def _columns(records: list[FrameRecord]) -> dict[str, np.ndarray]:
    return {
        "index": np.asarray([r.index for r in records], np.int64),
        "timestamp": np.asarray([r.timestamp for r in records], np.float64),
        "keyframe": np.asarray([r.keyframe for r in records], np.int64),
        "relative": np.stack([r.relative for r in records]) if records else np.zeros((0, 4, 4)),
        "is_keyframe": np.asarray([r.is_keyframe for r in records], bool),
        "submap_id": np.asarray([r.submap_id for r in records], np.int64),
        "anchor": np.asarray([r.anchor for r in records], np.int64),
        "anchored": (np.stack([np.eye(4) if r.anchored is None else r.anchored for r in records]) if records
                     else np.zeros((0, 4, 4))),
    }


def _with_anchor_columns(part: Mapping[str, Any]) -> dict[str, Any]:
    """Frame columns of a state or chunk written before anchors: none anchored."""
    count = len(part["index"])
    return {"anchor": np.full(count, NO_ANCHOR, np.int64), "anchored": np.tile(np.eye(4), (count, 1, 1)), **part}


class Trajectory:
    """Keyframe poses by keyframe id (ids are frame indices) and per-frame records, with a revision counter."""

    def __init__(self, chunk_frames: int = CHUNK_FRAMES) -> None:
        if chunk_frames < 1:
            raise ValueError("chunk_frames must be at least 1")
        self.frames: list[FrameRecord] = []
        self.keyframe_poses: dict[int, np.ndarray] = {}
        self.tracked_keyframe_poses: dict[int, np.ndarray] = {}
        self.revision = 0
        self.chunk_frames = chunk_frames
        self.chunk_revisions: dict[int, int] = {}  # sealed chunks whose records were revised: chunk -> version
        self._last_index: int | None = None
        # Tracking's world -> this trajectory's world for a keyframe with no reference (the first): moved with the
        # whole world (`move_world`), e.g. a session anchored in a stored map before its first keyframe
        self.world_base = np.eye(4)

    def add_keyframe(self, kf_id: int, tracked_pose: np.ndarray, reference: int | None = None) -> np.ndarray:
        """Add keyframe `kf_id` from its tracked pose; returns its world pose. With a `reference` keyframe, the
        new keyframe follows that keyframe's corrections (its tracked relative pose is kept), so a keyframe after a
        loop closure starts from the corrected trajectory, not from the drifted odometry."""
        tracked = nearest_sim3(tracked_pose)
        pose = tracked if np.array_equal(self.world_base, np.eye(4)) else nearest_sim3(self.world_base @ tracked)
        if reference is not None:
            pose = nearest_sim3(self.keyframe_poses[reference] @ _inv(self.tracked_keyframe_poses[reference]) @ tracked)
        self.tracked_keyframe_poses[int(kf_id)] = tracked
        self.keyframe_poses[int(kf_id)] = pose
        return pose

    def add_frame(self, index: int, timestamp: float, keyframe: int, tracked_pose: np.ndarray, is_keyframe: bool,
                  submap_id: int, anchor: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """Record a frame from its tracked pose, tied to `keyframe`; returns its world pose now. `anchor`: an
        earlier keyframe the source measured the frame against and the pose relative to it (`anchor_frames`)."""
        if self._last_index is not None and index <= self._last_index:
            raise ValueError(f"frame index {index} is not after the previous frame {self._last_index}")
        rel = nearest_sim3(_inv(self.tracked_keyframe_poses[keyframe]) @ np.asarray(tracked_pose, np.float64))
        record = FrameRecord(int(index), float(timestamp), int(keyframe), rel, bool(is_keyframe), int(submap_id))
        if anchor is not None and not is_keyframe and int(anchor[0]) in self.keyframe_poses:
            record.anchor, record.anchored = int(anchor[0]), nearest_sim3(np.asarray(anchor[1], np.float64))
        self.frames.append(record)
        self._last_index = int(index)
        return self.pose_of(self.frames[-1])

    def move_world(self, transform: np.ndarray) -> None:
        """The whole world moved by `transform` (the keyframes move by their own correction): keyframes made
        without a reference from now on start in the moved world."""
        self.world_base = np.asarray(transform, np.float64) @ self.world_base

    def provisional(self, tracked_pose: np.ndarray) -> np.ndarray:
        """The world pose of a frame tracked before any keyframe (not recorded): its tracked pose moved with the
        world."""
        return self.world_base @ np.asarray(tracked_pose, np.float64)

    def pose_of(self, record: FrameRecord) -> np.ndarray:
        return self.keyframe_poses[record.keyframe] @ record.relative

    def pose_at(self, index: int) -> np.ndarray:
        """The current world pose of frame `index` (recent frames are found first)."""
        for record in reversed(self.frames):
            if record.index == index:
                return self.pose_of(record)
        raise ValueError(f"frame {index} is not in the trajectory")

    def revise_frames(self, poses: dict[int, np.ndarray], keyframe: int | None = None,
                      submap_id: int | None = None) -> int:
        """Replace the tracked poses of past non-keyframes (a pose source re-estimated them, e.g. the frames
        before a monocular initialisation); with `keyframe`, the frames are tied to that keyframe (and its
        `submap_id`) instead of the one they followed. Returns the new revision."""
        touched = set()
        for position, record in enumerate(self.frames):
            if record.index in poses and not record.is_keyframe:
                if keyframe is not None:
                    record.keyframe = int(keyframe)
                    record.submap_id = record.submap_id if submap_id is None else int(submap_id)
                record.relative = _inv(self.tracked_keyframe_poses[record.keyframe]) @ np.asarray(
                    poses[record.index], np.float64)
                touched.add(position)
        return self._revised(touched)

    def place_frames(self, poses: dict[int, np.ndarray]) -> int:
        """Put past non-keyframes at these world poses as the trajectory is now (their keyframes' current poses:
        unlike `revise_frames`, whose poses are in the world the keyframes were tracked in). Returns the new
        revision."""
        touched = set()
        for position, record in enumerate(self.frames):
            if record.index in poses and not record.is_keyframe:
                record.relative = _inv(self.keyframe_poses[record.keyframe]) @ np.asarray(poses[record.index],
                                                                                            np.float64)
                touched.add(position)
        return self._revised(touched)

    def source_corrected_poses(self, corrections: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
        """World poses of every recorded frame after the pose source moved its own keyframes (frame index -> the
        motion, rigid or a similarity, from the pose it handed out to the adjusted one, in the world it tracked
        in): each frame's tracked pose moves with the source keyframes before and after it, by how near it is to
        each (the first and last ones alone outside them). The source's adjustment replaces the corrections made
        here since."""
        order = np.array(sorted(corrections), np.int64)
        if len(order) == 0:
            return {}
        moves = [torch.from_numpy(np.asarray(corrections[int(k)], np.float64)) for k in order]
        placed = {}
        for record in self.frames:
            tracked = self.tracked_keyframe_poses[record.keyframe] @ record.relative
            after = int(np.searchsorted(order, record.index, side="right"))
            if after == 0 or after == len(order):
                move = moves[min(after, len(order) - 1)].numpy()
            else:
                a, b = order[after - 1], order[after]
                move = sim3_blend(moves[after - 1], moves[after], float(record.index - a) / float(b - a)).numpy()
            placed[record.index] = self.world_base @ move @ tracked
        return placed

    def anchor_frames(self) -> int:
        """Put every anchored frame at its anchor keyframe's current pose times the pose measured against it (the
        frame keeps following its own keyframe from there). Returns how many frames were placed; a new revision
        when any was."""
        placed = {r.index: self.keyframe_poses[r.anchor] @ r.anchored for r in self.frames
                  if r.anchor != NO_ANCHOR and r.anchor in self.keyframe_poses}
        if placed:
            self.place_frames(placed)
        return len(placed)

    def spread_keyframe_moves(self, old_keyframe_poses: Mapping[int, np.ndarray]) -> int:
        """After keyframes moved from `old_keyframe_poses` to their current poses, each frame between its keyframe
        and the next one moves with both, by how near it is to each (frame indices; the rotation along the geodesic),
        instead of rigidly with the one before it: the move of a keyframe that was refined alone (not as part of a
        rigid correction) says little about frames next to the keyframe after it. Returns the new revision."""
        order = sorted(self.keyframe_poses)
        next_keyframe = dict(zip(order, order[1:]))
        moves = {k: self.keyframe_poses[k] @ _inv(old) for k, old in old_keyframe_poses.items()
                 if k in self.keyframe_poses}
        # keyframes whose move differs from the next keyframe's: only their frames change (checked once each, not
        # once a frame: a long session's finish walks every frame record)
        spread = {a for a, b in next_keyframe.items()
                  if a in moves and b in moves and not np.allclose(moves[a], moves[b], rtol=0.0, atol=1e-12)}
        touched = set()
        for position, record in enumerate(self.frames):
            a = record.keyframe
            if record.is_keyframe or a not in spread or not a < record.index < next_keyframe[a]:
                continue
            b = next_keyframe[a]
            old_pose = old_keyframe_poses[a] @ record.relative
            with_a, with_b = moves[a] @ old_pose, moves[b] @ old_pose
            placed = sim3_blend(torch.from_numpy(with_a), torch.from_numpy(with_b), (record.index - a) / (b - a))
            record.relative = _inv(self.keyframe_poses[a]) @ placed.numpy()
            touched.add(position)
        return self._revised(touched)

    def _revised(self, positions: set[int]) -> int:
        """A new revision after the records at `positions` changed: their sealed chunks are rewritten at a new
        version (the tail is in the state anyway)."""
        sealed = len(self.frames) // self.chunk_frames
        for chunk in {position // self.chunk_frames for position in positions}:
            if chunk < sealed:
                self.chunk_revisions[chunk] = self.chunk_revisions.get(chunk, 0) + 1
        self.revision += 1
        return self.revision

    def update_keyframes(self, poses: dict[int, np.ndarray]) -> int:
        """Replace keyframe poses (after PGO); returns the new revision."""
        for kf, pose in poses.items():
            if kf not in self.keyframe_poses:
                raise ValueError(f"unknown keyframe {kf}")
            self.keyframe_poses[int(kf)] = np.asarray(pose, np.float64).copy()  # as the map takes them
        self.revision += 1
        return self.revision

    def listing(self, which: str = "all") -> list[tuple[int, float, np.ndarray]]:
        """[(index, timestamp, pose c2w 4x4)] for "all" frames or only "keyframes"."""
        if which not in ("all", "keyframes"):
            raise ValueError(f"trajectory kind must be 'all' or 'keyframes', got {which!r}")
        return [(r.index, r.timestamp, self.pose_of(r)) for r in self.frames if which == "all" or r.is_keyframe]

    def _keyframe_state(self) -> dict[str, Any]:
        kf = sorted(self.keyframe_poses)
        return {
            "revision": self.revision,
            "keyframe_ids": np.asarray(kf, np.int64),
            "keyframe_poses": np.stack([self.keyframe_poses[k] for k in kf]) if kf else np.zeros((0, 4, 4)),
            "tracked_keyframe_poses": (np.stack([self.tracked_keyframe_poses[k] for k in kf]) if kf
                                       else np.zeros((0, 4, 4))),
            "chunk_frames": self.chunk_frames,
            "chunk_revisions": dict(self.chunk_revisions),
            "world_base": self.world_base,
        }

    def state_dict(self) -> dict:
        """The whole trajectory, every frame record included (self-contained)."""
        return {**self._keyframe_state(), **_columns(self.frames)}

    def chunked_state(self, stored: Mapping[int, int]) -> tuple[dict, ChunkWrite]:
        """The state without the sealed records, and the chunks it needs: those not in `stored` (chunk -> version
        already written) are packed into `ChunkWrite.new`. Its size does not grow with the frame count."""
        size = self.chunk_frames
        sealed = len(self.frames) // size
        revisions = {i: v for i, v in self.chunk_revisions.items() if i < sealed}
        manifest = {"frames": size, "sealed": sealed, "versions": revisions}
        new = {}
        for i in range(sealed):
            version = revisions.get(i, 0)
            if stored.get(i) != version:
                new[i] = pack({"chunk": i, "version": version, **_columns(self.frames[i * size:(i + 1) * size])})
        state = {**self._keyframe_state(), **_columns(self.frames[sealed * size:]), "chunks": manifest}
        return state, ChunkWrite(manifest, new)

    @staticmethod
    def joined_state(state: dict, chunks: Mapping[int, bytes]) -> dict:
        """The full state of a chunked one (`chunked_state`) with its sealed `chunks` (chunk -> bytes); a full
        state is returned as it is. Raises ValueError when a chunk is missing or at another version."""
        manifest = state.get("chunks")
        if manifest is None:
            return state
        parts = []
        for i, version in chunk_versions(manifest).items():
            raw = chunks.get(i)
            if raw is None:
                raise ValueError(f"the snapshot needs trajectory chunk {i}, which is missing")
            part = unpack(raw)
            if int(part["chunk"]) != i or int(part["version"]) != version:
                raise ValueError(f"trajectory chunk {i} is at version {part['version']} (chunk {part['chunk']}); "
                                 f"the snapshot needs version {version}")
            parts.append(part)
        parts.append(state)
        parts = [_with_anchor_columns(p) for p in parts]
        joined = {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in FRAME_COLUMNS}
        return {**{k: v for k, v in state.items() if k != "chunks"}, **joined,
                "chunk_frames": int(manifest["frames"])}

    def load_state_dict(self, d: dict) -> None:
        """Load a full state (`state_dict`, or `joined_state` of a chunked one)."""
        if "chunks" in d:
            raise ValueError("a chunked trajectory state needs its chunks: load Trajectory.joined_state(state, ...)")
        self.revision = int(d["revision"])
        self.chunk_frames = int(d.get("chunk_frames", self.chunk_frames))
        self.chunk_revisions = {int(k): int(v) for k, v in (d.get("chunk_revisions") or {}).items()}
        self.world_base = np.asarray(d.get("world_base", np.eye(4)), np.float64).reshape(4, 4)
        self.keyframe_poses = {int(k): np.asarray(p, np.float64) for k, p in zip(d["keyframe_ids"],
                                                                              d["keyframe_poses"])}
        self.tracked_keyframe_poses = {int(k): np.asarray(p, np.float64)
                                       for k, p in zip(d["keyframe_ids"], d["tracked_keyframe_poses"])}
        d = _with_anchor_columns(d)
        self.frames = [FrameRecord(int(i), float(t), int(k), np.asarray(rel, np.float64), bool(kf), int(s), int(a),
                                   None if a == NO_ANCHOR else np.asarray(anchored, np.float64))
                       for i, t, k, rel, kf, s, a, anchored in zip(d["index"], d["timestamp"], d["keyframe"],
                                                                   d["relative"], d["is_keyframe"], d["submap_id"],
                                                                   d["anchor"], d["anchored"])]
        self._last_index = self.frames[-1].index if self.frames else None
