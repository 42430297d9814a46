"""The web viewer (issue 22): bytes over the wire per map format, each format's round-trip error against the PLY,
and in headless Chromium (software WebGL through SwiftShader: a floor, a GPU does far better) the time from page
load to the first splat frame and the frame rate while orbiting, for a 50k- and a 500k-surfel map.

The maps are a real one (the engine's map of the bundled ICL sequence, or --ply) cut down to 50k surfels or tiled
(copies side by side) up to 500k. The page is the real viewer on a real stack; only the map bytes of its session
come from a loopback file server (the page's map requests are redirected there through the DevTools protocol),
since no session of the bundled data holds 500k surfels.
`python -m bench web_viewer [--ply MAP.ply] [--sizes 50000,500000]`.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "tests" / "viewer"))
FORMAT_NAMES = {"ply": "PLY, SH degree 0", "spz": "SPZ v3", "splat": ".splat"}  # the scoreboard's map_formats rows
WEBGL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def engine_map(frames: int = 24) -> bytes:
    """The real engine's map of the bundled ICL sequence (posed RGB-D, rgbd preset)."""
    from live_stack import LiveStack

    from client.sdk import FlashMonoClient
    from client.streaming import WireOptions, open_frames

    data = list(open_frames(REPO / "tests" / "data" / "icl_mini", max_frames=frames, stride=71 // frames,
                            use_gt_poses=True))
    with LiveStack(workers=1, engine="slam", extra_env={"FLASHMONO_LOG_LEVEL": "WARNING"}) as stack:
        with FlashMonoClient(stack.url) as client:
            session = client.create_session(intrinsics=data[0].intrinsics, preset="rgbd", name="bench-map",
                                            skip_frames=False)
            client.stream(session.id, data, wire=WireOptions(send_depth=True, send_pose=True), max_pending=4)
            return client.download_map(session.id)


def ply_of(arrays) -> bytes:
    """A 3DGS-layout PLY (SH degree 0) of SplatArrays."""
    from worker.mapping.ply import SH_C0, ply_with_sh_degree

    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    record = np.zeros(len(arrays), dtype=[(n, "<f4") for n in names])
    for i, axis in enumerate("xyz"):
        record[axis] = arrays.means[:, i]
    for c in range(3):
        record[f"f_dc_{c}"] = (arrays.colors[:, c] - 0.5) / SH_C0
    p = np.clip(arrays.opacities.astype(np.float64), 1e-6, 1 - 1e-6)
    record["opacity"] = np.log(p / (1 - p))
    for i in range(3):
        record[f"scale_{i}"] = np.log(np.maximum(arrays.scales[:, i], np.exp(-10.0)))
    for i in range(4):
        record[f"rot_{i}"] = arrays.quats[:, i]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(record)}"]
    header += [f"property float {n}" for n in names] + ["end_header"]
    return ply_with_sh_degree(("\n".join(header) + "\n").encode() + record.tobytes(), 0)


def resized(arrays, n: int, seed: int = 0):
    """`n` surfels: a random subset of the map, or copies of it side by side along x."""
    from worker.mapping.splat_arrays import SplatArrays

    fields = ("means", "scales", "quats", "opacities", "colors")
    if n <= len(arrays):
        keep = np.sort(np.random.default_rng(seed).choice(len(arrays), n, replace=False))
        return SplatArrays(**{f: getattr(arrays, f)[keep] for f in fields})
    copies = -(-n // len(arrays))
    extent = float(np.ptp(arrays.means[:, 0])) * 1.1
    parts = {f: np.concatenate([getattr(arrays, f)] * copies)[:n] for f in fields}
    parts["means"] = parts["means"].copy()
    parts["means"][:, 0] += np.repeat(np.arange(copies) * extent, len(arrays))[:n].astype(np.float32)
    return SplatArrays(**parts)


def round_trip(ply: bytes) -> list[dict]:
    from worker.mapping.map_formats import encode_map
    from worker.mapping.splat_arrays import splat_arrays_from_ply
    from worker.mapping.splat_file import decode_splat
    from worker.mapping.spz import decode_spz

    ref = splat_arrays_from_ply(ply)
    rows = [{"format": "ply", "bytes": len(ply), "per_surfel": len(ply) / len(ref)}]
    for fmt, decode in (("spz", decode_spz), ("splat", decode_splat)):
        t0 = time.perf_counter()
        body = encode_map(ply, fmt).body
        encode_s = time.perf_counter() - t0
        back = decode(body)
        q, r = back.quats.astype(np.float64), ref.quats.astype(np.float64)
        r = r * np.where((q * r).sum(1) < 0, -1.0, 1.0)[:, None]
        angle = np.degrees(4 * np.arcsin(np.clip(np.linalg.norm(q - r, axis=1) / 2, 0, 1)))
        rows.append({"format": fmt, "bytes": len(body), "per_surfel": len(body) / len(ref), "encode_s": encode_s,
                     "position_mm": 1000 * float(np.abs(back.means - ref.means).max()),
                     "colour_255": 255 * float(np.abs(back.colors - np.clip(ref.colors, 0, 1)).max()),
                     "opacity_255": 255 * float(np.abs(back.opacities - ref.opacities).max()),
                     "log_scale": float(np.abs(np.log(back.scales[:, :2] / ref.scales[:, :2])).max()),
                     "rotation_deg_mean": float(angle.mean()), "rotation_deg_max": float(angle.max())})
    return rows


class MapFiles:
    """A loopback HTTP server of map bodies by format (/spz, /splat, /ply) the page's map requests are sent to."""

    def __init__(self) -> None:
        import http.server
        import threading

        self.bodies: dict[str, bytes] = {}
        files = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                body = files.bodies.get(self.path.strip("/"))
                self.send_response(200 if body is not None else 404)
                self.send_header("Content-Type", "application/octet-stream")
                self.send_header("Content-Length", str(len(body or b"")))
                self.send_header("Access-Control-Allow-Origin", "*")
                self.end_headers()
                self.wfile.write(body or b"")

            def log_message(self, *args) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


async def page_figures(chromium: str, url: str, session_id: str, files: MapFiles, fmt: str) -> dict:
    from cdp import Browser

    async with Browser(chromium, extra_flags=WEBGL_FLAGS) as page:
        page.reply_timeout_s = 600
        await page.redirect(f"*/v1/sessions/{session_id}/map?format=*",
                            lambda u: next((f"{files.url}/{f}" for f in files.bodies if u.endswith(f"format={f}")),
                                           None))
        select = (f"(() => {{ const s = document.getElementById('splat-format'); s.value = '{fmt}';"
                  " s.dispatchEvent(new Event('change')); })()")
        await page.navigate(f"{url}/viewer?session={session_id}")
        if fmt != "spz":  # the page's default; choose before the first map request
            await page.wait_for("window.viewerState && window.viewerState.splat.ready", 60)
            await page.evaluate(select)
        loaded = await page.wait_for(f"window.viewerState.splat.map && window.viewerState.splat.map.format === '{fmt}'"
                                     " && window.viewerState.splat.map", 300)
        first = await page.wait_for("window.viewerState.splat.firstSplatFrameMs", 60)
        start = await page.evaluate("(() => { const v = window.splatView; v.orbit.autoRotate = true;"
                                    " v.orbit.autoRotateSpeed = 20; return [v.frames, performance.now()]; })()")
        await asyncio.sleep(8)
        await page.wait_for(f"window.splatView.frames >= {start[0] + 3}", 600)
        end = await page.evaluate("[window.splatView.frames, performance.now()]")
        fps = 1000 * (end[0] - start[0]) / (end[1] - start[1])  # over 8+ s and 3+ frames, re-sorting as it turns
        return {"format": fmt, "splats": loaded["splats"], "bytes": loaded["bytes"], "fetch_ms": loaded["fetchMs"],
                "decode_ms": loaded["ms"], "first_splat_frame_ms": first, "fps": fps,
                "errors": page.console_errors[:3]}


def round_trip_record(row: dict, surfels: int, real: bool, map_name: str) -> tuple[dict, dict]:
    """(case, values) of one round-trip row: the real map's rows feed the scoreboard's area "map_formats" (bytes per
    surfel); the resized maps' rows are records of their own."""
    values = {("bytes_per_surfel" if k == "per_surfel" else k): round(v, 4) if isinstance(v, float) else v
              for k, v in row.items() if k != "format"}
    mode = FORMAT_NAMES.get(row["format"], row["format"])
    if real:
        return {"area": "map_formats", "sequence": f"{map_name} ({surfels:,} surfels)", "mode": mode}, values
    return {"sequence": f"{map_name} resized to {surfels:,} surfels", "mode": mode, "variant": "round trip"}, values


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench web_viewer")
    parser.add_argument("--ply", help="a map PLY (default: the engine maps the bundled ICL sequence)")
    parser.add_argument("--sizes", default="50000,500000")
    parser.add_argument("--formats", default="spz,splat")
    args = parser.parse_args(argv)
    from bench.record import Recorder

    recorder = Recorder("web_viewer", argv)
    map_name = Path(args.ply).name if args.ply else "ICL map"
    from cdp import ensure_chromium
    from live_stack import LiveStack

    from client.sdk import FlashMonoClient
    from client.streaming import WireOptions, open_frames
    from worker.mapping.map_formats import encode_map
    from worker.mapping.ply import ply_with_sh_degree
    from worker.mapping.splat_arrays import splat_arrays_from_ply

    print(f"load average at the start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    base = Path(args.ply).read_bytes() if args.ply else engine_map()
    real = splat_arrays_from_ply(base)
    print(f"real map: {len(real)} surfels")
    print("format  surfels   bytes/surfel  encode s  position mm  colour /255  opacity /255  log scale  "
          "rot deg mean/max")
    for n in [len(real), *(int(s) for s in args.sizes.split(","))]:
        ply = ply_with_sh_degree(base, 0) if n == len(real) else ply_of(resized(real, n))
        for row in round_trip(ply):
            extra = "" if row["format"] == "ply" else (
                f"{row['encode_s']:8.2f}  {row['position_mm']:11.3f}  {row['colour_255']:11.2f}  "
                f"{row['opacity_255']:12.2f}  {row['log_scale']:9.4f}  {row['rotation_deg_mean']:.3f}/"
                f"{row['rotation_deg_max']:.3f}")
            print(f"{row['format']:6}  {n:8d}  {row['per_surfel']:12.2f}  {extra}")
            recorder.write(*round_trip_record(row, n, n == len(real), map_name))
    chromium = ensure_chromium()
    frames = list(open_frames(REPO / "tests" / "data" / "icl_mini", max_frames=8, stride=8, use_gt_poses=True))
    with LiveStack(workers=1, engine="passthrough") as stack:
        with FlashMonoClient(stack.url) as client:  # a session for the page: its poses, keyframes, status
            session = client.create_session(intrinsics=frames[0].intrinsics, name="bench-page", skip_frames=False)
            client.stream(session.id, frames, wire=WireOptions(send_pose=True))
        print("surfels  format  MB over the wire  fetch ms  decode ms  load->first splat frame ms  frames/s (orbiting)")
        files = MapFiles()
        for n in (int(s) for s in args.sizes.split(",")):
            ply = ply_of(resized(real, n))
            files.bodies = {fmt: encode_map(ply, fmt).body for fmt in ("ply", "spz", "splat")}
            for fmt in args.formats.split(","):
                r = asyncio.run(page_figures(chromium, stack.url, session.id, files, fmt))
                print(f"{n:7d}  {fmt:6}  {r['bytes'] / 1e6:16.2f}  {r['fetch_ms']:8.0f}  {r['decode_ms']:9.0f}  "
                      f"{r['first_splat_frame_ms']:26.0f}  {r['fps']:.2f}  {r['errors'] or ''}", flush=True)
                recorder.write({"sequence": f"{map_name} resized to {n:,} surfels", "mode": FORMAT_NAMES.get(fmt, fmt),
                                "variant": "page, SwiftShader"},
                               {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()})
        files.close()
    print(f"load average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
