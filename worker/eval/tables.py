"""Paper-style tables (markdown) from per-sequence metrics dicts.

A metrics dict is what `flashmono run` writes to metrics.json: at least ate_rmse (metres), psnr, ssim, depth_l1
(metres), fps, num_gaussians, and optionally lpips, sequence, method, dataset, num_frames, runtime_s. Rows are
methods, columns sequences, as in the paper: Table 1 (ATE), Table 2 (SSIM/LPIPS/PSNR + FPS per dataset), Table 5
(mean depth L1 per dataset).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

DEFAULT_METHOD = "Ours"


def load_metrics(paths: Iterable[str | Path]) -> list[dict]:
    """Read metrics.json files; a missing `sequence` is taken from the file's folder name."""
    rows = []
    for path in paths:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"cannot read metrics from {path}: {exc}") from exc
        if not isinstance(data, dict):
            raise ValueError(f"{path}: metrics must be a JSON object")
        data.setdefault("sequence", path.parent.name or path.stem)
        rows.append(data)
    return rows


def _number(value) -> float | None:
    if value is None:
        return None
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(value) else value


def _fmt(value, digits: int) -> str:
    value = _number(value)
    if value is None:
        return "-"
    return "inf" if math.isinf(value) else f"{value:.{digits}f}"


def _markdown(header: Sequence[str], rows: Sequence[Sequence[str]], title: str) -> str:
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    def line(cells):
        return "| " + " | ".join(str(c).ljust(w) for c, w in zip(cells, widths)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([title, "", line(header), sep, *(line(r) for r in rows)]) + "\n"


def _methods_and_sequences(metrics: Sequence[dict]) -> tuple[list[str], list[str]]:
    if not metrics:
        raise ValueError("no metrics to tabulate")
    methods, sequences = [], []
    for i, m in enumerate(metrics):
        if not isinstance(m, dict):
            raise ValueError(f"metrics[{i}] is not a dict")
        method, sequence = m.get("method", DEFAULT_METHOD), str(m.get("sequence", f"seq{i}"))
        if method not in methods:
            methods.append(method)
        if sequence not in sequences:
            sequences.append(sequence)
    return methods, sequences


def _lookup(metrics: Sequence[dict]) -> dict[tuple[str, str], dict]:
    return {(m.get("method", DEFAULT_METHOD), str(m.get("sequence", f"seq{i}"))): m for i, m in enumerate(metrics)}


def ate_table(metrics: Sequence[dict], unit: str = "cm") -> str:
    """Table 1 (cm, ScanNet/BundleFusion) or Table 3 (unit="m", KITTI): ATE RMSE per sequence, one row per method."""
    factors = {"cm": 100.0, "m": 1.0, "mm": 1000.0}
    if unit not in factors:
        raise ValueError(f"unit must be one of {sorted(factors)}, got {unit!r}")
    methods, sequences = _methods_and_sequences(metrics)
    table = _lookup(metrics)
    rows = []
    for method in methods:
        cells = [method]
        for seq in sequences:
            ate = _number(table.get((method, seq), {}).get("ate_rmse"))
            cells.append(_fmt(None if ate is None else ate * factors[unit], 2))
        rows.append(cells)
    return _markdown([f"ATE RMSE [{unit}]"] + sequences, rows, f"ATE RMSE ({unit}), lower is better")


def pooled_fps(entries: Sequence[dict]) -> float | None:
    """End-to-end FPS of several runs: total frames / total runtime when both are known, else the mean fps."""
    frames = [_number(e.get("num_frames")) for e in entries]
    runtimes = [_number(e.get("runtime_s")) for e in entries]
    if entries and all(f is not None for f in frames) and all(r is not None and r > 0 for r in runtimes):
        return sum(frames) / sum(runtimes)
    values = [v for v in (_number(e.get("fps")) for e in entries) if v is not None]
    return sum(values) / len(values) if values else None


def mapping_table(metrics: Sequence[dict]) -> str:
    """Table 2: SSIM, LPIPS and PSNR per sequence (three rows per method) and the method's end-to-end FPS."""
    methods, sequences = _methods_and_sequences(metrics)
    table = _lookup(metrics)
    rows = []
    for method in methods:
        entries = [table[(method, s)] for s in sequences if (method, s) in table]
        fps = _fmt(pooled_fps(entries), 2)
        for key, label, digits in (("ssim", "SSIM ↑", 3), ("lpips", "LPIPS ↓", 3), ("psnr", "PSNR ↑", 2)):
            cells = [method if key == "ssim" else "", label]
            cells += [_fmt(table.get((method, s), {}).get(key), digits) for s in sequences]
            cells.append(fps if key == "ssim" else "")
            rows.append(cells)
    return _markdown(["Method", "Metric"] + sequences + ["FPS ↑"], rows, "Mapping quality (rendering on non-keyframes)")


def depth_table(metrics: Sequence[dict]) -> str:
    """Table 5: mean depth L1 (m) per dataset (the `dataset` key; all sequences together when absent)."""
    methods, _ = _methods_and_sequences(metrics)
    datasets: list[str] = []
    for m in metrics:
        if m.get("dataset", "all") not in datasets:
            datasets.append(m.get("dataset", "all"))
    rows = []
    for method in methods:
        cells = [method]
        for dataset in datasets:
            values = [_number(m.get("depth_l1")) for m in metrics
                      if m.get("method", DEFAULT_METHOD) == method and m.get("dataset", "all") == dataset]
            values = [v for v in values if v is not None]
            cells.append(_fmt(sum(values) / len(values) if values else None, 3))
        rows.append(cells)
    return _markdown(["L1 (m) ↓"] + datasets, rows, "Mean depth L1 error (m), lower is better")


def all_tables(metrics: Sequence[dict], ate_unit: str = "cm") -> str:
    """Tables 1, 2 and 5 one after the other."""
    return "\n".join([ate_table(metrics, ate_unit), mapping_table(metrics), depth_table(metrics)])
