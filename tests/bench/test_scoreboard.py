"""The scoreboard (bench/scoreboard.py) from real record files: newest record per case, the README's block, no drift."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import record, scoreboard
from bench.scoreboard_areas import STATUS

ICL = "icl_livingroom1_micro"


def _write(folder: Path, name: str, case: dict, values: dict, date: str, source: str = "measured") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps({
        "benchmark": "live", "case": case, "values": values, "commit": "abc1234",
        "machine": {"cores": 2, "cpu": "test", "gpu": None}, "load": [1.0, 1.2], "command": "python -m bench live",
        "date": date, "source": source}))


def _readme() -> str:
    return f"# X\n\n## Status\n\n{scoreboard.BEGIN}\nold\n{scoreboard.END}\n\n## Next\n"


def test_newest_record_of_a_case_wins_and_tables_follow(tmp_path: Path) -> None:
    case = {"area": "live", "sequence": ICL, "mode": "rgbd", "size": "320x240"}
    _write(tmp_path / "live", "old.json", case, {"latency_p95_ms": 250.0, "posed_share": 0.5}, "2026-01-01 00:00:00")
    _write(tmp_path / "live", "new.json", case, {"latency_p95_ms": 42.0, "posed_share": 0.995}, "2026-02-01 00:00:00")
    tiny = {"area": "frontend", "sequence": "224x160", "mode": "tiny, CPU fp32, 2 threads"}
    _write(tmp_path / "other", "t.json", tiny, {"latency_ms": 41.9}, None,
           "transcribed from bench/journal/02-frontend.md (section Frontend)")

    results, readme = scoreboard.render(tmp_path, _readme())

    live = results.split("## Live")[1].split("\n## ")[0]
    assert "| ICL living room (211 frames) | RGB-D | 320x240 | 99.5 % | 42.0 |" in live
    assert "250" not in live and "50.0 %" not in live
    assert "| *target* |  |  | *>= 90 %* | *<= 100* |" in live
    assert "transcribed: [02-frontend](journal/02-frontend.md)" in results
    block = readme.split(scoreboard.BEGIN)[1].split(scoreboard.END)[0]
    assert "old" not in block and readme.endswith("## Next\n")
    assert "| live ICL RGB-D 320x240: pose latency p95 (ms) | 42.0 | <= 100 | measured 2026-02-01 |" in block
    assert "| `tiny` frontend 224x160, CPU: per frame (ms) | 41.9 | <= 50 | transcribed |" in block
    # a row whose record is missing shows "-", never a figure from elsewhere
    assert "| service, 32 sessions at 30 FPS: ack p99 (ms) | - | <= 20 | - |" in block


def test_readme_block_has_at_most_twelve_rows(tmp_path: Path) -> None:
    _, readme = scoreboard.render(tmp_path, _readme())
    block = readme.split(scoreboard.BEGIN)[1].split(scoreboard.END)[0]
    rows = [line for line in block.splitlines() if line.startswith("| ") and not line.startswith("| figure")]
    assert len(rows) == len(STATUS) <= 12


def test_out_of_box_case_file_reads_as_live_and_offline_records(tmp_path: Path) -> None:
    raw = {"benchmark": "out_of_box", "sequence": "tum", "source": "tum_fr1_xyz", "mode": "rgb", "size": "320x240",
           "commit": "c0ffee0", "machine": {"cores": 2}, "command": "python -m bench out_of_box", "date": "2026-03-01",
           "live": {"posed_share": 1.0, "latency_p95_ms": 59.0, "ate_m": 0.0414, "load": [3.2, 2.6]},
           "offline": {"ate_m": 0.0196, "psnr": 20.65, "wall_s": 105.8}}
    (tmp_path / "tum_rgb_320x240.json").write_text(json.dumps(raw))
    records = {r["case"]["area"]: r for r in scoreboard.load_records(tmp_path)}
    assert records["live"]["values"]["ate_m"] == 0.0414 and records["live"]["load"] == [3.2, 2.6]
    assert records["offline"]["values"] == {"ate_m": 0.0196, "psnr_db": 20.65, "wall_s": 105.8, "fps": None}
    assert records["offline"]["case"] == {"area": "offline", "sequence": "tum_fr1_xyz", "mode": "rgb",
                                          "size": "320x240"}


def test_a_readme_without_markers_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="status:begin"):
        scoreboard.render(tmp_path, "# no block\n")


def test_recorder_writes_one_file_per_case(tmp_path: Path) -> None:
    recorder = record.Recorder("live", ["--mode", "rgb"], folder=tmp_path)
    path = recorder.write({"area": "live", "sequence": "icl_mini", "mode": "rgb", "size": "320x240"},
                          {"latency_p95_ms": 12.5})
    assert path.name == "live_icl_mini_rgb_320x240.json"
    written = json.loads(path.read_text())
    assert set(written) == {"benchmark", "case", "values", "commit", "machine", "load", "command", "date", "source"}
    assert written["command"] == "python -m bench live --mode rgb" and written["source"] == "measured"
    assert len(written["load"]) == 2 and written["machine"]["cores"] >= 1 and "gpu" in written["machine"]
    assert scoreboard.load_records(tmp_path)[0]["values"] == {"latency_p95_ms": 12.5}


def test_committed_scoreboard_and_readme_match_the_committed_records() -> None:
    """bench/RESULTS.md and the README's status block cannot drift from bench/results/."""
    results, readme = scoreboard.render()
    assert scoreboard.RESULTS_MD.read_text() == results, "run `python -m bench scoreboard`"
    assert scoreboard.README.read_text() == readme, "run `python -m bench scoreboard`"


def test_every_figure_traces_to_a_source() -> None:
    for rec in scoreboard.load_records():
        source = rec.get("source", "")
        assert source == "measured" or source.startswith("transcribed from bench/journal/"), rec["path"]
        if source.startswith("transcribed"):
            journal = source.removeprefix("transcribed from ").split(" ", 1)[0]
            assert (record.ROOT / journal).is_file(), journal
