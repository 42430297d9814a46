"""The runtime breakdown (paper appendix E): per-module wall times from a real run, and the bookkeeping itself."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from worker.config import SlamConfig
from worker.offline import PoseDrift, run_sequence
from worker.pipeline.stage_times import STAGES, StageTimes, breakdown_table

ICL = Path(__file__).parents[1] / "data" / "icl_mini"


def test_stage_times_accumulate_events_and_reject_unknown_stages():
    times = StageTimes()
    for _ in range(3):
        with times.measure("map_refine"):
            time.sleep(0.002)
    times.add("pgo", 0.5)
    b = times.breakdown(frames=10)
    assert b["map_refine"]["events"] == 3 and b["map_refine"]["total_s"] >= 0.006
    assert b["map_refine"]["ms_per_frame"] == pytest.approx(1e3 * b["map_refine"]["total_s"] / 10)
    assert b["pgo"]["ms_per_event"] == pytest.approx(500.0)
    assert b["frontend_inference"]["events"] == 0
    with pytest.raises(ValueError, match="unknown stage"):
        times.add("rendering", 1.0)


def test_a_run_reports_where_its_time_went(tmp_path):
    config = SlamConfig.preset("test", input={"pose_mode": "prior", "surfel_init": "depth"},
                               frontend={"keyframe_every": 3})
    metrics = run_sequence(ICL, tmp_path, config, use_gt_depth=True, use_gt_poses=True, max_frames=7,
                           resize=(80, 60), drift=PoseDrift(0.05, 0.001))
    b = metrics["runtime_breakdown"]
    assert set(b) == set(STAGES)
    keyframes = metrics["num_keyframes"]
    assert keyframes >= 2
    assert b["map_merge"]["events"] == keyframes and b["map_merge"]["total_s"] > 0
    assert b["map_refine"]["events"] == keyframes
    assert b["loop_detection"]["events"] == keyframes  # every keyframe is queried for loops
    assert b["frontend_inference"]["events"] == 0  # depth-initialised surfels and given poses: no model
    # a solve per loop and per keyframe whose dense edges to its neighbours were kept (`drift_corrected`)
    assert b["pgo"]["events"] == metrics["loops"] + metrics["events"].get("drift_corrected", 0)
    table = breakdown_table(b, metrics["num_frames"])
    assert "total per frame" in table and "merge & voxelization" in table


@pytest.mark.parametrize("live_pacing", [False, True])
def test_an_offline_run_refines_every_keyframe_unless_paced_like_a_live_stream(tmp_path, live_pacing):
    """Mapping far slower than tracking (given poses and depth, 25 refinement iterations a keyframe): an offline run
    sheds nothing by default, so its map does not depend on the machine's load; paced like a live stream it sheds."""
    config = SlamConfig.preset("test", threaded=True, queue_size=24, input={"pose_mode": "fixed",
                                                                          "surfel_init": "depth"},
                               mapping={"refine_iterations": 25, "shed_backlog": 1, "merge_only_backlog": 2,
                                        "final_refine_passes": 0},
                               frontend={"keyframe_every": 1})
    metrics = run_sequence(ICL, tmp_path, config, use_gt_depth=True, use_gt_poses=True, max_frames=8,
                           resize=(80, 60), live_pacing=live_pacing)
    shed = metrics["keyframes_shed"]
    refined = metrics["runtime_breakdown"]["map_refine"]["events"]
    if live_pacing:
        assert shed["merge_only"] > 0 and refined < metrics["num_keyframes"]
    else:
        assert shed == {"reduced": 0, "merge_only": 0, "dropped": 0}
        assert refined == metrics["num_keyframes"] >= 6


def test_complete_pacing_turns_lighterglue_on_unless_the_config_set_it():
    from worker.offline import complete_pacing

    paced = complete_pacing(SlamConfig.preset("rgbd"))
    assert paced.tracking.visual.learned_glue and paced.mapping.shed_backlog == 0 and paced.queue_size >= 256
    kept = complete_pacing(SlamConfig.preset("rgbd", tracking={"visual": {"learned_glue": False}}))
    assert not kept.tracking.visual.learned_glue and kept.mapping.shed_backlog == 0
