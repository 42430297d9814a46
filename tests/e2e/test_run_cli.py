"""`flashmono run` and `flashmono eval` end to end on the ICL subset (posed RGB-D mode: no model needed)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from worker.eval import read_tum

REPO = Path(__file__).resolve().parents[2]


def flashmono(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "client.cli", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=900)


def test_run_writes_trajectories_map_renders_and_metrics(data_dir: Path, tmp_path: Path) -> None:
    overrides = tmp_path / "cfg.json"
    overrides.write_text(json.dumps({"input": {"surfel_init": "depth", "pose_mode": "fixed"},
                                     "frontend": {"keyframe_every": 3, "keyframe_parallax": 1.0}}))
    out = tmp_path / "run"
    proc = flashmono("run", str(data_dir / "icl_mini"), "--out", str(out), "--use-gt-depth", "--use-gt-poses",
                     "--preset", "test", "--max-frames", "6", "--resize", "80x60", "--config", str(overrides),
                     "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("ate_rmse", "psnr", "psnr_normalised", "ssim", "depth_l1", "fps", "num_gaussians"):
        assert metrics[key] is not None, key
    assert "lpips" in metrics and (metrics["lpips"] is not None or metrics["lpips_note"])
    assert metrics["ate_rmse"] < 1e-6  # fixed ground-truth poses
    assert metrics["psnr"] > 18 and metrics["depth_l1"] < 0.1 and metrics["num_gaussians"] > 0
    assert metrics["num_frames"] == 6 and metrics["num_keyframes"] == 2
    held = metrics["held_out"]  # per held-out frame, for comparing modes on the frames both held out
    assert len(held["index"]) == len(held["psnr"]) == len(held["psnr_normalised"]) == metrics["eval_frames"] >= 2
    assert np.isclose(np.mean(held["psnr"]), metrics["psnr"]) and np.isclose(np.mean(held["psnr_normalised"]),
                                                                              metrics["psnr_normalised"])
    from bench.held_out import common_scores

    fewer = {key: values[1:] for key, values in held.items()}  # another run that mapped the first of these frames
    common, means = common_scores({"a": held, "b": fewer})
    assert common == held["index"][1:]
    assert np.isclose(means["a"]["psnr"], np.mean(held["psnr"][1:])) and means["a"] == means["b"]
    assert len(read_tum(out / "trajectory_all.tum")) == 6
    assert len(read_tum(out / "trajectory_keyframes.tum")) == 2
    intr = json.loads((out / "intrinsics.json").read_text())
    assert np.isclose(intr["fx"], 262.5 / 4) and intr["width"] == 80
    assert (out / "map.ply").read_bytes().startswith(b"ply")
    renders = sorted((out / "renders").glob("*.png"))
    assert renders
    import cv2

    assert cv2.imread(str(renders[0])).shape == (60, 160, 3)  # rendered | ground truth


def test_run_reports_bad_sources_clearly(tmp_path: Path) -> None:
    proc = flashmono("run", str(tmp_path / "missing"), "--out", str(tmp_path / "o"), "--no-progress")
    assert proc.returncode == 2 and "error:" in proc.stderr
    proc = flashmono("run", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "turbo", "--no-progress")
    assert proc.returncode == 2 and "unknown preset" in proc.stderr


def test_runs_default_to_the_rgbd_preset() -> None:
    import argparse

    from client.commands.run import add_run_options, default_preset

    parser = argparse.ArgumentParser()
    parser.add_argument("source")
    add_run_options(parser)
    choose = lambda *argv: default_preset(parser.parse_args(["seq", "--out", "o", *argv]))  # noqa: E731
    assert choose("--use-gt-depth", "--use-gt-poses") == "rgbd"
    assert choose("--use-gt-depth") == "rgbd"  # RGB-D odometry maps like the posed RGB-D mode
    assert choose() == choose("--use-gt-poses") == "rgbd"  # multi-view depth too
    assert choose("--use-gt-depth", "--use-gt-poses", "--preset", "paper") == "paper"


def test_deterministic_runs_repeat_exactly(data_dir: Path, tmp_path: Path) -> None:
    """`--deterministic` runs the threaded preset's stages inline: two runs give the same map, poses and scores."""
    import argparse

    from client.commands.run import add_run_options, load_config

    parser = argparse.ArgumentParser()
    parser.add_argument("source")
    add_run_options(parser)
    assert load_config(parser.parse_args(["seq", "--out", "o"])).threaded  # the rgbd preset threads its stages
    assert not load_config(parser.parse_args(["seq", "--out", "o", "--deterministic"])).threaded
    runs = []
    for name in ("a", "b"):
        out = tmp_path / name
        proc = flashmono("run", str(data_dir / "icl_mini"), "--out", str(out), "--use-gt-depth", "--deterministic",
                         "--max-frames", "8", "--resize", "80x60", "--no-progress")
        assert proc.returncode == 0, proc.stderr[-3000:]
        runs.append(out)
    first, second = (json.loads((out / "metrics.json").read_text()) for out in runs)
    assert first["threaded"] is False and first["psnr"] is not None
    for key in ("psnr", "ate_rmse", "depth_l1", "num_gaussians", "held_out"):
        assert first[key] == second[key], key
    assert (runs[0] / "trajectory_all.tum").read_text() == (runs[1] / "trajectory_all.tum").read_text()
    assert (runs[0] / "map.ply").read_bytes() == (runs[1] / "map.ply").read_bytes()
