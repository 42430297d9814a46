"""The one interface the runtime drives: a per-session SLAM engine.

`create_engine(kind, preset, intrinsics)` and `restore_engine(kind, blob)` build engines of two kinds:
- "slam": the real `worker.slam.SlamSystem` (the default).
- "passthrough": a tiny deterministic engine that tracks nothing (it reports the frame's own pose, or identity)
  and renders a flat image. It exists to test the runtime's delivery guarantees quickly and to measure the
  service's own per-frame overhead without the engine's compute; it is never the default.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from protocol.codec import pack, unpack
from worker.data.frame import Frame, FrameResult
from worker.geometry import Intrinsics
from worker.pipeline.snapshot_chunks import ChunkWrite, chunk_versions
from worker.settings_choice import MAPPING_PROCESS_CORES, Machine, SessionInput, choose_settings

log = logging.getLogger(__name__)

ENGINE_KINDS = ("slam", "passthrough")


class SessionEngine(Protocol):
    """What the runtime needs from an engine (the SlamSystem contract)."""

    revision: int

    def push(self, frame: Frame) -> FrameResult: ...

    def finish(self) -> None: ...

    def trajectory(self, which: str = "all") -> list[tuple[int, float, np.ndarray]]: ...

    def render_view(self, pose_c2w: np.ndarray, K: np.ndarray, width: int, height: int,
                    as_captured_at: int | None = None) -> tuple[np.ndarray, np.ndarray]: ...

    def export_ply(self) -> bytes: ...

    def snapshot(self) -> bytes: ...


def create_engine(kind: str, preset: str | None, intrinsics: Intrinsics | None,
                  pose_mode: str | None = None, tracking_side: int | None = None,
                  depth_camera: dict[str, Any] | None = None,
                  overrides: dict[str, Any] | None = None, in_map: Any = None) -> SessionEngine:
    """A fresh engine of `kind` for a new session. `preset` None: the settings `choose_settings` picks for an input
    not known yet on this machine; `overrides` (a settings choice's) are merged into the preset; `pose_mode`
    (prior/fixed/ignore/seeded) and `tracking_side` (the tracking resolution's long side) override both;
    `depth_camera` (the session's: intrinsics + depth_to_color) registers depth to the colour camera; `in_map`
    (worker.maps.SessionInMap) the stored map the session runs in."""
    if kind == "slam":
        from worker.config import deep_merge
        from worker.slam import SlamConfig, SlamSystem

        if preset is None:
            choice = choose_settings(SessionInput(), Machine.detect())
            preset, overrides = choice.preset, deep_merge(choice.engine_overrides(), overrides or {})
        merged: dict[str, Any] = deep_merge(overrides or {}, {})
        merged.setdefault("input", {})
        if pose_mode:
            merged["input"]["pose_mode"] = pose_mode
        if tracking_side:
            merged.setdefault("tracking", {})["max_side"] = int(tracking_side)
        if depth_camera:
            merged["input"]["depth_camera"] = {**depth_camera["intrinsics"],
                                               "depth_to_color": depth_camera["depth_to_color"]}
        return SlamSystem(SlamConfig.preset(preset, **merged), intrinsics=intrinsics, in_map=in_map)
    if kind == "passthrough":
        return PassthroughEngine(intrinsics=intrinsics, delay_s=_passthrough_delay_s(),
                                 finish_delay_s=_passthrough_finish_delay_s())
    raise ValueError(f"unknown engine kind {kind!r}; expected one of {ENGINE_KINDS}")


def _passthrough_delay_s() -> float:
    """FLASHMONO_PASSTHROUGH_DELAY_MS: simulated compute per frame (tests that need a worker busy mid-stream)."""
    return float(os.environ.get("FLASHMONO_PASSTHROUGH_DELAY_MS", "0")) / 1000.0


def _passthrough_finish_delay_s() -> float:
    """FLASHMONO_PASSTHROUGH_FINISH_MS: simulated final refinement (tests of requests while a session finishes)."""
    return float(os.environ.get("FLASHMONO_PASSTHROUGH_FINISH_MS", "0")) / 1000.0


def restore_engine(kind: str, blob: bytes, chunks: Mapping[int | str, bytes] | None = None,
                   in_map: Any = None) -> SessionEngine:
    """An engine rebuilt from `snapshot()` bytes (and, for a chunked snapshot, the `chunks` it lists), in the
    stored map `in_map` when the session runs in one."""
    if kind == "slam":
        from worker.slam import SlamSystem

        return SlamSystem.restore(blob, chunks, in_map=in_map)
    if kind == "passthrough":
        engine = PassthroughEngine.restore(blob, chunks)
        engine.delay_s, engine.finish_delay_s = _passthrough_delay_s(), _passthrough_finish_delay_s()
        return engine
    raise ValueError(f"unknown engine kind {kind!r}; expected one of {ENGINE_KINDS}")


def warm_up(kind: str) -> None:
    """Load what an engine of `kind` needs on its first session (the SLAM system, its pose sources, stages, the
    compiled kernels, and the optimiser, whose first use imports torch's compiler stack for ~2 s while holding the
    GIL), so that neither a new session's first frames nor a worker taking over a dead worker's session pay for it
    then (measured live: RGB only at 30 frames/s skipped 31 of its first 60 frames while these loaded)."""
    if kind != "slam":
        return
    import importlib

    import torch

    for module in ("worker.slam", "worker.tracking.rgbd_odometry", "worker.tracking.visual_odometry",
                   "worker.pipeline.mapping_stage", "worker.pipeline.loop_stage", "worker.pipeline.loop_closer",
                   "worker.pipeline.depth_sources.multiview", "worker.loop.pose_graph"):
        importlib.import_module(module)
    for kernels in ("worker.mapping.raster_cpu", "worker.depth.mvs_cpu", "worker.tracking.dense_native",
                    "worker.tracking.schur_native"):
        importlib.import_module(kernels).available()  # compiles on a fresh machine, else loads the cached library
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    machine = Machine.detect()
    if not machine.cuda and machine.cpu_cores >= MAPPING_PROCESS_CORES:  # RGB-only sessions map in processes
        from worker.pipeline.mapping_process.launcher import prestart

        if not prestart():  # sessions still start their mapping processes; the first may wait for the server
            log.warning("the mapping processes' fork server did not answer its start-up probe")


def engine_intrinsics(engine: SessionEngine) -> dict[str, float | int] | None:
    """The camera the engine uses at the frames' resolution (its `estimated_intrinsics()`: given or estimated),
    as {fx, fy, cx, cy, width, height}; None while unknown or when the engine cannot tell."""
    estimate = getattr(engine, "estimated_intrinsics", None)
    camera = estimate() if estimate is not None else None
    return camera.to_dict() if camera is not None else None


def close_engine(engine: SessionEngine | None) -> None:
    """Stop an engine's background threads, if it has any (SlamSystem.close)."""
    close = getattr(engine, "close", None)
    if close is not None:
        close()


class PassthroughEngine:
    """Deterministic engine without tracking: pose = the frame's pose (or identity), every 4th frame a keyframe."""

    KEYFRAME_EVERY = 4
    CHUNK_POSES = 8  # small, so that the runtime's tests cross chunk boundaries

    def __init__(self, intrinsics: Intrinsics | None = None, delay_s: float = 0.0, finish_delay_s: float = 0.0
                 ) -> None:
        self.intrinsics = intrinsics
        self.finish_delay_s = finish_delay_s
        self.delay_s = delay_s
        self.revision = 0
        self._poses: list[tuple[int, float, np.ndarray, bool]] = []
        self._colors: list[np.ndarray] = []
        self._first_camera: Intrinsics | None = None
        self.finished = False

    def push(self, frame: Frame) -> FrameResult:
        if self.finished:
            raise RuntimeError("push after finish")
        if self.delay_s:
            time.sleep(self.delay_s)
        pose = np.eye(4) if frame.pose is None else np.asarray(frame.pose, dtype=np.float64)
        self._first_camera = self._first_camera or frame.intrinsics
        is_keyframe = len(self._poses) % self.KEYFRAME_EVERY == 0
        self._poses.append((frame.index, frame.timestamp, pose, is_keyframe))
        if is_keyframe:
            self._colors.append(frame.image.reshape(-1, 3).mean(axis=0))
        return FrameResult(index=frame.index, timestamp=frame.timestamp, pose=pose, is_keyframe=is_keyframe,
                           submap_id=len(self._poses) // 8, revision=self.revision)

    def finish(self) -> None:
        if self.finish_delay_s:
            time.sleep(self.finish_delay_s)
        self.finished = True

    def estimated_intrinsics(self) -> Intrinsics | None:
        """The given camera, else the first frame's own (no estimation here)."""
        return self.intrinsics or self._first_camera

    def trajectory(self, which: str = "all") -> list[tuple[int, float, np.ndarray]]:
        if which not in ("all", "keyframes"):
            raise ValueError("which must be 'all' or 'keyframes'")
        return [(i, t, p) for i, t, p, kf in self._poses if which == "all" or kf]

    def render_view(self, pose_c2w: np.ndarray, K: np.ndarray, width: int, height: int,
                    as_captured_at: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        mean = np.mean(self._colors, axis=0) if self._colors else np.zeros(3)
        rgb = np.broadcast_to(mean.astype(np.uint8), (height, width, 3)).copy()
        depth = np.full((height, width), 1.0 + float(np.linalg.norm(pose_c2w[:3, 3])), dtype=np.float32)
        return rgb, depth

    def export_ply(self) -> bytes:
        centres = [p[:3, 3] for _, _, p, _ in self._poses]
        lines = ["ply", "format ascii 1.0", f"element vertex {len(centres)}", "property float x",
                 "property float y", "property float z", "end_header"]
        lines += [f"{c[0]:.6f} {c[1]:.6f} {c[2]:.6f}" for c in centres]
        return ("\n".join(lines) + "\n").encode()

    def snapshot(self) -> bytes:
        return pack(self._state(self._poses))

    def begin_snapshot(self, stored_chunks: Mapping[int, int]) -> ReadySnapshot:
        """A chunked snapshot (as SlamSystem's): runs of `CHUNK_POSES` poses are sealed into chunks written once."""
        sealed = len(self._poses) // self.CHUNK_POSES
        size = self.CHUNK_POSES
        new = {i: pack({"chunk": i, "version": 0, "poses": self._rows(self._poses[i * size:(i + 1) * size])})
               for i in range(sealed) if stored_chunks.get(i) != 0}
        manifest = {"frames": size, "sealed": sealed, "versions": {}}
        blob = pack({**self._state(self._poses[sealed * size:]), "chunks": manifest})
        return ReadySnapshot(blob, ChunkWrite(manifest, new))

    def _state(self, poses: list[tuple[int, float, np.ndarray, bool]]) -> dict[str, Any]:
        return {"intrinsics": self.intrinsics.to_dict() if self.intrinsics else None, "revision": self.revision,
                "finished": self.finished, "colors": [c for c in self._colors], "poses": self._rows(poses)}

    @staticmethod
    def _rows(poses: list[tuple[int, float, np.ndarray, bool]]) -> list[list[Any]]:
        return [[i, t, p, kf] for i, t, p, kf in poses]

    @classmethod
    def restore(cls, blob: bytes, chunks: Mapping[int, bytes] | None = None) -> PassthroughEngine:
        state: dict[str, Any] = unpack(blob)
        engine = cls(Intrinsics.from_dict(state["intrinsics"]) if state["intrinsics"] else None)
        engine.revision = int(state["revision"])
        engine.finished = bool(state["finished"])
        engine._colors = list(state["colors"])
        rows = []
        for i in chunk_versions(state["chunks"]) if state.get("chunks") else []:
            if chunks is None or i not in chunks:
                raise ValueError(f"the snapshot needs pose chunk {i}, which is missing")
            rows += unpack(chunks[i])["poses"]
        engine._poses = [(int(i), float(t), np.asarray(p), bool(kf)) for i, t, p, kf in rows + state["poses"]]
        return engine


class ReadySnapshot:
    """A snapshot that is complete at once (the SnapshotFuture interface, for engines without stages)."""

    def __init__(self, blob: bytes, chunks: ChunkWrite | None = None) -> None:
        self._blob = blob
        self.chunks = chunks

    def done(self) -> bool:
        return True

    def result(self, timeout: float | None = None) -> bytes:
        return self._blob
