"""SlamConfig: the paper's defaults, presets, overrides and clear rejections of bad values."""

from __future__ import annotations

import pytest

from worker.config import SlamConfig


def test_default_preset_has_the_paper_settings() -> None:
    cfg = SlamConfig.preset("default")
    assert cfg.frontend.submap_size == 8 and cfg.frontend.submap_overlap == 1
    assert cfg.mapping.voxel_block == 2
    assert cfg.mapping.refine_iterations == 20 and cfg.mapping.refine_keyframes == 5
    assert cfg.loop.robust_kernel == "cauchy"
    assert SlamConfig.preset("paper").frontend.model == "paper"


def test_presets_differ_and_overrides_merge_into_sections() -> None:
    fast, test = SlamConfig.preset("fast"), SlamConfig.preset("test")
    assert fast.mapping.refine_iterations < 20
    assert test.threaded is False and test.frontend.long_side < fast.frontend.long_side
    cfg = SlamConfig.preset("test", mapping={"refine_iterations": 7}, threaded=True)
    assert cfg.mapping.refine_iterations == 7 and cfg.threaded is True
    assert cfg.mapping.refine_keyframes == test.mapping.refine_keyframes  # untouched keys of the section stay


def test_round_trip_through_a_plain_dict() -> None:
    cfg = SlamConfig.preset("fast", loop={"top_k": 2})
    assert SlamConfig.from_dict(cfg.model_dump(mode="json")) == cfg


@pytest.mark.parametrize("overrides, needle", [
    ({"frontend": {"submap_size": 1}}, "submap_size"),
    ({"frontend": {"long_side": 100}}, "multiple of 16"),
    ({"mapping": {"voxel_block": 3}}, "voxel_block"),
    ({"mapping": {"tau_accum": 1.5}}, "tau_accum"),
    ({"loop": {"robust_kernel": "tukey"}}, "robust_kernel"),
    ({"device": "tpu"}, "device"),
    ({"mapping": {"no_such_knob": 1}}, "no_such_knob"),
])
def test_bad_values_are_rejected_with_the_field_named(overrides: dict, needle: str) -> None:
    with pytest.raises(ValueError, match=needle):
        SlamConfig.preset("default", **overrides)


def test_unknown_preset_and_missing_checkpoint() -> None:
    with pytest.raises(ValueError, match="unknown preset"):
        SlamConfig.preset("turbo")
    cfg = SlamConfig.preset("test", frontend={"checkpoint": "/nonexistent/weights.safetensors"})
    with pytest.raises(ValueError, match="does not exist"):
        cfg.checkpoint_path()


def test_paper_preset_keeps_the_paper_mapping_and_rgbd_preset_is_its_own() -> None:
    paper, rgbd = SlamConfig.preset("paper"), SlamConfig.preset("rgbd")
    assert paper.mapping.prune and paper.mapping.voxel_block == 2 and paper.mapping.tau_accum == 0.7
    assert paper.mapping.refine_iterations == 20 and paper.mapping.refine_keyframes == 5
    assert not rgbd.mapping.prune and rgbd.mapping.tau_accum == 0.95 and rgbd.input.surfel_init == "depth"
    assert paper.mapping.final_refine_passes == 0 and paper.mapping.archived_images == 0  # the paper has none
    assert rgbd.mapping.final_refine_passes > 0 and rgbd.mapping.archived_images > 0


def test_the_pose_source_of_earlier_configs_moves_to_tracking_source() -> None:
    # configs and snapshots of earlier versions named it `frontend.tracking`
    old = SlamConfig.preset("rgbd").model_dump(mode="json")
    old["frontend"]["tracking"] = "visual_odometry"
    del old["tracking"]["source"]
    config = SlamConfig.from_dict(old)
    assert config.tracking.source == "visual_odometry" and "tracking" not in config.frontend.model_dump()
    assert SlamConfig.preset("rgbd", frontend={"tracking": "device"}).tracking.source == "device"
    with pytest.raises(ValueError, match="tracking"):
        SlamConfig.preset("rgbd", tracking={"source": "teleport"})
