"""What the engine's session-level modules (finish, stats, snapshots) read of a session: its parts, as a protocol,
so that they need not import the system that assembles them (worker.slam)."""

from __future__ import annotations

from typing import Any, Protocol

from worker.config import SlamConfig
from worker.events import EngineEvent
from worker.geometry import Intrinsics
from worker.pipeline.finish_status import FinishStatus
from worker.pipeline.judged_start import JudgedStart
from worker.pipeline.learned_model import LearnedModel
from worker.pipeline.loop_closer import LoopCloser
from worker.pipeline.loop_stage import LoopClosingStage
from worker.pipeline.mapping_process import MappingProcess
from worker.pipeline.mapping_stage import MappingStage
from worker.pipeline.session_camera import SessionCamera
from worker.pipeline.stage_times import StageTimes
from worker.pipeline.tracking_stage import TrackingStage


class SessionParts(Protocol):
    """A session's stages, choices and counters (worker.slam.SlamSystem is one)."""

    config: SlamConfig
    intrinsics: Intrinsics | None
    camera: SessionCamera
    tracking_stage: TrackingStage
    mapping_stage: MappingStage | MappingProcess | None
    judged_start: JudgedStart
    timings: StageTimes
    counters: dict[str, float]
    tracking: str | None
    mode: str | None
    model_id: str | None
    learned: LearnedModel | None
    loop_closer: LoopCloser | None
    with_depth: bool
    wall_offset: float
    finish_events: list[EngineEvent]
    finish_status: FinishStatus

    @property
    def loop_stage(self) -> LoopClosingStage: ...

    @property
    def pose_source(self) -> Any: ...

    @property
    def revision(self) -> int: ...

    @property
    def num_gaussians(self) -> int: ...

    @property
    def model_intrinsics(self) -> Intrinsics | None: ...

    def setup(self, tracking: str, with_depth: bool) -> None: ...
