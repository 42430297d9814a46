"""A finished session's map as a map package (protocol.map_package), and a package back as a GaussianMap.

The package holds every keyframe of the map with its camera-to-world pose, intrinsics, image (JPEG) and half-
resolution float16 depth (the compact form the map archives keyframes in, worker.mapping.keyframe_archive) and
exposure; a keyframe whose photo the map had let go (beyond `archived_images`) gets the map's render at its pose
instead (`rendered`). The surfels go as the engine's binary PLY with each surfel's keyframe id, so that a loaded
map's surfels still move with their keyframes (loop corrections), and the map's background (a multi-view stereo
session's sky box) and voxel size go with them (`engine`), so that the loaded map renders and grows as the
original did.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from protocol.map_package import MapKeyframe, MapPackage, encode_package
from protocol.splats.ply_records import ply_with_sh_degree
from worker.mapping import GaussianMap, MapConfig, surfels_from_ply_bytes
from worker.mapping.background import DirectionalBackground
from worker.mapping.keyframe_archive import ArchivedKeyframe
from worker.settings_choice import SessionInput

from .views import with_places


def build_package(system: Any, name: str, session_ids: list[str]) -> bytes:
    """The map of a finished `worker.slam.SlamSystem` as package bytes named `name`, built by `session_ids`.
    Its scale is metric when the session had sensor depth or tracked by the device's poses, else up to scale.
    ValueError when the session has no map (mapping disabled, no keyframe)."""
    stage = system.mapping_stage
    if stage is None:
        raise ValueError("mapping is disabled in this session's settings: it has no map")
    metric = bool(system.with_depth) or system.tracking == "device"
    mode = "unknown" if system.tracking is None else SessionInput(
        depth=bool(system.with_depth), device_poses=system.tracking == "device").mode
    with stage.lock:
        package = package_from_map(stage.map, name, session_ids, "metric" if metric else "up_to_scale", mode)
    return encode_package(package)


def package_from_map(gmap: GaussianMap, name: str, session_ids: list[str], scale: str, mode: str) -> MapPackage:
    """A GaussianMap as a MapPackage (see the module docstring); `scale` and `mode` describe the session's input."""
    state = gmap.state_dict()
    keyframes = with_places([_keyframe(gmap, entry) for entry in state["keyframes"]])
    ply = ply_with_sh_degree(gmap.to_ply_bytes(include_keyframe_id=True), 0)
    engine = {"voxel_size": state["voxel_size"], "background": _background(state["background"])}
    return MapPackage(name=name, keyframes=keyframes, surfels_ply=ply, scale=scale, mode=mode,
                      sessions=list(session_ids), engine=engine)


def load_gaussian_map(package: MapPackage, device: str = "cpu", config: MapConfig | None = None) -> GaussianMap:
    """The map of `package`, its keyframes (ids, poses, cameras, images and depth archived, exposures) and surfels
    as they were. `config` defaults to MapConfig's with room for every keyframe's image (a config that keeps fewer
    `archived_images` lets the most redundant views go at once)."""
    config = config or MapConfig(device=device, archived_images=len(package.keyframes))
    surfels = surfels_from_ply_bytes(package.surfels_ply)
    background = package.engine.get("background")
    state = {
        "version": 1, "config": config.to_dict(),
        "surfels": {k: v.numpy() for k, v in surfels.tensors().items()},
        "keyframes": [{"id": kf.id, "pose": kf.pose, "K": kf.K.astype(np.float32), "width": kf.width,
                       "height": kf.height, "image": None, "depth": None, "exposure": kf.exposure,
                       "archived": {"jpeg": kf.jpeg, "depth": kf.depth, "width": kf.width, "height": kf.height}}
                      for kf in package.keyframes],
        "voxel_size": package.engine.get("voxel_size"),
        "background": None if background is None else _background_state(background),
    }
    gmap = GaussianMap(config)
    gmap.load_state_dict(state)
    return gmap


def _keyframe(gmap: GaussianMap, entry: dict[str, Any]) -> MapKeyframe:
    """A map keyframe (a GaussianMap.state_dict() entry) in the package's compact form."""
    rendered = entry["archived"] is None and entry["image"] is None
    exposure = None if entry["exposure"] is None or rendered else np.asarray(entry["exposure"], np.float32)
    if entry["archived"] is not None:
        compact = ArchivedKeyframe.from_dict(entry["archived"])
    elif not rendered:
        depth = None if entry["depth"] is None else torch.from_numpy(entry["depth"])
        compact = ArchivedKeyframe.pack(torch.from_numpy(entry["image"]), depth)
    else:  # the map let its photo go: what the map shows there, depth in the keyframe's own units
        pose = torch.from_numpy(entry["pose"])
        out = gmap.render(pose, torch.from_numpy(entry["K"]), entry["width"], entry["height"])
        scale = float(torch.linalg.det(pose[:3, :3]).abs() ** (1 / 3))
        compact = ArchivedKeyframe.pack(out.rgb.cpu(), out.depth.cpu() / scale)
    return MapKeyframe(id=int(entry["id"]), pose=np.asarray(entry["pose"], np.float64),
                       K=np.asarray(entry["K"], np.float64), width=compact.width, height=compact.height,
                       jpeg=compact.jpeg, depth=compact.depth, exposure=exposure, rendered=rendered)


def _background(state: dict[str, Any] | None) -> dict[str, Any] | None:
    """The package form of a DirectionalBackground state: each cube cell's mean colour and whether it belongs to
    the background; None when the map keeps none or it saw nothing."""
    if state is None:
        return None
    background = DirectionalBackground.from_state(state)
    n = background.face_cells
    seen = ((background.weight > 0) & (background.weight > background.covered)).reshape(6, n, n)
    if not bool(seen.any()):
        return None
    colour = background.colour_sum / background.weight.clamp_min(1e-6).unsqueeze(-1)
    rgb = (colour.clamp(0, 1) * 255).round().to(torch.uint8).reshape(6, n, n, 3)
    return {"face_cells": n, "rgb": rgb.numpy(), "seen": seen.numpy()}


def _background_state(background: dict[str, Any]) -> dict[str, Any]:
    """A DirectionalBackground state from the package form (one observation per cell seen)."""
    seen = np.asarray(background["seen"], np.float32).reshape(-1)
    colour = np.asarray(background["rgb"], np.float32).reshape(-1, 3) / 255.0
    return {"face_cells": int(background["face_cells"]), "colour_sum": colour * seen[:, None], "weight": seen,
            "covered": np.zeros_like(seen)}
