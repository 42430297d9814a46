"""Cameras as they come (issue 43 point 4), live through `flashmono serve`, sessions as openapi.yaml documents them.

- **A Kinect as it records** (TUM fr1/xyz, 788 frames): the raw frames (lens distortion and all, 320x240 as a phone
  would send them) with TUM's published calibration in the session's intrinsics, streamed at 30 frames/s; beside
  them in the same run the same raw frames sent without their lens, and the frames TUM's calibration undistorted
  offline (`../shared/data/tum_fr1_xyz`, the out_of_box case). ATE against the motion capture; PSNR of rendered
  non-keyframes against the offline-undistorted frames (the lens cases: the session's own undistortion is not the
  reference).
- **Phone photos** (instant-ngp's fox: 50 photos 1080x1920, COLMAP poses, k1 0.058 k2 -0.081): posed RGB, every 8th
  photo held out, streamed with their lens; a held-out photo's view rendered at its pose against the photo
  undistorted by OpenCV at full size (to the session's pinhole camera, then area-downscaled to the render's size);
  beside it the same photos sent without their lens, scored against the photo as taken.

Data fetched, not shipped: `--tum-raw DIR` (TUM's `rgbd_dataset_freiburg1_xyz` folder, `rgb/` and `depth/`),
`--fox DIR` (a transforms.json folder). Records go to `bench/results/lens/`.

`python -m bench lens --tum-raw DIR [--fox DIR] [--cases ...] [--frames N]`
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np

from bench.live import load_frames
from bench.out_of_box import ServeProcess, case_args, live_figures
from bench.record import Recorder, loadavg

ROOT = Path(__file__).resolve().parent.parent
TUM = ROOT.parent / "shared" / "data" / "tum_fr1_xyz"
TUM_CASES = ("rgbd-lens", "rgbd-no-lens", "rgbd-undistorted", "rgb-lens", "rgb-no-lens", "rgb-undistorted")
FOX_CASES = ("fox-lens", "fox-no-lens")
HOLD_OUT_EVERY = 8


def tum_calibration() -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """(raw camera at 640x480, its lens, the offline-undistorted pinhole camera at 320x240) of TUM fr1."""
    meta = json.loads((TUM / "intrinsics.json").read_text())
    raw = meta["source_intrinsics_640x480"]
    k1, k2, p1, p2, k3 = raw["dist_k1_k2_p1_p2_k3"]
    camera = {"fx": raw["fx"], "fy": raw["fy"], "cx": raw["cx"], "cy": raw["cy"], "width": 640, "height": 480}
    lens = {"model": "radtan", "k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3}
    pinhole = {k: meta[k] for k in ("fx", "fy", "cx", "cy", "width", "height")}
    return camera, lens, pinhole


def raw_tum_messages(raw_dir: Path, count: int, with_depth: bool, size: tuple[int, int] = (640, 480)
                     ) -> list[bytes]:
    """The first `count` frames of the shared sequence as the Kinect recorded them: the raw colour frame at `size`
    (640x480 as recorded, or area-downscaled; JPEG q95), its raw depth (TUM's 5000 units/m as millimetres,
    nearest), no per-frame intrinsics (the session's carry the lens)."""
    rows = [line.split() for line in (TUM / "source_frames.txt").read_text().splitlines()
            if not line.startswith("#")][:count]
    messages = []
    for seq, (_, _, rgb_file, _, depth_file, _) in enumerate(rows):
        colour = cv2.resize(cv2.imread(str(raw_dir / rgb_file)), size, interpolation=cv2.INTER_AREA)
        message = {"type": "frame", "seq": seq, "timestamp": seq / 30.0,
                   "image": cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()}
        if with_depth:
            raw = cv2.imread(str(raw_dir / depth_file), cv2.IMREAD_UNCHANGED).astype(np.float64)
            depth = cv2.resize(np.round(raw / 5.0).astype(np.uint16), size, interpolation=cv2.INTER_NEAREST)
            message["depth"] = cv2.imencode(".png", depth)[1].tobytes()
        messages.append(msgpack.packb(message, use_bin_type=True))
    return messages


def tum_case(stack: ServeProcess, case: str, raw_dir: Path, frames_cap: int | None,
             raw_size: tuple[int, int] = (640, 480)) -> dict[str, Any]:
    from bench.live import encode

    mode, variant = case.split("-", 1)
    with_depth = mode == "rgbd"
    frames, undistorted = load_frames(str(TUM), (320, 240), frames_cap, with_depth=with_depth)
    args = case_args(mode, "320x240", frames_cap)
    camera, lens, _ = tum_calibration()
    if variant == "undistorted":
        messages = encode(frames, with_depth=with_depth)
    else:
        messages = raw_tum_messages(raw_dir, len(frames), with_depth, raw_size)
        args.session_fields = {"intrinsics": {**camera, "distortion": lens} if variant == "lens" else camera}
        if variant == "no-lens":
            args.psnr_every = 0  # its map is in the distorted camera: no undistorted reference to score it against
    return live_figures(stack, frames, undistorted, messages, args)


def decoded_folder(raw_dir: Path, out: Path, variant: str, count: int | None,
                   raw_size: tuple[int, int] = (640, 480)) -> Path:
    """The raw frames as the worker decodes them (`decode_frame`: with the lens, undistorted; without, as sent),
    written losslessly as a folder `flashmono run` reads (PNG, millimetre depth, the camera the worker used, the
    motion capture): the offline run of exactly what a live session's engine receives."""
    import shutil

    from worker.runtime.frames import decode_frame

    camera, lens, _ = tum_calibration()
    declared = {**camera, "distortion": lens} if variant == "lens" else camera
    messages = raw_tum_messages(raw_dir, count or 10**6, with_depth=True, size=raw_size)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    for message in messages:
        frame = decode_frame(msgpack.unpackb(message, raw=False), declared)
        name = f"{frame.index:06d}.png"
        cv2.imwrite(str(out / "rgb" / name), cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(out / "depth" / name), np.round(frame.depth * 1000).astype(np.uint16))
    k = frame.intrinsics
    (out / "intrinsics.json").write_text(json.dumps({"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
                                                    "width": k.width, "height": k.height, "depth_scale": 1000.0,
                                                    "fps": 30}))
    lines = (TUM / "groundtruth.txt").read_text().splitlines(keepends=True)
    (out / "groundtruth.txt").write_text("".join(lines[:len(messages) + sum(line.startswith("#") for line in lines)]))
    shutil.copy(TUM / "README.md", out / "SOURCE_README.md")
    return out


def offline_case(case: str, raw_dir: Path, frames_cap: int | None, raw_size: tuple[int, int] = (640, 480)
                 ) -> dict[str, Any]:
    """`flashmono run` (its defaults) of the frames a live session's engine receives: the raw frames decoded with
    their lens or without, or the frames undistorted offline at 640x480."""
    import tempfile

    from bench.live import run_offline

    mode, variant = case.split("-", 1)
    args = case_args(mode, "320x240", frames_cap)
    with tempfile.TemporaryDirectory(prefix="bench-lens-") as tmp:
        source = TUM if variant == "undistorted" else decoded_folder(raw_dir, Path(tmp) / "frames", variant,
                                                                      frames_cap, raw_size)
        return run_offline(str(source), (320, 240), frames_cap, args, Path(tmp) / "run")


# ------------------------------------------------------------------------------------------------------ photos
def fox_photos(folder: Path) -> tuple[dict[str, Any], dict[str, Any], list[tuple[Path, np.ndarray]]]:
    """(camera, lens, [(photo, camera-to-world pose in OpenCV axes)] in file order) of a transforms.json folder
    (frames whose photo is missing are left out: the fox lists 67, ships 50)."""
    data = json.loads((folder / "transforms.json").read_text())
    camera = {"fx": data["fl_x"], "fy": data["fl_y"], "cx": data["cx"], "cy": data["cy"], "width": int(data["w"]),
              "height": int(data["h"])}
    lens = {"model": "radtan", **{k: data[k] for k in ("k1", "k2", "p1", "p2", "k3") if k in data}}
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    photos = sorted(((folder / f["file_path"], np.asarray(f["transform_matrix"], np.float64) @ flip)
                     for f in data["frames"] if (folder / f["file_path"]).is_file()), key=lambda item: item[0].name)
    return camera, lens, photos


def fox_case(stack: ServeProcess, case: str, folder: Path) -> dict[str, Any]:
    """Posed RGB photos streamed by the SDK as a photo app would (every photo tracked, none skipped), every 8th held
    out; the held-out views rendered by the service (as captured: `exposure_of` the held-out seq, interpolated
    between the keyframes around it) against the photos."""
    from client.async_sdk import decode_png
    from client.frames import StreamFrame
    from client.sdk import FlashMonoClient
    from client.streaming import WireOptions
    from worker.eval import psnr
    from worker.geometry import Intrinsics
    from worker.geometry.lens import Lens, undistorted_camera

    camera, lens, photos = fox_photos(folder)
    with_lens = case == "fox-lens"
    held = {i for i in range(len(photos)) if i % HOLD_OUT_EVERY == HOLD_OUT_EVERY // 2}
    frames = [StreamFrame(i, i / 2.0, cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB), pose=pose)
              for i, (path, pose) in enumerate(photos) if i not in held]
    started = time.monotonic()
    with FlashMonoClient(stack.base_url, timeout_s=600) as client:
        session = client.create_session(intrinsics={**camera, "distortion": lens} if with_lens else camera,
                                        name=f"bench-{case}")
        summary = client.stream(session.id, frames, wire=WireOptions(send_pose=True, send_intrinsics=False,
                                                                     jpeg_quality=95))
        record = client.get_session(session.id)
        used = record.estimated_intrinsics
        full = Intrinsics(camera["fx"], camera["fy"], camera["cx"], camera["cy"], camera["width"], camera["height"])
        lens_model = Lens.from_wire(lens)
        pinhole = undistorted_camera(full, lens_model) if with_lens else full
        scores = []
        for i in sorted(held):
            photo = cv2.cvtColor(cv2.imread(str(photos[i][0])), cv2.COLOR_BGR2RGB)
            if with_lens:  # OpenCV's own undistortion at full size: independent of the session's
                K = np.array([[full.fx, 0, full.cx], [0, full.fy, full.cy], [0, 0, 1]])
                P = np.array([[pinhole.fx, 0, pinhole.cx], [0, pinhole.fy, pinhole.cy], [0, 0, 1]])
                photo = cv2.undistort(photo, K, lens_model.array, newCameraMatrix=P)
            truth = cv2.resize(photo, (used["width"], used["height"]), interpolation=cv2.INTER_AREA)
            view = client.render(session.id, photos[i][1], width=used["width"], height=used["height"],
                                 fx=used["fx"], fy=used["fy"], cx=used["cx"], cy=used["cy"], exposure_of=i)
            scores.append(psnr(decode_png(view), truth))
    return {"photos": len(photos), "held_out": len(held), "sent": len(frames), "posed": len(summary.poses),
            "errors": len(summary.errors), "held_out_psnr_db": float(np.mean(scores)),
            "held_out_psnr_each_db": [round(float(s), 2) for s in scores], "wall_s": round(time.monotonic() - started,
                                                                                           1),
            "render_camera": used, "settings": record.settings, "load": [round(os.getloadavg()[0], 2)]}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench lens", description=__doc__.split("\n\n")[0])
    parser.add_argument("--tum-raw", type=Path, help="TUM's raw rgbd_dataset_freiburg1_xyz folder")
    parser.add_argument("--fox", type=Path, help="instant-ngp's fox folder (transforms.json + images/)")
    parser.add_argument("--cases", nargs="+", choices=TUM_CASES + FOX_CASES, default=list(TUM_CASES + FOX_CASES))
    parser.add_argument("--frames", type=int, default=None, help="at most this many TUM frames a case")
    parser.add_argument("--raw-size", default="640x480", help="the raw TUM frames' size as sent: 640x480 as "
                        "recorded, or smaller (area-downscaled, as a phone app may send them)")
    parser.add_argument("--offline", action="store_true", help="the TUM cases through `flashmono run` instead (the "
                        "frames the worker decodes, written losslessly: the lens handling without live load)")
    args = parser.parse_args(argv)
    recorder = Recorder("lens", argv)
    raw_size = tuple(int(v) for v in args.raw_size.split("x"))
    todo = [c for c in args.cases if (c in FOX_CASES and args.fox) or (c in TUM_CASES and args.tum_raw)]
    if not todo:
        raise SystemExit("give --tum-raw and/or --fox (the data is fetched, not shipped)")
    if args.offline:
        for case in [c for c in todo if c in TUM_CASES]:
            load_start = loadavg()
            values = offline_case(case, args.tum_raw, args.frames, raw_size)
            values["psnr_db"] = values.get("psnr")  # scored on the frames it ran on (the live cases' key)
            print(f"{case} offline: ATE {100 * (values['ate_m'] or float('nan')):.2f} cm, PSNR "
                  f"{values['psnr'] or float('nan'):.2f} dB, {values['wall_s']:.0f} s", flush=True)
            mode, variant = case.split("-", 1)
            recorder.write({"area": "lens", "sequence": "tum_fr1_xyz_raw", "mode": mode,
                            "variant": f"{variant}-offline", "size": args.raw_size}, values,
                           load_at_case_start=load_start)
        return 0
    with ServeProcess() as stack:
        for case in todo:
            load_start = loadavg()
            if case in FOX_CASES:
                values = fox_case(stack, case, args.fox)
                print(f"{case}: {values['posed']}/{values['sent']} posed, held-out {values['held_out_psnr_db']:.2f} "
                      f"dB over {values['held_out']} photos, {values['wall_s']} s", flush=True)
                sequence, mode = "instant_ngp_fox", "posed-rgb"
            else:
                values = tum_case(stack, case, args.tum_raw, args.frames, raw_size)
                print(f"{case}: posed {values['posed_share']:.1%}, p95 {values['latency_p95_ms']:.0f} ms, ATE "
                      f"{100 * (values['ate_m'] or float('nan')):.2f} cm, PSNR {values['psnr_db'] or float('nan'):.2f}"
                      f" dB, finish {values['finish_s']:.1f} s", flush=True)
                sequence, mode = "tum_fr1_xyz_raw", case.split("-", 1)[0]
                values["raw_size"] = args.raw_size
            variant = case.split("-", 1)[1] if case in TUM_CASES else case.removeprefix("fox-")
            recorder.write({"area": "lens", "sequence": sequence, "mode": mode, "variant": variant}, values,
                           load_at_case_start=load_start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
