"""Monocular visual odometry as a pose source.

Points are followed from frame to frame by sub-pixel optical flow (Lucas-Kanade, forward-backward checked, guided
by the motion model) and re-matched against the last keyframe's image, so that small errors do not add up from frame
to frame. The map starts from a two-view reconstruction of the first tracks with enough parallax; each frame's pose
then comes from the tracks that measure map points (robust refinement from the constant-velocity guess, PnP + RANSAC
when that fails). Keyframes are taken when tracks drop or the baseline grows: they add new corners, triangulate the
candidate tracks that gained enough parallax since the oldest keyframe that saw them, and run a local bundle
adjustment over the keyframes sharing the most points with the new one, those that also see their points held
fixed (`covisibility`), so scale carries over without rescaling. A lost frame first tries to take up the last
tracked frame's tracks (a short loss), then place recognition with the ORB features the keyframes keep, then a map
restarted from two views. A restarted map is joined to the older one, scale included, when one of its keyframes
recognises an older keyframe (`map_join`: the map moves, the poses handed out do not jump, and the `maps_merged`
event carries the Sim(3) edge for the pose graph). When the camera comes back, a keyframe VO takes for its own map
is not offered to the engine (`keyframe_hint=False`) if an engine keyframe at least `reuse_min_age` frames old lies
near and sees most of the frame's tracked map points: a place walked through again keeps the keyframes of its first
visit. A turn faster than points can be triangulated is followed by the rotation the tracks agree on
(`rotation_only`); where too few tracks survive (stripes, a plain wall, blur) the whole image is aligned to the last
tracked frame's (`direct_rotation`: the turn measured, the position predicted), and only then is the frame lost.

Poses are camera-to-world rigid 4x4 matrices (a Sim(3) with s = 1); the world is the camera of the frame the map
was initialised from and the scale makes that map's median depth 1. Poses handed out are the map's moved by the
output similarity (the identity until a restarted map is joined to an older one).

`VisualOdometry` only sequences the phases, each a module of functions of the state (`vo_state.VoState`: all that
changes while tracking, with the snapshot's fields) and the fixed parts (`vo_state.VoParts`: settings, ORB, places,
XFeat): `vo_calibration` (the camera, the focal length), `vo_initialisation` (the two-view map),
`vo_frame_tracking` (a frame on the map, the turn bridges), `vo_mapping` (keyframes, triangulation, the BA window),
`vo_map_join` (a restarted map joined to an older one; the output similarity), `vo_recovery` (lost, relocalised,
restarted), over `vo_tracks` (optical flow, new corners) and `vo_places` (keyframes as places).
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace
from typing import Any

import cv2
import numpy as np

from worker.data.frame import Frame
from worker.geometry import Intrinsics

from . import schur_native
from .base import TrackingResult
from .global_adjustment import GlobalAdjustment, adjust_globally
from .keyframe_scale import local_scales, scale_spread, scaled_moves
from .learned_places import LearnedPlaces
from .local_map import LocalMap
from .map_join import similarity_scale
from .projection import camera_matrix
from .relocalization import Place
from .vo_calibration import camera_of
from .vo_config import VisualOdometryConfig
from .vo_frame_tracking import track_frame
from .vo_initialisation import initialise
from .vo_map_join import output_is_identity, to_output
from .vo_places import archive
from .vo_recovery import lose, lose_or_restart, recognise_place, relocalise
from .vo_state import STATE_VERSION, Anchor, JoinState, VoParts, VoState


class VisualOdometry:
    """PoseSource for RGB-only streams (see the module docstring)."""

    name = "visual_odometry"
    submap_seam = "new_map"  # the pose-graph edge kind between a lost map and the new map begun after it

    def __init__(self, config: VisualOdometryConfig | None = None) -> None:
        self.config = config or VisualOdometryConfig()
        self.parts = VoParts.build(self.config)
        schur_native.available()  # builds (or loads) the compiled kernel now, not at the first keyframe
        self.state = VoState.start(self.config)
        self._camera: Intrinsics | None = None
        self.final_adjustment: GlobalAdjustment | None = None  # the last `keyframe_corrections()`'s outcome

    # ---- what callers read (the state's, read-only here) -----------------------------------------------------
    @property
    def learned(self) -> LearnedPlaces:
        """XFeat matching against remembered keyframes (its counters tell how often the network ran)."""
        return self.parts.learned

    @property
    def status(self) -> str:
        return self.state.status

    @property
    def pose(self) -> np.ndarray:
        return self.state.pose

    @property
    def estimated_intrinsics(self) -> Intrinsics | None:
        return self.state.estimated_intrinsics

    @property
    def map(self) -> LocalMap:
        return self.state.map

    @property
    def map_id(self) -> int:
        return self.state.map_id

    @property
    def map_depth(self) -> float:
        return self.state.map_depth

    @property
    def join(self) -> JoinState | None:
        return self.state.join

    @property
    def anchor(self) -> Anchor | None:
        return self.state.anchor

    @property
    def retired(self) -> list[Place]:
        return self.state.retired

    @property
    def keyframe_images(self) -> dict[int, np.ndarray]:
        return self.state.keyframe_images

    @property
    def engine_keyframes(self) -> deque[tuple[int, np.ndarray]]:
        return self.state.engine_keyframes

    # ---- PoseSource ------------------------------------------------------------------------------------------
    def track(self, frame: Frame, intrinsics: Intrinsics | None, motion_guess: np.ndarray | None = None
              ) -> TrackingResult:
        """Track the next frame (see the module docstring); bad frames lose tracking, they never raise.
        `motion_guess` (previous^-1 @ current in this odometry's units, e.g. a device's relative motion) replaces
        the constant-velocity guess when given."""
        s, parts, index = self.state, self.parts, frame.index
        camera = self._camera = camera_of(s, frame, intrinsics)
        gray = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
        parts.learned.begin_frame(index)
        if motion_guess is not None and not output_is_identity(s):  # output units -> the map's
            motion_guess = np.array(motion_guess, np.float64)
            motion_guess[:3, 3] /= similarity_scale(s.output)
        if s.status == "initializing":
            # after a loss, the old map's places are looked for while the new map waits to be made
            found = recognise_place(s, parts, index, gray, camera) if s.maps_started > 1 and s.retired else None
            if found is not None:
                s.maps_started -= 1  # back on the old map: the new one was never made
                s.pending, s.pending_orientation, s.init_state = [], {}, ""
            result = found or initialise(s, parts, index, gray, camera, intrinsics is None)
        elif s.status == "lost":
            result = relocalise(s, parts, index, gray, camera)
        else:
            result = track_frame(s, parts, index, gray, camera, motion_guess)
            if isinstance(result, str):  # lost: a map may restart from the last tracked frame at once
                result = lose_or_restart(s, parts, index, gray, camera, result)
        if not np.all(np.isfinite(result.pose)):  # never hand out a NaN pose, whatever happened above
            result = lose(s, parts, index, "non-finite pose estimate")
        s.pose = result.pose
        if result.tracked:
            s.last_tracked = index
        result.submap_id = s.maps_started - 1
        return to_output(s, result)

    def keyframe_added(self, frame: Frame, pose: np.ndarray) -> None:
        """The engine's keyframes do not change VO's own; they are remembered as places to come back to."""
        if self.config.reuse_keyframes > 0:
            self.state.engine_keyframes.append((int(frame.index), np.asarray(pose, np.float64).copy()))

    def is_keyframe(self, index: int) -> bool:
        """Whether frame `index` became one of this odometry's keyframes that the final adjustment will see."""
        archive_ = self.state.archive
        return index in archive_.handed_out or index in archive_.keyframes

    def adjusted_keyframes(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """The final bundle adjustment (`global_adjustment`) over every keyframe this odometry made: for each, by
        frame index, the pose its frame was given and the adjusted pose (this odometry's world). Empty when it did
        not run: off, no revisits, a map restarted after a loss, or a joined map's poses handed out through a
        similarity."""
        s = self.state
        if s.archive.max_keyframes == 0 or self._camera is None or not output_is_identity(s):
            return {}
        archive(s, self.parts, s.map.keyframes)  # the window's keyframes, as they are now
        before = {k: kf.pose if kf.handed_out is None else kf.handed_out for k, kf in s.archive.keyframes.items()}
        result = adjust_globally(s.archive, camera_matrix(self._camera), s.map_depth, self.config,
                                 self.parts.extractor.level_sigmas)
        self.final_adjustment = result
        return {k: (before[k], pose) for k, pose in result.poses.items()}

    def keyframe_corrections(self) -> dict[int, np.ndarray]:
        """Each adjusted keyframe's move from the pose its frame was given to its adjusted pose
        (`adjusted_keyframes`), by frame index: a similarity whose scale is the local scale the adjustment found
        (worker.tracking.keyframe_scale), so the keyframe's part of the map takes it; frames between keyframes
        follow them."""
        adjusted = self.adjusted_keyframes()
        given = {k: before for k, (before, _) in adjusted.items()}
        placed = {k: after for k, (_, after) in adjusted.items()}
        scales = local_scales(given, placed)
        if self.final_adjustment is not None:
            self.final_adjustment = replace(self.final_adjustment, local_scales=scale_spread(scales))
        return scaled_moves(given, placed, scales)

    # ---- snapshots -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything to continue after a restart (msgpack-able; bounded by the window and the place memory)."""
        return {"version": STATE_VERSION, "config": self.config.model_dump(), **self.state.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from `state_dict()` (the configuration comes with the state)."""
        if int(state.get("version", -1)) != STATE_VERSION:
            raise ValueError(f"visual odometry state version {state.get('version')!r}, expected {STATE_VERSION}")
        self.__init__(VisualOdometryConfig(**state["config"]))
        self.state.load_state_dict(state)
