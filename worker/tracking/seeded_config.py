"""Settings of seeded tracking (`worker.tracking.seeded.SeededTracking`): how far device poses are trusted."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class DevicePoseConfig(BaseModel):
    """The stated uncertainty of a device's poses and the thresholds that call a device motion a jump."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    prior_translation: float = Field(
        0.10, gt=0, le=100, description="standard deviation (pose units, metres for ARKit/ARCore) of a device pose "
        "as an absolute prior on its keyframe in the pose graph")
    prior_rotation_deg: float = Field(2.0, gt=0, le=180, description="... and of its orientation, in degrees")
    jump_translation: float = Field(
        0.05, gt=0, description="a frame's device motion that differs from the tracked motion by more than this "
        "(pose units) is a jump (relocalisation, glitch): it is not used and the next keyframe gets no prior")
    jump_rotation_deg: float = Field(3.0, gt=0, le=180, description="... or by more than this rotation")
