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


def _transcribed_cases() -> list[dict]:
    cases = []
    for path in (RESULTS_DIR / "transcribed").glob("*.json"):
        raw = json.loads(path.read_text())
        cases += [r["case"] for r in (raw if isinstance(raw, list) else [raw])]
    return cases


def test_default_runs_name_their_cases_as_the_transcribed_records_do() -> None:
    """A fresh run at the settings the scoreboard quotes replaces the transcribed record of its case."""
    import argparse

    from bench.hole_fill import record as hole_fill_record
    from bench.long_session import record_case as long_case
    from bench.mvs import DATA
    from bench.pose_graph import record_cases
    from bench.render import record_case as render_case
    from bench.training import SHIPPED
    from bench.training import record_case as training_case
    from bench.web_viewer import round_trip_record

    transcribed = _transcribed_cases()
    long_args = argparse.Namespace(source="icl", frames=18000, mode="rgbd", size="320x240", preset="rgbd",
                                   kill_at=None, no_finish=False)
    row = {"borders_l1": 0.04, "borders_cov": 0.75, "planes_l1": 0.05, "planes_cov": 0.7, "stereo_l1": 0.04,
           "cov_before": 0.5, "filled": 0.1}
    produced = [
        *record_cases(2000, 100, per_keyframe=True, threshold=None),
        long_case(long_args),
        render_case(320, 240, 50_000, "cpu", 2),
        render_case(320, 240, 50_000, "gsplat", 2),
        training_case("synthetic (held out)", str(SHIPPED), argparse.Namespace(synthetic=10, frames=24,
                                                                              first_seed=10_000)),
        round_trip_record({"format": "spz", "bytes": 1, "per_surfel": 14.5}, 68_614, True, "ICL map")[0],
        hole_fill_record([row], argparse.Namespace(sequence=None, data=DATA, every=6, resize=(320, 240)))[0],
        hole_fill_record([row], argparse.Namespace(sequence="TUM fr3/cabinet", data=DATA, every=6,
                                                   resize=(320, 240)))[0],
    ]
    for case in produced:
        assert case in transcribed, case
