"""The SLAM system: one object per session, frame in -> pose out, with a 2DGS map behind it.

Two threads as in the paper (appendix E): the caller's thread is the frontend (model step, submaps, keyframes,
loop detection, relocalization, PGO) and a backend thread maps keyframes (voxelize, prune, fuse, refine, loop
correction); a bounded queue joins them. `SlamConfig.threaded=False` runs the backend inline: deterministic.

Input modes, picked from the first frame:
- monocular: the feed-forward model tracks submaps (worker.frontend.tracker) and predicts the surfels;
- posed (frames carry `pose` and `input.pose_mode != "ignore"`): the given poses are the odometry, used as priors
  in the pose graph ("prior", loop closures can still correct them) or kept as they are ("fixed");
- RGB-D (frames carry `depth`, `input.use_depth`): surfel means from the unprojected depth, the other attributes
  from the model or, with `input.surfel_init="depth"`, initialised from the image and depth alone.

`snapshot()` writes everything needed to continue (config, model id, tracker, bag of hidden states, pose graph,
trajectory, map, counters) as msgpack; `SlamSystem.restore(data)` continues from it in any process.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import torch

from worker.config import SlamConfig
from worker.data.frame import Frame, FrameResult
from worker.engine.backend import KeyframeJob, MapBackend, PoseUpdateJob
from worker.engine.keyframes import MotionKeyframeSelector
from worker.engine.surfel_init import grid_from_depth
from worker.engine.trajectory import Trajectory
from worker.geometry import Intrinsics, sim3_inverse
from worker.loop.pose_graph import EdgeSigmas, Sim3PoseGraph
from worker.serialization import pack, unpack

log = logging.getLogger(__name__)

SNAPSHOT_FORMAT = "flashmono.slam/1"


def _w2c(pose_c2w: np.ndarray | torch.Tensor) -> torch.Tensor:
    return sim3_inverse(torch.as_tensor(np.asarray(pose_c2w, np.float64))).to(torch.float32)


class SlamSystem:
    """Monocular / posed / RGB-D 2DGS SLAM over a stream of `Frame`s (see the module docstring)."""

    def __init__(self, config: SlamConfig | None = None, intrinsics: Intrinsics | None = None) -> None:
        self.config = config if config is not None else SlamConfig.preset("default")
        if not isinstance(self.config, SlamConfig):
            raise ValueError(f"config must be a SlamConfig, got {type(self.config).__name__}")
        torch.set_num_threads(self.config.num_threads)
        self.intrinsics = intrinsics
        self.mode: str | None = None  # "posed" or "monocular", set by the first frame
        self._traj = Trajectory()
        self.pose_graph = self._new_pose_graph()
        self.selector = MotionKeyframeSelector(self.config.frontend.keyframe_every,
                                               self.config.frontend.keyframe_translation,
                                               self.config.frontend.keyframe_rotation_deg)
        self.backend = (MapBackend(self.config.mapping, self.config.threaded, self.config.queue_size,
                                   self.config.device) if self.config.mapping.enabled else None)
        self.counters: dict[str, float] = {"frames": 0, "keyframes": 0, "loops": 0, "frontend_seconds": 0.0,
                                           "wall_seconds": 0.0}
        self._last_keyframe: int | None = None
        self._submap_of: dict[int, int] = {}
        self._frame_size: tuple[int, int] | None = None
        self._keyframe_images: dict[int, np.ndarray] = {}
        self._finished = False
        self._model = None
        self._tracker = None
        self._loop = None
        self._started: float | None = None

    # ------------------------------------------------------------------------------------------------ public API
    @property
    def revision(self) -> int:
        """The trajectory revision: grows each time a loop closure rewrites past poses."""
        return self._traj.revision

    @property
    def num_gaussians(self) -> int:
        return 0 if self.backend is None else self.backend.num_gaussians()

    def push(self, frame: Frame) -> FrameResult:
        """Track one frame (and queue its keyframe for mapping); returns its pose and events."""
        if self._finished:
            raise ValueError("this SLAM session is finished; start a new one")
        if not isinstance(frame, Frame):
            raise ValueError(f"push() takes a worker.data.Frame, got {type(frame).__name__}")
        if self.backend is not None:
            self.backend.raise_if_failed()
        start = time.perf_counter()
        self._started = self._started or start
        self._check_frame(frame)
        if self.mode == "posed":
            result = self._push_posed(frame)
        else:
            result = self._push_monocular(frame)
        self.counters["frames"] += 1
        self.counters["frontend_seconds"] += time.perf_counter() - start
        self.counters["wall_seconds"] = time.perf_counter() - self._started
        return result

    def finish(self) -> None:
        """Wait for the backend to map every keyframe, run the final refinement, stop the backend thread."""
        if self._finished:
            return
        if self.backend is not None:
            self.backend.wait_idle()
            if self.config.mapping.final_refine_iterations:
                self.backend.refine_all(self.config.mapping.final_refine_iterations)
            self.backend.close()
        if self._started is not None:
            self.counters["wall_seconds"] = time.perf_counter() - self._started
        self._finished = True

    def close(self) -> None:
        """Stop the backend thread without further work (idempotent)."""
        if self.backend is not None:
            self.backend.close()

    def trajectory(self, which: str = "all") -> list[tuple[int, float, np.ndarray]]:
        """[(index, timestamp, c2w pose 4x4)] of "all" frames or the "keyframes", at the current revision."""
        return self._traj.listing(which)

    def render_view(self, pose_c2w: np.ndarray, K: np.ndarray | torch.Tensor, width: int, height: int
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Render the map: (rgb uint8 [h,w,3], depth float32 [h,w]) seen from c2w `pose_c2w` with intrinsics K."""
        if self.backend is None:
            raise ValueError("mapping is disabled in this session's config")
        pose = np.asarray(pose_c2w, np.float64)
        Km = torch.as_tensor(np.asarray(K, np.float64), dtype=torch.float32)
        if pose.shape != (4, 4) or tuple(Km.shape) != (3, 3):
            raise ValueError("render_view needs a 4x4 pose and a 3x3 K")
        if not (0 < width <= 8192 and 0 < height <= 8192):
            raise ValueError(f"render size must be within 1..8192, got {width}x{height}")
        out = self.backend.render(pose, Km, int(width), int(height))
        rgb = (out.rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        return rgb, out.depth.to(torch.float32).cpu().numpy()

    def export_ply(self) -> bytes:
        """The map as a binary PLY (3DGS/2DGS layout)."""
        if self.backend is None:
            raise ValueError("mapping is disabled in this session's config")
        return self.backend.to_ply_bytes()

    def stats(self) -> dict[str, Any]:
        """Counters for status pages and metrics."""
        frames = self.counters["frames"]
        wall = self.counters["wall_seconds"]
        return {**self.counters, "revision": self.revision, "mode": self.mode,
                "num_gaussians": self.num_gaussians, "fps": frames / wall if wall > 0 else 0.0,
                "backend_pending": 0 if self.backend is None else self.backend.pending,
                "backend_seconds": 0.0 if self.backend is None else self.backend.busy_seconds}

    # ------------------------------------------------------------------------------------------------- helpers
    def _new_pose_graph(self) -> Sim3PoseGraph:
        lc = self.config.loop
        return Sim3PoseGraph(robust=None if lc.robust_kernel == "none" else lc.robust_kernel, robust_k=lc.robust_k,
                             sigmas={"loop": EdgeSigmas(0.02, 0.04, 0.02)})

    def _check_frame(self, frame: Frame) -> None:
        size = (frame.width, frame.height)
        if self._frame_size is None:
            self._frame_size = size
            posed = frame.pose is not None and self.config.input.pose_mode != "ignore"
            self.mode = "posed" if posed else "monocular"
        elif size != self._frame_size:
            raise ValueError(f"frame {frame.index} is {size[0]}x{size[1]}, the session's frames are "
                             f"{self._frame_size[0]}x{self._frame_size[1]}")
        if self.mode == "posed" and frame.pose is None:
            raise ValueError(f"frame {frame.index} has no pose, but this session runs in posed mode")

    def frame_intrinsics(self, frame: Frame) -> Intrinsics | None:
        """The frame's camera: its own intrinsics, else the session's (rescaled to the frame size)."""
        if frame.intrinsics is not None:
            return frame.intrinsics
        if self.intrinsics is None:
            return None
        if (self.intrinsics.width, self.intrinsics.height) != (frame.width, frame.height):
            return self.intrinsics.scaled(frame.width, frame.height)
        return self.intrinsics

    def _uses_depth(self, frame: Frame) -> bool:
        return frame.depth is not None and self.config.input.use_depth

    # --------------------------------------------------------------------------------------------- posed mode
    def _push_posed(self, frame: Frame) -> FrameResult:
        pose = np.asarray(frame.pose, np.float64)
        events: list[dict[str, Any]] = []
        is_kf = self.selector.is_keyframe(pose)
        if is_kf:
            self._add_keyframe(frame.index, pose, submap_id=0)
            events += self._close_loops_posed(frame)
        world = self._traj.add_frame(frame.index, frame.timestamp, self._last_keyframe, pose, is_kf, 0)
        if is_kf and self.backend is not None:
            self.backend.submit(self._posed_keyframe_job(frame, self._traj.keyframe_poses[frame.index]))
        return FrameResult(frame.index, frame.timestamp, world, is_kf, 0, self.revision, events)

    def _add_keyframe(self, kf_id: int, tracked_pose: np.ndarray, submap_id: int) -> np.ndarray:
        """Insert a keyframe in the trajectory and the pose graph (odometry edge from the previous keyframe)."""
        previous = self._last_keyframe
        world = self._traj.add_keyframe(kf_id, tracked_pose, reference=previous)
        self.pose_graph.add_node(kf_id, world)
        if previous is not None:
            rel = sim3_inverse(torch.from_numpy(self._traj.tracked_keyframe_poses[previous])) @ torch.from_numpy(
                np.asarray(tracked_pose, np.float64))
            kind = "sequential" if self._submap_of.get(previous, submap_id) == submap_id else "inter_submap"
            self.pose_graph.add_edge(previous, kf_id, rel.numpy(), kind=kind)
        self._submap_of[kf_id] = submap_id
        self._last_keyframe = kf_id
        self.counters["keyframes"] += 1
        return world

    def _posed_keyframe_job(self, frame: Frame, world_pose: np.ndarray) -> KeyframeJob:
        K_intr = self.frame_intrinsics(frame)
        if K_intr is None:
            raise ValueError("posed mapping needs intrinsics: give them with the frames or to SlamSystem()")
        image = torch.from_numpy(frame.image).to(torch.float32) / 255.0
        K = K_intr.matrix()
        depth = torch.from_numpy(np.asarray(frame.depth, np.float32)) if self._uses_depth(frame) else None
        if depth is None:
            grid = self._model_grid(frame, K_intr, depth=None)
        elif self.config.input.surfel_init == "depth":
            grid = grid_from_depth(image, depth, K)
        else:
            grid = self._model_grid(frame, K_intr, depth=depth)
        return KeyframeJob(frame.index, world_pose, K, image, grid, depth)

    def _close_loops_posed(self, frame: Frame) -> list[dict[str, Any]]:
        if self.config.input.pose_mode == "fixed" or not self.config.loop.enabled:
            return []
        return self._detect_and_close(frame)

    # ----------------------------------------------------------------------------------------- monocular mode
    def _push_monocular(self, frame: Frame) -> FrameResult:
        raise NotImplementedError("monocular tracking is integrated once worker.frontend.tracker lands")

    def _model_grid(self, frame: Frame, K: Intrinsics, depth: torch.Tensor | None) -> dict[str, torch.Tensor]:
        raise NotImplementedError("model-predicted surfels are integrated once worker.frontend lands")

    # ------------------------------------------------------------------------------------------ loop closure
    def _detect_and_close(self, frame: Frame) -> list[dict[str, Any]]:
        return []

    def _apply_pgo(self, loop_from: int, loop_to: int) -> dict[str, Any]:
        """Optimise the pose graph, move the trajectory and the map; returns the loop event."""
        old = {k: v.copy() for k, v in self._traj.keyframe_poses.items()}
        result = self.pose_graph.optimize(max_iterations=self.config.loop.pgo_iterations)
        revision = self._traj.update_keyframes(result.poses)
        if self.backend is not None:
            changed = {k: p for k, p in result.poses.items() if not np.allclose(p, old[k], atol=1e-9)}
            self.backend.submit(PoseUpdateJob(changed))
        self.counters["loops"] += 1
        return {"type": "loop_closed", "revision": revision, "from_keyframe": int(loop_from),
                "to_keyframe": int(loop_to), "pgo_error_before": result.initial_error,
                "pgo_error_after": result.final_error}

    # ---------------------------------------------------------------------------------------- snapshot/restore
    def snapshot(self) -> bytes:
        """Everything needed to continue this session, as msgpack bytes (waits for the backend to be idle)."""
        if self.backend is not None:
            self.backend.wait_idle()
        state = {
            "format": SNAPSHOT_FORMAT,
            "config": self.config.model_dump(mode="json"),
            "intrinsics": None if self.intrinsics is None else self.intrinsics.to_dict(),
            "mode": self.mode,
            "frame_size": None if self._frame_size is None else list(self._frame_size),
            "last_keyframe": self._last_keyframe,
            "submap_of": [[k, v] for k, v in self._submap_of.items()],
            "counters": dict(self.counters),
            "trajectory": self._traj.state_dict(),
            "pose_graph": self.pose_graph.state_dict(),
            "selector": self.selector.state_dict(),
            "map": None if self.backend is None else self.backend.state_dict(),
        }
        return pack(state)

    @classmethod
    def restore(cls, data: bytes) -> SlamSystem:
        """A system continuing from `snapshot()` bytes (never unpickles anything)."""
        state = unpack(data)
        if not isinstance(state, dict) or state.get("format") != SNAPSHOT_FORMAT:
            raise ValueError("not a Flash-Mono SLAM snapshot")
        config = SlamConfig.from_dict(state["config"])
        intrinsics = None if state["intrinsics"] is None else Intrinsics.from_dict(state["intrinsics"])
        system = cls(config, intrinsics)
        system.mode = state["mode"]
        system._frame_size = None if state["frame_size"] is None else tuple(state["frame_size"])
        system._last_keyframe = state["last_keyframe"]
        system._submap_of = {int(k): int(v) for k, v in state["submap_of"]}
        system.counters.update(state["counters"])
        system._traj.load_state_dict(state["trajectory"])
        system.pose_graph.load_state_dict(state["pose_graph"])
        system.selector.load_state_dict(state["selector"])
        if system.backend is not None and state["map"] is not None:
            system.backend.load_state_dict(state["map"])
        return system
