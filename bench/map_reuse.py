"""Maps that outlive a session (issue 44): a map built live, saved, and sessions run in it, through `flashmono serve`
as a newcomer uses it (sessions as openapi.yaml documents them, no preset; 30 frames/s, a client that does not wait).

Per sequence x input mode, in one server:
- `whole`: one session over the whole sequence, no map: the peer a session in a map is measured against;
- `build`: a session over the first half, finished, saved with `POST /v1/maps`;
- `second_half` and `again` (the whole sequence played again): `localize` sessions in that map;
- `unrelated`: another sequence (another room) in the map: every relocalization there is a false one.
For each session in the map: frames posed, pose latency p50/p95, the time from the first frame's capture to the
`relocalized` message, the share of frames whose pose came after it (live in the map's world; every earlier pose is
revised into the map's world with it), and the ATE in the map's world: the build session's trajectory aligned to the
ground truth (SE(3); Sim(3) for RGB only) and that one alignment applied to the session in the map, no alignment of
its own. Also the map's size and, offline, its load time and memory. One JSON file per case under
`bench/results/map_reuse/` per session in the map (`run`: second_half, again), the whole case beside (`detail`);
a case already written is skipped, `--force` runs it again.

With `--together`, two devices map one room at once (issue 44 point 3): a session over the first third builds the
map, then two `extend` sessions stream the second and the last third concurrently (`together_case`).

`python -m bench map_reuse [--sequences icl tum] [--modes rgbd posed-rgb rgb] [--force] [--together]`
"""

from __future__ import annotations

import argparse
import asyncio
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.live import encode, load_frames, mode_inputs, stream_case
from bench.out_of_box import SEQUENCES, ServeProcess, case_args
from bench.record import Recorder, case_slug

ROOT = Path(__file__).resolve().parent.parent
SIZE = "320x240"
UNRELATED = {"icl": "tum", "tum": "icl"}  # another room for each map


def _session(stack: ServeProcess, frames, intrinsics, mode: str, fields: dict[str, Any] | None = None
             ) -> dict[str, Any]:
    """One live session of `frames` (as openapi.yaml documents it, plus `fields`); its summary, run and poses."""
    import httpx

    args = case_args(mode, SIZE, None)
    args.psnr_every = 0
    args.session_fields = fields or {}
    with_depth, with_pose = mode_inputs(mode)
    result = asyncio.run(stream_case(stack, frames, intrinsics, encode(frames, with_depth, with_pose), args))
    sid = result["summary"]["session"]
    poses = httpx.get(f"{stack.base_url}/v1/sessions/{sid}/trajectory", timeout=60).json()["poses"]
    result["poses"] = {int(p["seq"]): np.asarray(p["pose"], np.float64).reshape(4, 4) for p in poses}
    return result


def _alignment(poses: dict[int, np.ndarray], frames, rgb_only: bool) -> np.ndarray:
    """The transform that takes a session's world to the ground truth's (SE(3), Sim(3) for RGB only)."""
    from worker.eval.metrics import alignment_transform

    seqs = [i for i in sorted(poses) if frames[i].gt_pose is not None]
    est = np.stack([poses[i][:3, 3] for i in seqs])
    ref = np.stack([np.asarray(frames[i].gt_pose)[:3, 3] for i in seqs])
    return alignment_transform(est, ref, "sim3" if rgb_only else "se3")


def _ate_in(world_to_gt: np.ndarray, poses: dict[int, np.ndarray], frames) -> float | None:
    """RMSE of the positions moved by `world_to_gt` against the ground truth (no alignment of their own)."""
    seqs = [i for i in sorted(poses) if frames[i].gt_pose is not None]
    if len(seqs) < 3:
        return None
    est = np.stack([poses[i][:3, 3] for i in seqs]) @ world_to_gt[:3, :3].T + world_to_gt[:3, 3]
    ref = np.stack([np.asarray(frames[i].gt_pose)[:3, 3] for i in seqs])
    return float(np.sqrt(np.mean(np.sum((est - ref) ** 2, axis=1))))


def _in_map_figures(result: dict[str, Any], map_id: str, world_to_gt: np.ndarray | None, frames) -> dict[str, Any]:
    """What a session in the map showed (see the module docstring)."""
    run, summary = result["run"], result["summary"]
    relocalized = [(t, m) for t, m in run.events if m.get("type") == "relocalized" and m.get("map_id") == map_id]
    first = relocalized[0] if relocalized else None
    in_map = sum(1 for f in run.frames if f.pose is not None and first is not None and f.pose >= first[0])
    out = {
        "frames": summary["frames"], "posed_share": summary["with_pose"] / max(1, summary["frames"]),
        "latency_p50_ms": summary["latency_ms"][50], "latency_p95_ms": summary["latency_ms"][95],
        "finish_s": summary["finish_s"], "rss_worker_peak_mib": summary["rss_worker_peak_mib"],
        "relocalizations": len(relocalized),
        "first_pose_in_map_s": None if first is None else first[0] - run.start,
        "relocalized_at_seq": None if first is None else first[1].get("seq"),
        "relocalization": None if first is None else {k: first[1].get(k) for k in (
            "frame", "keyframe", "inliers", "matches", "reprojection_px", "depth_agreement")},
        "live_in_map_share": in_map / max(1, summary["frames"]),
        "map_drift_corrections": sum(1 for _, m in run.events if m.get("type") == "drift_corrected"
                                     and m.get("source") == "map"),
        "priors_from_other_sessions": sum(m.get("from_other_sessions") or 0 for _, m in run.events
                                          if m.get("type") == "drift_corrected"),
        "acked_lost": summary["acked_lost"],
    }
    out["ate_in_map_m"] = (None if world_to_gt is None or first is None
                           else _ate_in(world_to_gt, result["poses"], frames))
    return out


def _map_load(stack: ServeProcess, map_id: str) -> dict[str, Any]:
    """The map's size, and offline what loading it takes: decoding, the localizer's places, the renderable map."""
    import httpx

    from protocol.map_package import decode_package
    from worker.maps.session_in_map import SessionInMap

    data = httpx.get(f"{stack.base_url}/v1/maps/{map_id}/export", timeout=120).content
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    package = decode_package(data)
    t1 = time.perf_counter()
    in_map = SessionInMap.from_package(map_id, 1, "localize", package)
    places = len(in_map.localizer)
    t2 = time.perf_counter()
    in_map.renderer(None)._loaded()
    t3 = time.perf_counter()
    return {"size_bytes": len(data), "keyframes": len(package.keyframes), "places": places,
            "decode_s": t1 - t0, "places_s": t2 - t1, "renderable_s": t3 - t2,
            "peak_rss_growth_mib": (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024}


def run_case(stack: ServeProcess, name: str, source: Path, other: Path | None, mode: str) -> dict[str, Any]:
    import httpx

    width, height = (int(v) for v in SIZE.split("x"))
    with_depth, with_pose = mode_inputs(mode)
    frames, intrinsics = load_frames(str(source), (width, height), None, with_depth, with_pose)
    half = len(frames) // 2
    rgb_only = mode == "rgb"
    out: dict[str, Any] = {}
    whole = _session(stack, frames, intrinsics, mode)
    peer_ate = whole["summary"]["ate_m"]
    out["whole"] = {"ate_m": peer_ate, "posed_share": whole["summary"]["with_pose"] / len(frames),
                    "latency_p95_ms": whole["summary"]["latency_ms"][95]}
    build = _session(stack, frames[:half], intrinsics, mode)
    world_to_gt = _alignment(build["poses"], frames, rgb_only)
    out["build"] = {"frames": half, "ate_m": build["summary"]["ate_m"], "finish_s": build["summary"]["finish_s"]}
    saved = httpx.post(f"{stack.base_url}/v1/maps", json={"session_id": build["summary"]["session"],
                                                           "name": f"{name} {mode}"}, timeout=300)
    saved.raise_for_status()
    map_id = saved.json()["id"]
    out["map"] = {"id": map_id, "meta": saved.json()["meta"], **_map_load(stack, map_id)}
    second = _session(stack, frames[half:], intrinsics, mode, {"map_id": map_id})
    out["second_half"] = _in_map_figures(second, map_id, world_to_gt, frames[half:])
    again = _session(stack, frames, intrinsics, mode, {"map_id": map_id})
    out["again"] = _in_map_figures(again, map_id, world_to_gt, frames)
    if other is not None:
        unrelated, other_intrinsics = load_frames(str(other), (width, height), None, with_depth, with_pose)
        result = _session(stack, unrelated, other_intrinsics, mode, {"map_id": map_id})
        figures = _in_map_figures(result, map_id, None, unrelated)
        out["unrelated"] = {"sequence": other.name, "frames": figures["frames"],
                            "relocalizations": figures["relocalizations"],
                            "false_per_1000_frames": 1000 * figures["relocalizations"] / max(1, figures["frames"]),
                            "latency_p95_ms": figures["latency_p95_ms"]}
    out["peer_ate_m"] = peer_ate
    return out


async def _concurrent(stack: ServeProcess, runs: list[tuple[list, Any, dict[str, Any]]], mode: str) -> list[dict]:
    """Several live sessions streaming at once (two devices), each as `_session` streams one."""
    import httpx

    with_depth, with_pose = mode_inputs(mode)
    jobs = []
    for frames, intrinsics, fields in runs:
        args = case_args(mode, SIZE, None)
        args.psnr_every, args.session_fields = 0, fields
        jobs.append(stream_case(stack, frames, intrinsics, encode(frames, with_depth, with_pose), args))
    results = await asyncio.gather(*jobs)
    async with httpx.AsyncClient(base_url=stack.base_url, timeout=60) as http:
        for result in results:
            sid = result["summary"]["session"]
            poses = (await http.get(f"/v1/sessions/{sid}/trajectory")).json()["poses"]
            result["poses"] = {int(p["seq"]): np.asarray(p["pose"], np.float64).reshape(4, 4) for p in poses}
    return results


def together_case(stack: ServeProcess, name: str, source: Path, mode: str) -> dict[str, Any]:
    """Two devices mapping one room together (issue 44 point 3): a session over the first third builds the map;
    two `extend` sessions then stream the second and the last third at the same time, each at 30 frames/s. Each
    device's ATE in the map's world (the build's alignment, none of their own), both together, the peer (one
    session over the last two thirds, no map), and the map's versions and sessions afterwards."""
    import httpx

    width, height = (int(v) for v in SIZE.split("x"))
    with_depth, with_pose = mode_inputs(mode)
    frames, intrinsics = load_frames(str(source), (width, height), None, with_depth, with_pose)
    third = len(frames) // 3
    rgb_only = mode == "rgb"
    build = _session(stack, frames[:third], intrinsics, mode)
    world_to_gt = _alignment(build["poses"], frames, rgb_only)
    saved = httpx.post(f"{stack.base_url}/v1/maps", json={"session_id": build["summary"]["session"],
                                                           "name": f"{name} {mode} together"}, timeout=300)
    saved.raise_for_status()
    map_id = saved.json()["id"]
    parts = {"device_a": frames[third:2 * third], "device_b": frames[2 * third:]}
    extend = {"map_id": map_id, "map_mode": "extend"}
    results = asyncio.run(_concurrent(stack, [(part, intrinsics, extend) for part in parts.values()], mode))
    out: dict[str, Any] = {"map_id": map_id, "build": {"frames": third, "ate_m": build["summary"]["ate_m"]}}
    joint_est, joint_ref = [], []
    for (device, part), result in zip(parts.items(), results):
        out[device] = _in_map_figures(result, map_id, world_to_gt, part)
        out[device]["session"] = result["summary"]["session"]
        for seq, pose in result["poses"].items():
            if part[seq].gt_pose is not None:
                joint_est.append(world_to_gt[:3, :3] @ pose[:3, 3] + world_to_gt[:3, 3])
                joint_ref.append(np.asarray(part[seq].gt_pose)[:3, 3])
    out["together_ate_in_map_m"] = float(np.sqrt(np.mean(np.sum((np.stack(joint_est) - np.stack(joint_ref)) ** 2,
                                                                  axis=1))))
    peer = _session(stack, frames[third:], intrinsics, mode)
    out["peer_ate_m"] = peer["summary"]["ate_m"]
    stored = httpx.get(f"{stack.base_url}/v1/maps/{map_id}", timeout=60).json()
    members = httpx.get(f"{stack.base_url}/v1/maps/{map_id}/sessions", timeout=60).json()
    out["map_after"] = {"versions": [{"version": v["version"], "session_id": v["session_id"],
                                      "keyframes": v["meta"].get("keyframes"), "surfels": v["meta"].get("surfels")}
                                     for v in stored.get("versions", [])],
                        "sessions": members}
    return out


def _source(name: str) -> Path | None:
    return next((p for p in SEQUENCES[name] if p.is_dir()), None)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench map_reuse", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", nargs="+", choices=sorted(SEQUENCES), default=["icl", "tum"])
    parser.add_argument("--modes", nargs="+", choices=["rgbd", "posed-rgbd", "posed-rgb", "rgb"],
                        default=["rgbd", "posed-rgb", "rgb"])
    parser.add_argument("--force", action="store_true", help="run cases whose results exist again")
    parser.add_argument("--together", action="store_true", help="two devices extending one map at once instead")
    args = parser.parse_args(argv)
    recorder = Recorder("map_reuse", argv)
    if args.together:
        return _together(args, recorder)
    cases = [(n, _source(n), m) for n in args.sequences for m in args.modes if _source(n) is not None]
    todo = [c for c in cases if args.force or not (recorder.folder / f"{case_slug(_case(c, 'again'))}.json").exists()]
    print(f"{len(cases)} cases, {len(todo)} to run", flush=True)
    if not todo:
        return 0
    with ServeProcess() as stack:
        for name, source, mode in todo:
            started = time.monotonic()
            figures = run_case(stack, name, source, _source(UNRELATED[name]), mode)
            figures["wall_s"] = round(time.monotonic() - started, 1)
            for run in ("second_half", "again"):
                recorder.write(_case((name, source, mode), run), _values(figures, run), detail=figures)
            again, second = figures["again"], figures["second_half"]
            print(f"{name} {mode}: peer ATE {_cm(figures['peer_ate_m'])} | in map: second half ATE "
                  f"{_cm(second['ate_in_map_m'])}, first pose in map {_s(second)}, live in map "
                  f"{second['live_in_map_share']:.1%}, p95 {second['latency_p95_ms']:.0f} ms | again ATE "
                  f"{_cm(again['ate_in_map_m'])}, {_s(again)}, {again['live_in_map_share']:.1%} | unrelated "
                  f"{figures.get('unrelated', {}).get('relocalizations')} relocalized", flush=True)
    return 0


def _together(args: argparse.Namespace, recorder: Recorder) -> int:
    with ServeProcess() as stack:
        for name in args.sequences:
            source = _source(name)
            if source is None:
                continue
            for mode in args.modes:
                started = time.monotonic()
                figures = together_case(stack, name, source, mode)
                figures["wall_s"] = round(time.monotonic() - started, 1)
                a, b = figures["device_a"], figures["device_b"]
                recorder.write({**_case((name, source, mode), "together")},
                               {"together_ate_in_map_m": figures["together_ate_in_map_m"],
                                "peer_ate_m": figures["peer_ate_m"],
                                "device_a_ate_in_map_m": a["ate_in_map_m"], "device_b_ate_in_map_m": b["ate_in_map_m"],
                                "device_a_first_pose_in_map_s": a["first_pose_in_map_s"],
                                "device_b_first_pose_in_map_s": b["first_pose_in_map_s"],
                                "device_a_posed_share": a["posed_share"], "device_b_posed_share": b["posed_share"],
                                "device_a_latency_p95_ms": a["latency_p95_ms"],
                                "device_b_latency_p95_ms": b["latency_p95_ms"],
                                "device_a_priors_from_b": a["priors_from_other_sessions"],
                                "device_b_priors_from_a": b["priors_from_other_sessions"]}, detail=figures)
                print(f"{name} {mode} together: ATE in the map's world {_cm(a['ate_in_map_m'])} / "
                      f"{_cm(b['ate_in_map_m'])}, both {_cm(figures['together_ate_in_map_m'])} (peer "
                      f"{_cm(figures['peer_ate_m'])}); first pose in map {_s(a)} / {_s(b)}; posed "
                      f"{a['posed_share']:.1%} / {b['posed_share']:.1%}; p95 {a['latency_p95_ms']:.0f} / "
                      f"{b['latency_p95_ms']:.0f} ms; priors from the other device {a['priors_from_other_sessions']} / "
                      f"{b['priors_from_other_sessions']}; map versions {len(figures['map_after']['versions'])}",
                      flush=True)
    return 0


def _case(case: tuple[str, Path, str], run: str) -> dict[str, str]:
    _, source, mode = case
    return {"sequence": source.name, "mode": mode, "size": SIZE, "run": run, "area": "map_reuse"}


def _values(figures: dict[str, Any], run: str) -> dict[str, Any]:
    """A session in the map's figures, with the peer's ATE, the other room's false relocalizations and the map's
    size beside them."""
    own = figures[run]
    unrelated = figures.get("unrelated") or {}
    return {"live_in_map_share": own["live_in_map_share"], "first_pose_in_map_s": own["first_pose_in_map_s"],
            "ate_in_map_m": own["ate_in_map_m"], "peer_ate_m": figures["peer_ate_m"],
            "latency_p95_ms": own["latency_p95_ms"], "posed_share": own["posed_share"],
            "false_per_1000_frames": unrelated.get("false_per_1000_frames"),
            "map_bytes": figures["map"]["size_bytes"]}


def _cm(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.2f} cm"


def _s(figures: dict[str, Any]) -> str:
    value = figures["first_pose_in_map_s"]
    return "never" if value is None else f"{value:.2f} s"
