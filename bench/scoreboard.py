"""The scoreboard: `python -m bench scoreboard` writes bench/RESULTS.md and the README's status block from the records
in bench/results/ (the newest record of each case), so neither is edited by hand. `--check` writes nothing and
fails when either differs from what the records make.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from bench.record import RESULTS_DIR, ROOT
from bench.scoreboard_areas import AREAS, MODES, SEQUENCES, STATUS, Area, Column, StatusRow

RESULTS_MD = ROOT / "bench" / "RESULTS.md"
README = ROOT / "README.md"
BEGIN, END = "<!-- status:begin -->", "<!-- status:end -->"
MAX_STATUS_ROWS = 12


def expand(raw: Any) -> list[dict[str, Any]]:
    """A file's records: a record, a list of them, or bench.out_of_box's case file (its live and offline runs)."""
    if isinstance(raw, list):
        return [r for item in raw for r in expand(item)]
    if "values" in raw:
        return [raw]
    if raw.get("benchmark") == "out_of_box" and "live" in raw:
        case = {"sequence": raw["source"], "mode": raw["mode"], "size": raw["size"]}
        common = {k: raw.get(k) for k in ("benchmark", "commit", "machine", "command", "date")}
        live = raw["live"]
        out = [{**common, "case": {"area": "live", **case}, "load": raw.get("load") or live.get("load"),
                "source": "measured",
                "values": {k: live.get(k) for k in ("posed_share", "latency_p50_ms", "latency_p95_ms", "finish_s",
                                                    "ate_m", "psnr_db", "rss_worker_peak_mib", "acked_lost")}}]
        offline = raw.get("offline")
        if offline:
            out.append({**common, "case": {"area": "offline", **case}, "load": None, "source": "measured",
                        "values": {"ate_m": offline.get("ate_m"), "psnr_db": offline.get("psnr"),
                                   "wall_s": offline.get("wall_s"), "fps": offline.get("fps")}})
        return out
    return []


def load_records(folder: Path = RESULTS_DIR) -> list[dict[str, Any]]:
    records = []
    for path in sorted(folder.rglob("*.json")):
        for record in expand(json.loads(path.read_text())):
            records.append({**record, "path": path.relative_to(folder).as_posix()})
    return records


def _case_id(case: dict[str, Any]) -> tuple[tuple[str, str], ...]:
    return tuple(sorted((k, str(v)) for k, v in case.items()))


def newest(records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """The newest record of each case (a record without a date counts as the oldest)."""
    best: dict[tuple, dict[str, Any]] = {}
    for record in records:
        key = _case_id(record["case"])
        if key not in best or (record.get("date") or "") >= (best[key].get("date") or ""):
            best[key] = record
    return list(best.values())


def fmt(value: Any, unit: str) -> str:
    if value is None:
        return "-"
    if unit == "cm":
        return f"{100 * value:.2f}"
    if unit == "%":
        return f"{100 * value:.1f} %"
    if unit in ("ms", "MiB", "fps", "B") and abs(value) >= 100:
        return f"{value:,.0f}"
    if unit in ("ms", "s", "MiB", "fps", "B"):
        return f"{value:.1f}"
    if unit == "dB":
        return f"{value:.2f}"
    return f"{value:g}" if isinstance(value, float) else str(value)


def target(column: Column | StatusRow, case: dict[str, Any]) -> str:
    goal = column.target
    if isinstance(goal, str):
        return goal
    sequence, mode = case.get("sequence", ""), case.get("mode", "")
    return goal.get(f"{sequence}/{mode}") or goal.get(mode) or goal.get("*") or "-"


def _row_target(column: Column) -> str:
    """The column's target for every case (shown once, in the target row); case-specific ones show in the cell."""
    if isinstance(column.target, str):
        return column.target
    return column.target.get("*", "-")


def _name(key: str, value: Any) -> str:
    return {"sequence": SEQUENCES, "mode": MODES}.get(key, {}).get(value, str(value))


def _origin(record: dict[str, Any]) -> str:
    source = record.get("source") or "measured"
    if source.startswith("transcribed from bench/journal/"):
        journal = source.removeprefix("transcribed from bench/journal/").split(" ", 1)[0]
        return f"transcribed: [{journal.removesuffix('.md')}](journal/{journal})"
    return f"measured: `results/{record['path']}`" if "path" in record else "measured"


def _when(record: dict[str, Any]) -> str:
    return " ".join(str(record[k]) for k in ("date", "commit") if record.get(k)) or "-"


def area_table(area: Area, records: list[dict[str, Any]]) -> str:
    keys = [k for k in area.case_keys if any(k in r["case"] for r in records)]
    columns = [c for c in area.columns if any(r["values"].get(c.key) is not None for r in records)]
    head = [*keys, *(f"{c.label} ({c.unit})" if c.unit and c.unit != "%" else c.label for c in columns),
            "date, commit", "source"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(keys) + "---:|" * len(columns) + "---|---|",
             "| " + " | ".join(["*target*", *[""] * (len(keys) - 1), *(f"*{_row_target(c)}*" for c in columns),
                                "", ""]) + " |"]
    order = sorted(records, key=lambda r: tuple(str(r["case"].get(k, "")) for k in keys))
    for record in order:
        cells = [_name(k, record["case"].get(k, "")) for k in keys]
        for column in columns:
            value = fmt(record["values"].get(column.key), column.unit)
            goal = target(column, record["case"])
            specific = goal not in ("-", _row_target(column)) and value != "-"
            cells.append(f"{value} ({goal})" if specific else value)
        note = f"; {record['note']}" if record.get("note") else ""
        cells += [_when(record), _origin(record) + note]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def results_md(records: list[dict[str, Any]]) -> str:
    current = newest(records)
    parts = ["# Benchmark scoreboard", "",
             "Generated by `python -m bench scoreboard` from the records in `bench/results/` (the newest of each "
             "case); do not edit by hand. Each table's first row gives the targets the issues state; a target that "
             "holds for one case only is in brackets beside its figure. "
             "\"transcribed\" figures were read from the journal (the narrative this file held until issue 45), not "
             "re-measured; the linked file says on which machine and load. The narrative is in "
             "[`bench/journal/`](journal/README.md).", ""]
    for area in AREAS:
        mine = [r for r in current if r["case"].get("area") == area.key]
        if not mine:
            continue
        parts += [f"## {area.title}", "", area.how, "", area_table(area, mine), ""]
    return "\n".join(parts)


def _find(records: list[dict[str, Any]], row: StatusRow) -> dict[str, Any] | None:
    for record in records:
        case = record["case"]
        if case.get("area") == row.area and "variant" not in case and all(
                str(case.get(k)) == v for k, v in row.case.items()):
            return record
    return None


def status_block(records: list[dict[str, Any]]) -> str:
    """The README's status table: one figure per row, at most MAX_STATUS_ROWS rows."""
    assert len(STATUS) <= MAX_STATUS_ROWS, "the README's status shows at most 12 rows"
    current = newest(records)
    lines = [BEGIN, "<!-- generated by `python -m bench scoreboard` from bench/results/: do not edit -->", "",
             "| figure | today | target | measured |", "|---|---:|---|---|"]
    for row in STATUS:
        record = _find(current, row)
        column = next((c for a in AREAS if a.key == row.area for c in a.columns if c.key == row.value), None)
        value = "-" if record is None or column is None else fmt(record["values"].get(row.value), column.unit)
        origin = "-" if record is None else ("transcribed" if str(record.get("source", "")).startswith(
            "transcribed") else "measured") + (f" {record['date'][:10]}" if record.get("date") else "")
        lines.append(f"| {row.label} | {value} | {row.target} | {origin} |")
    lines += ["", "Every area, mode and sequence with its target and source: [`bench/RESULTS.md`](bench/RESULTS.md).",
              END]
    return "\n".join(lines)


def replace_status(readme: str, block: str) -> str:
    start, end = readme.find(BEGIN), readme.find(END)
    if start < 0 or end < start:
        raise ValueError(f"README.md has no {BEGIN} ... {END} block")
    return readme[:start] + block + readme[end + len(END):]


def render(folder: Path = RESULTS_DIR, readme: str | None = None) -> tuple[str, str]:
    """(bench/RESULTS.md, README.md) as the records in `folder` make them."""
    records = load_records(folder)
    return results_md(records), replace_status(README.read_text() if readme is None else readme,
                                               status_block(records))


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench scoreboard", description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if either file is stale")
    args = parser.parse_args(argv)
    results, readme = render()
    stale = [p for p, text in ((RESULTS_MD, results), (README, readme)) if p.read_text() != text]
    if args.check:
        for path in stale:
            print(f"{path.relative_to(ROOT)} differs from the records: run `python -m bench scoreboard`")
        return 1 if stale else 0
    RESULTS_MD.write_text(results)
    README.write_text(readme)
    print(f"wrote {', '.join(str(p.relative_to(ROOT)) for p in stale) or 'nothing (up to date)'}")
    return 0
