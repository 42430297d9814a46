"""Settings of the multi-view depth source (nestable as `SlamConfig.depth`).

Every threshold is unit-free: costs are 1 - ZNCC, geometry is relative (baseline over depth, pixels, degrees), so
the same settings hold for metric poses and for monocular SLAM's arbitrary scale.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class MultiViewDepthConfig(BaseModel):
    """Plane-sweep stereo with ZNCC costs, semi-global aggregation and a multi-view consistency check."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    # neighbour choice (select_neighbours)
    num_views: int = Field(4, ge=1, le=16, description="Neighbouring frames used per keyframe (at most).")
    min_parallax: float = Field(0.02, gt=0, description="Smallest baseline / scene depth for a neighbour.")
    max_parallax: float = Field(0.6, gt=0, description="Largest baseline / scene depth for a neighbour.")
    target_parallax: float = Field(0.07, gt=0, description="Preferred baseline / scene depth.")
    max_view_angle_deg: float = Field(
        45.0, gt=0, le=180, description="Largest angle between the keyframe's and a neighbour's optical axes.")

    # plane sweep and cost
    num_hypotheses: int = Field(48, ge=48, le=256, description="Planes swept, uniform in inverse depth.")
    window_radius: int = Field(3, ge=1, le=7, description="ZNCC window half-size (radius 3: 7x7 pixels).")
    min_texture_std: float = Field(
        0.003, ge=0, description="Below this grey-level std (images in [0, 1]) a window is textureless: ZNCC 0.")
    views_per_pixel: int = Field(
        2, ge=1, description="Per hypothesis, the mean of the best this many views' costs (robust to occlusion).")
    scale: float = Field(1.0, gt=0.1, le=1.0, description="Run the sweep on images resized by this factor.")

    # aggregation and refinement
    sgm_paths: Literal[4, 8] = Field(4, description="Semi-global aggregation paths (4: axes; 8: also diagonals).")
    sgm_p1: float = Field(0.03, ge=0, description="SGM penalty (cost units) for a one-hypothesis step.")
    sgm_p2: float = Field(0.25, ge=0, description="SGM penalty (cost units) for a larger jump.")

    # consistency and confidence
    min_views: int = Field(2, ge=1, description="Views that must agree with a pixel's depth for it to be kept.")
    support_margin: float = Field(
        0.1, ge=0, description="A view agrees when its cost at the chosen depth is within this of its own best.")
    max_view_cost: float = Field(0.6, gt=0, le=2, description="A view agrees only below this cost (1 - ZNCC).")
    uniqueness_full: float = Field(
        0.1, gt=0, description="Relative margin of the best aggregated cost over the runner-up worth full confidence.")
    margin_full: float = Field(
        0.03, gt=0, description="Margin of the best matching cost (1 - ZNCC) below every hypothesis more than two "
                                "away worth full confidence (intensity ramps match at many depths).")
    min_confidence: float = Field(0.25, ge=0, le=1, description="Pixels below this confidence get depth 0.")
    edge_jump: float = Field(
        0.1, ge=0, description="Drop pixels within a window radius of a point farther by this fraction of inverse "
                               "depth (foreground fattening at occluding edges); 0 disables.")
    speckle_size: int = Field(
        100, ge=0, description="Drop connected confident regions smaller than this many pixels (0 disables).")
    speckle_step: float = Field(2.0, gt=0, description="Hypotheses between neighbours of one connected region.")

    # depth range when none is given: multiples of the median keyframe-neighbour baseline (4 to 100: parallax 0.25
    # to 0.01, around target_parallax)
    near_over_baseline: float = Field(4.0, gt=0, description="Default nearest depth / median baseline.")
    far_over_baseline: float = Field(100.0, gt=0, description="Default farthest depth / median baseline.")
    min_sweep_pixels: float = Field(
        4.0, ge=0, description="A neighbour whose epipolar segment over the range is shorter (pixels) is dropped.")

    # execution
    backend: Literal["auto", "cpu", "reference"] = Field(
        "auto", description="auto: compiled kernels when they build, else the numpy reference.")
    threads: int = Field(
        1, ge=1, le=64, description="Threads of the compiled kernels (1 leaves the other core to the frontend; on a "
                                    "loaded 2-core machine 2 threads were not faster).")
    keep_buffers: bool = Field(
        True, description="Keep the large intermediate arrays for later calls (at most two sets per process, about "
                          "90 MB each at 320x240, 4 views, 48 planes): no page-zeroing on every keyframe.")
    warn_below_coverage: float = Field(
        0.01, ge=0, le=1, description="Log a warning when fewer pixels than this fraction are confident.")

    @model_validator(mode="after")
    def _consistent(self) -> MultiViewDepthConfig:
        if not self.min_parallax <= self.target_parallax <= self.max_parallax:
            raise ValueError("need min_parallax <= target_parallax <= max_parallax")
        if self.near_over_baseline >= self.far_over_baseline:
            raise ValueError("near_over_baseline must be below far_over_baseline")
        if self.sgm_p1 > self.sgm_p2:
            raise ValueError("sgm_p1 must not exceed sgm_p2")
        if self.min_views > self.num_views:
            raise ValueError(f"min_views ({self.min_views}) cannot exceed num_views ({self.num_views})")
        return self
