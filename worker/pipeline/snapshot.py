"""A session's snapshot: everything needed to continue it in any process, as msgpack (never pickle).

Format 2 keeps each stage's part packed apart: the tracking part is packed at once (the next frames change what it
refers to); the map and the loop-closing state at once too, each between two of its stage's work steps, with the
items submitted to it and not done yet as data (a backlog is not waited for; `QueuedStage.snapshot_now`,
`SnapshotFuture`). Keyframe jobs not handed to mapping yet are data in the depth source's part. Format 1 (one
dict, made after waiting for the stages) and format-2 snapshots of earlier versions (the multi-view frame ring in
`keyframe_depth`, loops waiting in `loop_after_depth`, the model's path in the counters) restore too.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from protocol.codec import pack, unpack
from worker.geometry import Intrinsics
from worker.pipeline.depth_sources import ModelSurfels, MultiViewDepth
from worker.pipeline.loop_stage import LoopQuery
from worker.pipeline.session_parts import SessionParts
from worker.pipeline.snapshot_future import SnapshotFuture
from worker.pipeline.trajectory import Trajectory

SNAPSHOT_FORMAT = "flashmono.slam/2"
SNAPSHOT_FORMATS = ("flashmono.slam/1", SNAPSHOT_FORMAT)


def begin_snapshot(system: SessionParts, stored_chunks: Mapping[int, int] | None = None) -> SnapshotFuture:
    """A snapshot of `system` as of now, without waiting (see SlamSystem.begin_snapshot)."""
    traj = system.tracking_stage.trajectory
    trajectory, chunks = (None, None) if stored_chunks is None else traj.chunked_state(stored_chunks)
    arrays = None if chunks is None else chunks.arrays
    tracking = pack(tracking_state(system, trajectory), external=arrays)
    mapping, loop_stage = system.mapping_stage, system.loop_stage
    parts = ["loop"] + ([] if mapping is None else ["map"])
    future = SnapshotFuture(parts, lambda done: pack({"format": SNAPSHOT_FORMAT, "tracking": tracking,
                                                      "map": done.get("map"), "loop": done["loop"]}))
    if mapping is not None:  # at once: the map between two refinement steps, its backlog as data
        mapping.snapshot_now(lambda make: future.deliver("map", make), external=arrays)
    loop_stage.snapshot_now(lambda make: future.deliver("loop", make), external=arrays)
    future.chunks = chunks
    return future


def tracking_state(system: SessionParts, trajectory: dict[str, Any] | None = None) -> dict[str, Any]:
    """The tracking thread's part (`trajectory`: the trajectory's chunked state)."""
    learned = system.learned
    return {
        "format": SNAPSHOT_FORMAT,
        "config": system.config.model_dump(mode="json"),
        "model_id": system.model_id,
        "intrinsics": None if system.intrinsics is None else system.intrinsics.to_dict(),
        "model_intrinsics": None if system.model_intrinsics is None else system.model_intrinsics.to_dict(),
        "mode": system.mode,
        "tracking": system.tracking,
        "with_depth": system.with_depth,
        "frame_size": None if system.camera.frame_size is None else list(system.camera.frame_size),
        "counters": dict(system.counters),
        **system.tracking_stage.state_dict(trajectory),
        "tracker": None if learned is None else learned.tracker.state_dict(),
        "bag": None if learned is None else learned.bag.to_bytes(torch.float32),
        "judged_frames": system.judged_start.state_dict(),
    }


def restore(cls: type, data: bytes, chunks: Mapping[int | str, bytes] | None = None, in_map: Any = None) -> Any:
    """A system of class `cls` (worker.slam.SlamSystem) continuing from snapshot bytes (see its `restore`), in the
    stored map `in_map` (worker.maps.SessionInMap) when it runs in one."""
    from worker.config import SlamConfig
    from worker.loop.bag import HiddenStateBag
    from worker.pipeline.assembly import TRACKING_OF_MODE

    chunks = chunks or {}
    state = flat_snapshot(unpack(data), {k: v for k, v in chunks.items() if isinstance(k, str)})
    state["trajectory"] = Trajectory.joined_state(state["trajectory"],
                                                  {k: v for k, v in chunks.items() if isinstance(k, int)})
    config = SlamConfig.from_dict(state["config"])
    intrinsics = None if state["intrinsics"] is None else Intrinsics.from_dict(state["intrinsics"])
    system = cls(config, intrinsics, in_map=in_map)
    if state["mode"] is not None:
        system.setup(state.get("tracking") or TRACKING_OF_MODE[state["mode"]], with_depth=bool(state["with_depth"]))
    if system.model_id != state["model_id"]:
        raise ValueError(f"the snapshot was made with model {state['model_id']!r}, this machine has "
                         f"{system.model_id!r}")
    learned = system.learned
    if state["model_intrinsics"] is not None and learned is not None:
        learned.tracking.model_intrinsics = Intrinsics.from_dict(state["model_intrinsics"])
    system.camera.frame_size = None if state["frame_size"] is None else tuple(state["frame_size"])
    system.counters.update({k: v for k, v in state["counters"].items() if k not in ("path_given", "path_tracked")})
    system.wall_offset = float(system.counters["wall_seconds"])
    system.tracking_stage.load_state_dict(state)
    if learned is not None:
        learned.tracker.load_state_dict(state["tracker"])
        learned.bag = HiddenStateBag.from_bytes(state["bag"])
        learned.tracking.bag = learned.bag
        if system.loop_closer is not None and system.loop_closer.pnp is None:
            system.loop_closer.relocalizer.bag = learned.bag
    system.loop_stage.load_state_dict(state)
    _load_earlier_versions(system, state)
    system.judged_start.load_state_dict(state.get("judged_frames"))
    if system.mapping_stage is not None and state["map"] is not None:
        system.mapping_stage.load_state_dict(state["map"])
    return system


def _load_earlier_versions(system: SessionParts, state: dict[str, Any]) -> None:
    """What snapshots of earlier versions kept elsewhere: the multi-view frame ring and its waiting keyframes
    (`keyframe_depth`), keyframes whose loop query waited for their depth (`loop_after_depth`; format 1's
    `loops_waiting`, with the depth when it was built: their queries go to the stage now), the model's path."""
    source = system.tracking_stage.depth_source
    waiting_loops = {int(k) for k in state.get("loop_after_depth") or []}
    old = state.get("keyframe_depth")
    if isinstance(source, MultiViewDepth) and old is not None and state.get("depth_source") is None:
        source.load_state_dict({**old, "pending": [{**p, "query_loops": int(p["kf_id"]) in waiting_loops}
                                                   for p in old["pending"]]})
        if source.builder is not None:
            source.builder.load_state_dict(old)
    if isinstance(source, ModelSurfels) and state.get("depth_source") is None:
        counters = state["counters"]
        source.load_state_dict({"path": [counters.get("path_given", 0.0), counters.get("path_tracked", 0.0)],
                                "previous_poses": state.get("previous_poses")})
    for e in state.get("loops_waiting") or []:
        if e["depth"] is None:
            continue  # its depth is built again from the ring: a format-1 ring has no flag, the query is lost
        image = torch.from_numpy(np.asarray(e["image"], np.uint8)).to(torch.float32) / 255.0
        K = torch.from_numpy(np.asarray(e["K"], np.float32))
        h, w = image.shape[:2]
        system.loop_stage.submit(LoopQuery(int(e["kf"]), image.permute(2, 0, 1)[None], Intrinsics.from_matrix(
            K, w, h), torch.from_numpy(np.asarray(e["depth"], np.float32)), K))


def flat_snapshot(state: Any, arrays: Mapping[str, bytes] | None = None) -> dict[str, Any]:
    """A snapshot's state as one dict of format 1's keys (format 2 keeps the stages' parts packed apart; `arrays`:
    the large arrays an incremental snapshot keeps outside, by digest)."""
    if not isinstance(state, dict) or state.get("format") not in SNAPSHOT_FORMATS:
        raise ValueError("not a Flash-Mono SLAM snapshot")
    if state["format"] != SNAPSHOT_FORMAT:
        return state
    arrays = arrays or {}
    flat = {**unpack(state["tracking"], external=arrays), **unpack(state["loop"], external=arrays)}
    flat["map"] = None if state["map"] is None else unpack(state["map"], external=arrays)
    return flat
