"""Paper-style tables from per-sequence metrics dicts."""

from __future__ import annotations

import json

import pytest

from worker.eval import all_tables, ate_table, depth_table, load_metrics, mapping_table
from worker.eval.tables import pooled_fps


def rows_of(table: str) -> list[list[str]]:
    lines = [line for line in table.splitlines() if line.startswith("| ")]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]


METRICS = [
    dict(sequence="0054", ate_rmse=0.1169, psnr=21.73, ssim=0.79, lpips=0.39, depth_l1=0.21, fps=12.0,
         num_gaussians=5, num_frames=120, runtime_s=10.0, dataset="ScanNet"),
    dict(sequence="0059", ate_rmse=0.0889, psnr=17.83, ssim=0.66, lpips=None, depth_l1=0.31, fps=13.0,
         num_gaussians=5, num_frames=80, runtime_s=6.0, dataset="ScanNet"),
    dict(sequence="apt0", ate_rmse=0.1144, psnr=19.03, ssim=0.66, depth_l1=0.12, fps=11.0, num_gaussians=5,
         dataset="BundleFusion"),
    dict(sequence="0054", method="MASt3R-SLAM", ate_rmse=0.1325, psnr=None, ssim=None, depth_l1=None, fps=None,
         num_gaussians=0),
]


def test_ate_table_in_centimetres_by_method_and_sequence():
    rows = rows_of(ate_table(METRICS))
    assert rows[0] == ["ATE RMSE [cm]", "0054", "0059", "apt0"]
    assert rows[1] == ["Ours", "11.69", "8.89", "11.44"]
    assert rows[2] == ["MASt3R-SLAM", "13.25", "-", "-"]
    assert rows_of(ate_table(METRICS, unit="m"))[1][1] == "0.12"
    with pytest.raises(ValueError, match="unit"):
        ate_table(METRICS, unit="ft")


def test_mapping_table_rows_and_pooled_fps():
    rows = rows_of(mapping_table(METRICS[:3]))
    assert rows[0] == ["Method", "Metric", "0054", "0059", "apt0", "FPS ↑"]
    assert rows[1][:5] == ["Ours", "SSIM ↑", "0.790", "0.660", "0.660"]
    assert rows[2][1:5] == ["LPIPS ↓", "0.390", "-", "-"]
    assert rows[3][1:5] == ["PSNR ↑", "21.73", "17.83", "19.03"]
    # apt0 lacks frames/runtime, so the mean of the fps values is used.
    assert rows[1][5] == "12.00"
    assert pooled_fps(METRICS[:2]) == pytest.approx(200 / 16)


def test_depth_table_averages_per_dataset():
    rows = rows_of(depth_table(METRICS[:3]))
    assert rows[0] == ["L1 (m) ↓", "ScanNet", "BundleFusion"]
    assert rows[1] == ["Ours", "0.260", "0.120"]


def test_load_metrics_names_sequences_after_their_folder(tmp_path):
    for name in ("seqA", "seqB"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.json").write_text(json.dumps(dict(ate_rmse=0.05, psnr=20, ssim=0.7,
                                                                     depth_l1=0.1, fps=10, num_gaussians=3)))
    metrics = load_metrics(sorted(tmp_path.glob("*/metrics.json")))
    assert [m["sequence"] for m in metrics] == ["seqA", "seqB"]
    text = all_tables(metrics)
    assert "seqA" in text and "5.00" in text
    (tmp_path / "bad.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="JSON object"):
        load_metrics([tmp_path / "bad.json"])
    with pytest.raises(ValueError, match="no metrics"):
        ate_table([])
