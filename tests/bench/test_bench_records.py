"""Benchmarks write their figures as result records (bench/record.py): the cheapest ones, at their smallest sizes,
write the cases and value keys the scoreboard reads (bench/scoreboard_areas.py), under $FLASHMONO_BENCH_RESULTS."""

from __future__ import annotations

import json
from pathlib import Path

from bench.record import RESULTS_DIR, Recorder, results_dir
from bench.scoreboard_areas import AREAS

COLUMNS = {area.key: {column.key for column in area.columns} for area in AREAS}


def _records(folder: Path) -> list[dict]:
    return [json.loads(path.read_text()) for path in sorted(folder.glob("*.json"))]


def test_the_results_folder_follows_the_environment(bench_results: Path, monkeypatch) -> None:
    assert results_dir() == bench_results
    assert Recorder("x", []).folder == bench_results / "x"
    monkeypatch.delenv("FLASHMONO_BENCH_RESULTS")
    assert Recorder("x", []).folder == RESULTS_DIR / "x"


def test_pose_graph_writes_the_loop_areas_records(bench_results: Path) -> None:
    from bench.pose_graph import main

    assert main(["--keyframes", "60", "--loops", "5", "--repeats", "1", "--per-keyframe"]) == 0
    records = _records(bench_results / "pose_graph")
    assert [r["case"] for r in records] == [
        {"area": "loop", "sequence": "60 keyframes, 5 loops", "mode": "pose graph, full solve"},
        {"area": "loop", "sequence": "60 keyframes, 5 loops", "mode": "pose graph, incremental after a loop"}]
    for record in records:
        assert set(record["values"]) == COLUMNS["loop"] and record["values"]["latency_ms"] > 0
        assert record["benchmark"] == "pose_graph" and record["source"] == "measured"
        assert record["command"].startswith("python -m bench pose_graph --keyframes 60")


def test_loop_detection_writes_the_time_per_keyframe(bench_results: Path) -> None:
    from bench.loop_detection import main

    assert main(["--only-long", "--long", "10", "--queries", "1", "--threads", "1"]) == 0
    (record,) = _records(bench_results / "loop_detection")
    assert record["case"] == {"area": "loop", "sequence": "10 keyframes", "mode": "loop detection per keyframe"}
    assert COLUMNS["loop"] <= set(record["values"]) and record["values"]["latency_ms"] > 0


def test_map_size_writes_its_own_record(bench_results: Path) -> None:
    from bench.map_size import main

    assert main(["--keyframes", "2", "--every", "6", "--report-every", "1", "--no-refine"]) == 0
    (record,) = _records(bench_results / "map_size")
    assert record["case"] == {"sequence": "synthetic seed 3", "mode": "rgbd mapping, fusion only",
                              "size": "2 keyframes every 6", "variant": record["case"]["variant"]}
    assert record["case"]["variant"].startswith("voxel cap ")
    values = record["values"]
    assert values["keyframes"] == 2 and values["surfels"] > 0 and values["rss_peak_mib"] > 0
    assert {"merge_ms", "refine_ms", "rss_mib"} <= set(values)
    assert [row["keyframes"] for row in record["rows"]] == [1, 2]
