"""The one decision of a session's settings (worker.settings_choice): for each input mode and each kind of machine,
and what `flashmono run` takes from it."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from client.commands.run import DEFAULT_FINISH_BUDGET_S, add_run_options, load_config
from worker.runtime.engine import close_engine, create_engine
from worker.runtime.session_settings import received_input, session_settings
from worker.settings_choice import (
    LIVE_TRACKING_SIDE,
    LIVE_WORKING_SIDE,
    SHIPPED_CHECKPOINT,
    Machine,
    SessionInput,
    choices_by_input,
    choose_settings,
)

CPU = Machine(cpu_cores=2)
GPU_ONLY = Machine(cpu_cores=16, cuda=True)
GPU_WEIGHTS = Machine(cpu_cores=16, cuda=True, checkpoint="/weights/cut3r_512.safetensors")
MODES = {"rgbd": (True, False), "posed-rgbd": (True, True), "posed-rgb": (False, True), "rgb": (False, False)}


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("live", [True, False])
def test_a_cpu_gets_the_cpu_mapping_settings_for_every_input(mode, live):
    depth, poses = MODES[mode]
    choice = choose_settings(SessionInput(depth=depth, device_poses=poses, width=320, height=240, live=live), CPU)
    assert choice.preset == "rgbd" and choice.decided == "auto"
    assert "device" not in choice.overrides and choice.tracking_side is None  # 320 px: tracked as it comes
    assert any("no CUDA GPU" in reason for reason in choice.reasons)
    assert choice.reasons[-1].startswith(f"input: {mode};")
    mapping = {"final_refine_budget_s": 0.0} if not live else {}  # a recording: every pass, as flashmono run
    if mode in ("rgb", "posed-rgb"):  # visual odometry on 2 cores: mapping beside tracking, not under it
        assert choice.overrides == {"mapping": {"process": True, **mapping}}
        assert any("process of its own" in reason for reason in choice.reasons)
    else:
        assert choice.overrides == ({"mapping": mapping} if mapping else {})


@pytest.mark.parametrize("mode", MODES)
def test_a_recording_gets_every_pass_of_the_final_refinement_and_a_live_stream_a_bounded_finish(mode):
    """A live stream's finish is bounded so the phone gets its map in time; a recording (every frame tracked) is
    refined as `flashmono run` refines it."""
    from worker.config import SlamConfig, deep_merge

    depth, poses = MODES[mode]
    budgets = {}
    for live in (True, False):
        choice = choose_settings(SessionInput(depth=depth, device_poses=poses, width=320, height=240, live=live), CPU)
        config = SlamConfig.preset(choice.preset, **deep_merge(choice.engine_overrides(), {}))
        budgets[live] = config.mapping.final_refine_budget_s
        assert config.mapping.final_refine_passes > 0
        assert any("every pass" in reason for reason in choice.reasons) == (not live)
    assert budgets == {True: SlamConfig().mapping.final_refine_budget_s, False: 0.0} and budgets[True] > 0


def test_one_core_maps_in_a_thread():
    received = SessionInput(depth=False, device_poses=False, width=320, height=240, live=True)
    choice = choose_settings(received, Machine(cpu_cores=1))
    assert choice.preset == "rgbd" and "mapping" not in choice.overrides


def test_the_paper_settings_need_a_gpu_and_trained_weights():
    received = SessionInput(depth=False, device_poses=False, width=640, height=480)
    assert choose_settings(received, CPU).preset == "rgbd"
    gpu_only = choose_settings(received, GPU_ONLY)
    assert gpu_only.preset == "rgbd" and gpu_only.overrides["device"] == "cuda"
    assert any("no trained weights" in reason for reason in gpu_only.reasons)
    paper = choose_settings(received, GPU_WEIGHTS)
    assert paper.preset == "paper"
    assert paper.engine_overrides()["frontend"] == {"checkpoint": "/weights/cut3r_512.safetensors"}
    # weights without a GPU are not enough
    assert choose_settings(received, Machine(cpu_cores=2, checkpoint="/w.safetensors")).preset == "rgbd"


@pytest.mark.parametrize("mode", MODES)
def test_a_live_stream_over_320_pixels_is_worked_on_at_320_on_a_cpu(mode):
    depth, poses = MODES[mode]
    live = choose_settings(SessionInput(depth=depth, device_poses=poses, width=640, height=480, live=True,
                                        frame_rate=30), CPU)
    recorded = choose_settings(SessionInput(depth=depth, device_poses=poses, width=640, height=480), CPU)
    assert live.working_side == LIVE_WORKING_SIDE and live.tracking_side is None
    assert any("30 frames/s" in reason for reason in live.reasons)
    assert recorded.working_side is None and recorded.tracking_side is None  # a recording keeps its size
    small = choose_settings(SessionInput(depth=depth, device_poses=poses, width=320, height=240, live=True), CPU)
    assert small.working_side is None


@pytest.mark.parametrize("mode", MODES)
def test_on_a_gpu_live_rgbd_over_320_pixels_is_tracked_at_320_and_mapped_whole(mode):
    depth, poses = MODES[mode]
    live = choose_settings(SessionInput(depth=depth, device_poses=poses, width=640, height=480, live=True), GPU_ONLY)
    assert live.working_side is None
    assert live.tracking_side == (LIVE_TRACKING_SIDE if depth else None)
    if depth:
        assert live.engine_overrides() == {"device": "cuda", "tracking": {"max_side": LIVE_TRACKING_SIDE}}


def test_an_unknown_input_still_gets_settings():
    choice = choose_settings(SessionInput(), CPU)
    assert choice.preset == "rgbd" and choice.tracking_side is None
    assert choice.reasons[-1].startswith("input: unknown;")


def test_choices_by_input_lists_every_mode():
    table = choices_by_input(CPU)
    assert set(table) == set(MODES)
    assert all(choice["working_side"] == LIVE_WORKING_SIDE for choice in table.values())
    gpu = choices_by_input(GPU_ONLY)
    assert gpu["rgbd"]["tracking_side"] == LIVE_TRACKING_SIDE and gpu["rgb"]["tracking_side"] is None


def test_the_machine_counts_only_trained_weights(tmp_path: Path, monkeypatch):
    monkeypatch.delenv("FLASHMONO_CHECKPOINT", raising=False)
    assert not Machine.detect().trained_weights
    assert not Machine.detect(str(SHIPPED_CHECKPOINT)).trained_weights  # the toy model is no trained weights
    assert not Machine.detect(str(tmp_path / "missing.safetensors")).trained_weights
    weights = tmp_path / "paper.safetensors"
    weights.write_bytes(b"x")
    monkeypatch.setenv("FLASHMONO_CHECKPOINT", str(weights))
    machine = Machine.detect()
    assert machine.trained_weights and machine.checkpoint == str(weights) and machine.cpu_cores >= 1
    assert Machine.from_dict(machine.to_dict()).trained_weights


def test_a_session_keeps_the_settings_recorded_for_it_and_a_named_preset_wins():
    import json

    first = {"skip_frames": "1", "frame_rate": "30"}
    received = received_input(first, None)
    assert received.live and received.frame_rate == 30 and received.mode == "unknown"
    recorded = choose_settings(SessionInput(depth=True, device_poses=False, width=640, height=480, live=True), CPU)
    # a worker that takes the session over reads the decision back, whatever its own machine
    again = session_settings({**first, "settings": json.dumps(recorded.to_record())}, None, GPU_WEIGHTS)
    assert again == recorded
    named = session_settings({"preset": "fast"}, None, GPU_WEIGHTS)
    assert named.preset == "fast" and named.decided == "named"
    assert session_settings({"preset": "auto"}, None, CPU).decided == "auto"


def test_the_engine_runs_the_chosen_settings():
    choice = choose_settings(SessionInput(depth=True, device_poses=False, width=640, height=480, live=True), GPU_ONLY)
    choice.overrides.pop("device")  # this machine has no GPU
    engine = create_engine("slam", choice.preset, None, overrides=choice.engine_overrides())
    try:
        assert engine.config.name == "rgbd" and engine.config.tracking.max_side == LIVE_TRACKING_SIDE
    finally:
        close_engine(engine)
    engine = create_engine("slam", choice.preset, None, tracking_side=480, overrides=choice.engine_overrides())
    try:  # the session's own tracking side wins over the choice's
        assert engine.config.tracking.max_side == 480
    finally:
        close_engine(engine)


def _run_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_run_options(parser)
    return parser.parse_args(["--out", "unused", *argv])


def test_flashmono_run_takes_the_same_decision_and_bounds_its_finish():
    config = load_config(_run_args("--use-gt-depth"))
    assert config.name == choose_settings(SessionInput(depth=True, device_poses=False), Machine.detect()).preset
    assert config.mapping.final_refine_budget_s == DEFAULT_FINISH_BUDGET_S == 0  # the passes complete
    assert load_config(_run_args("--deterministic")).mapping.final_refine_budget_s == 0  # no time-driven rates
    bounded = load_config(_run_args("--finish-budget", "60")).mapping
    assert bounded.final_refine_budget_s == 60
    assert not bounded.final_refine_budget_counts_drain  # the refinement's own budget, after the drain
    assert load_config(_run_args("--preset", "fast")).name == "fast"
