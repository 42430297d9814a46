"""The backend mapping thread (paper 4.3): voxelize -> prune -> fuse -> refine per keyframe, loop correction.

`MapBackend` owns the `GaussianMap`. The frontend submits keyframe jobs and pose updates through a bounded queue
(a full queue blocks the frontend: backpressure instead of unbounded memory); with `threaded=False` every job runs
inline in the caller, which makes runs deterministic. All map access goes through one lock, so renders and exports
from other threads see a map between two refinement steps, never in the middle of one.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from worker.config import MappingConfig
from worker.engine.stage_times import StageTimes
from worker.mapping.voxelize import voxelize

log = logging.getLogger(__name__)


@dataclass
class KeyframeJob:
    """One keyframe for the map: pose c2w (Sim(3)), K at the grid's resolution, image float [H,W,3] in [0,1],
    the per-pixel camera-frame surfel grid (see worker.engine.surfel_init) and the depth used to check renders, or
    `build`, which makes both in the backend thread."""

    kf_id: int
    pose: np.ndarray
    K: torch.Tensor | None  # None until `build` has run
    image: torch.Tensor
    grid: dict[str, torch.Tensor]
    depth: torch.Tensor | None = None
    # Builds (K, grid, depth) in the backend thread: costly ones (multi-view depth), or ones that need what is
    # known only later (the camera of a session whose focal length is being estimated).
    build: Callable[[], tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor | None]] | None = None


@dataclass
class PoseUpdateJob:
    poses: dict[int, np.ndarray]


_STOP = object()


def build_gaussian_map(cfg: MappingConfig, device: str):
    """The map object with this engine's mapping settings."""
    from worker.mapping.fusion import FusionThresholds
    from worker.mapping.gaussian_map import GaussianMap, MapConfig
    from worker.mapping.refine import RefineSettings

    return GaussianMap(MapConfig(
        window=cfg.refine_keyframes,
        iterations=cfg.refine_iterations,
        thresholds=FusionThresholds(rgb_error=cfg.prune_rgb_error if cfg.prune else math.inf,
                                    depth_error=cfg.prune_depth_error if cfg.prune else math.inf,
                                    tau_accum=cfg.tau_accum),
        refine=RefineSettings(lambda_ssim=cfg.ssim_weight, lambda_depth=cfg.depth_weight),
        archived_images=cfg.archived_images,
        archived_views_per_refine=cfg.archived_views_per_refine,
        device=device,
    ))


class MapBackend:
    """Runs map jobs in its own thread (or inline) and serves renders/exports under a lock."""

    def __init__(self, cfg: MappingConfig, threaded: bool, queue_size: int, device: str = "cpu",
                 timings: StageTimes | None = None) -> None:
        self.cfg = cfg
        self.timings = timings or StageTimes()
        self.device = device
        self.map = build_gaussian_map(cfg, device)
        self.lock = threading.RLock()
        self.keyframes_mapped = 0
        self.busy_seconds = 0.0
        self._error: BaseException | None = None
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self._queue = queue.Queue(maxsize=queue_size)
            self._thread = threading.Thread(target=self._run, name="slam-backend", daemon=True)
            self._thread.start()

    # -- submission -------------------------------------------------------------------------------------------
    def submit(self, job: KeyframeJob | PoseUpdateJob) -> None:
        """Queue a job (blocks while the queue is full); inline when not threaded."""
        self.raise_if_failed()
        if self._queue is None:
            self._process(job)
        else:
            self._queue.put(job)

    def wait_idle(self) -> None:
        """Block until every submitted job is done."""
        if self._queue is not None:
            self._queue.join()
        self.raise_if_failed()

    def close(self) -> None:
        if self._queue is not None and self._thread is not None and self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join()
        self._queue = None

    @property
    def pending(self) -> int:
        return 0 if self._queue is None else self._queue.qsize()

    def raise_if_failed(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the mapping backend failed: {self._error!r}") from self._error

    # -- work ---------------------------------------------------------------------------------------------------
    def _run(self) -> None:
        assert self._queue is not None
        while True:
            job = self._queue.get()
            try:
                if job is _STOP:
                    return
                if self._error is None:
                    self._process(job)
            except BaseException as err:  # noqa: BLE001 - reported to the frontend on its next call
                log.exception("backend job failed")
                self._error = err
            finally:
                self._queue.task_done()

    def _process(self, job: KeyframeJob | PoseUpdateJob) -> None:
        start = time.perf_counter()
        if isinstance(job, KeyframeJob) and job.build is not None:  # outside the lock: renders go on meanwhile
            with self.timings.measure("map_depth"):
                job.K, job.grid, job.depth = job.build()
            job.build = None
        with self.lock:
            if isinstance(job, KeyframeJob):
                self._map_keyframe(job)
            else:
                with self.timings.measure("map_loop_correction"):
                    self.map.apply_pose_updates({k: torch.as_tensor(v) for k, v in job.poses.items()})
        self.busy_seconds += time.perf_counter() - start

    def _map_keyframe(self, job: KeyframeJob) -> None:
        g = job.grid
        with self.timings.measure("map_merge"):
            vox = voxelize(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], valid=g["valid"],
                           tau_d=self.cfg.tau_depth, keyframe_id=job.kf_id,
                           merged_scale_factor=self.cfg.merged_scale_factor
                           ) if self.cfg.voxel_block > 1 else _unmerged(g, job.kf_id)
            self.map.add_keyframe(job.kf_id, torch.as_tensor(job.pose), job.K, job.image, vox.surfels,
                                  depth=job.depth)
        if self.cfg.refine_iterations > 0:
            with self.timings.measure("map_refine"):
                self.map.refine(self.cfg.refine_iterations)
        self.keyframes_mapped += 1

    def refine_all(self, passes: int) -> None:
        """The end-of-run refinement: every surfel against every keyframe image the map still holds, `passes`
        times over those keyframes."""
        with self.lock, self.timings.measure("map_final_refine"):
            self.map.refine_global(passes * self.map.held_images)

    # -- reads -----------------------------------------------------------------------------------------------------
    def render(self, pose_c2w: np.ndarray, K: torch.Tensor, width: int, height: int) -> Any:
        with self.lock, torch.no_grad():
            return self.map.render(torch.as_tensor(pose_c2w), K, width, height)

    def num_gaussians(self) -> int:
        with self.lock:
            return int(self.map.num_gaussians)

    def to_ply_bytes(self) -> bytes:
        with self.lock:
            return self.map.to_ply_bytes()

    def state_dict(self) -> dict:
        with self.lock:
            return {"map": self.map.state_dict(), "keyframes_mapped": self.keyframes_mapped}

    def load_state_dict(self, d: dict) -> None:
        with self.lock:
            self.map.load_state_dict(d["map"])
            self.keyframes_mapped = int(d["keyframes_mapped"])


def _unmerged(grid: dict[str, torch.Tensor], kf_id: int):
    """All valid per-pixel surfels, no voxelization (voxel_block = 1)."""
    from worker.mapping.surfels import Surfels
    from worker.mapping.voxelize import VoxelizedSurfels

    v = grid["valid"]
    rows, cols = torch.nonzero(v, as_tuple=True)
    surfels = Surfels(means=grid["means"][v], quats=grid["quats"][v], scales=grid["scales"][v],
                      opacities=grid["opacities"][v], colors=grid["colors"][v],
                      keyframe_ids=torch.full((int(v.sum()),), kf_id, dtype=torch.int64))
    return VoxelizedSurfels(surfels, torch.stack([rows, cols], -1), torch.zeros(len(surfels), dtype=torch.bool))
