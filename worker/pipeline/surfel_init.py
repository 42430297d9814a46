"""Per-pixel camera-frame surfel grids for a keyframe, from the model's prediction and/or a depth map.

A grid is a dict of tensors over the image: means [H,W,3], quats [H,W,4] wxyz, scales [H,W,2], opacities [H,W],
colors [H,W,3] and valid [H,W] bool: the input `worker.mapping.voxelize` takes. In RGB-D mode the means come from
the unprojected depth (paper: "means from unprojected depth"); the other attributes come from the model or, with
`surfel_init="depth"`, from the image and the depth's local surface (no model needed: the backend in isolation).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from worker.geometry import rotmat_to_quat, unproject_depth

# A per-pixel surfel's standard deviation in pixels: ~0.7 px covers the pixel without blurring its neighbours.
PIXEL_SIGMA = 0.5
INITIAL_OPACITY = 0.95
# A step between neighbouring pixels larger than this fraction of the depth is a discontinuity, not a surface.
EDGE_DEPTH_RATIO = 0.05


def depth_normals(points: torch.Tensor, edge_ratio: float = EDGE_DEPTH_RATIO) -> torch.Tensor:
    """Unit normals [H,W,3] of a camera-frame point grid, oriented towards the camera.

    Each axis uses the one-sided difference (forward or backward) whose depth step is smaller, so a normal never
    spans a depth discontinuity; where both steps exceed `edge_ratio` of the depth (a one-pixel-wide structure)
    the normal faces the camera."""
    p = F.pad(points.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0].permute(1, 2, 0)
    centre = p[1:-1, 1:-1]
    dx, edge_x = _smooth_side(p[1:-1, 2:] - centre, centre - p[1:-1, :-2], centre[..., 2], edge_ratio)
    dy, edge_y = _smooth_side(p[2:, 1:-1] - centre, centre - p[:-2, 1:-1], centre[..., 2], edge_ratio)
    n = torch.linalg.cross(dx, dy, dim=-1)
    norm = n.norm(dim=-1, keepdim=True)
    towards_camera = -centre / centre.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    usable = (norm > 1e-12) & ~(edge_x | edge_y)[..., None]
    n = torch.where(usable, n / norm.clamp_min(1e-12), towards_camera)
    facing = (n * centre).sum(-1, keepdim=True) > 0
    return torch.where(facing, -n, n)


def _smooth_side(forward: torch.Tensor, backward: torch.Tensor, depth: torch.Tensor, edge_ratio: float
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """(the difference with the smaller depth step, whether even that step is a discontinuity)."""
    use_forward = forward[..., 2].abs() <= backward[..., 2].abs()
    diff = torch.where(use_forward[..., None], forward, backward)
    return diff, diff[..., 2].abs() > edge_ratio * depth.abs().clamp_min(1e-9)


def normals_to_quats(normals: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions [...,4] of rotations whose third column is the given unit normal."""
    helper = torch.zeros_like(normals)
    use_x = normals[..., 0].abs() < 0.9
    helper[..., 0] = use_x.to(normals.dtype)
    helper[..., 1] = (~use_x).to(normals.dtype)
    u = torch.linalg.cross(helper, normals, dim=-1)
    u = u / u.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    v = torch.linalg.cross(normals, u, dim=-1)
    return rotmat_to_quat(torch.stack([u, v, normals], dim=-1))


def grid_from_depth(image: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, fill_holes: bool = True
                    ) -> dict[str, torch.Tensor]:
    """Surfels from an RGB image float [H,W,3] in [0,1] and metric depth [H,W] (0 = invalid): one per pixel at
    the unprojected depth, oriented along the depth's surface normal, coloured by the pixel, ~1 pixel wide.
    `fill_holes`: invalid pixels get a surfel at the farthest depth (a sensor's holes are far or glassy surfaces);
    otherwise none (a stereo hole says nothing about the depth there)."""
    depth = depth.to(torch.float32)
    if fill_holes:
        depth = fill_invalid_depth(depth)
    means = unproject_depth(depth, K.to(torch.float32))
    normals = depth_normals(means)
    footprint = depth / float(K[0, 0])
    # A tilted surfel must stretch to cover its pixel: divide by the cosine of the viewing angle (capped).
    view = means / means.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    cos = (normals * view).sum(-1).abs().clamp_min(0.3)
    sigma = (PIXEL_SIGMA * footprint / cos).clamp_min(1e-6)
    return {
        "means": means,
        "quats": normals_to_quats(normals),
        "scales": torch.stack([sigma, sigma], dim=-1),
        "opacities": torch.full_like(depth, INITIAL_OPACITY),
        "colors": image.to(torch.float32).clamp(0, 1),
        "valid": depth > 0,
    }


def fill_invalid_depth(depth: torch.Tensor) -> torch.Tensor:
    """Depth with holes (0, non-finite) filled by the frame's farthest valid depth: sensors drop far or glassy
    surfaces, and a surfel there (coloured by its pixel, behind everything else) renders them instead of black."""
    valid = torch.isfinite(depth) & (depth > 0)
    if bool(valid.all()) or not bool(valid.any()):
        return depth
    return torch.where(valid, depth, depth[valid].max())


def grid_from_prediction(points: torch.Tensor, conf: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                         opacities: torch.Tensor, colors: torch.Tensor, min_confidence: float,
                         depth: torch.Tensor | None = None, K: torch.Tensor | None = None,
                         min_kept_fraction: float = 0.0, ray_aligned: bool = False) -> dict[str, torch.Tensor]:
    """Surfels from one frame's model prediction (all [H,W,...] at model resolution).

    With a metric `depth` (same resolution) and K, the means come from the depth and the predicted scales are
    rescaled by depth / predicted z so the surfels keep their pixel footprint; confidence then does not gate pixels
    that have depth. Without depth, `ray_aligned` (needs K) puts each surfel on its own pixel's ray at the predicted
    z, as calibrated MASt3R-SLAM does: the model's point directions are the least reliable part of a pointmap.
    Pixels below `min_confidence` are dropped, unless that would keep fewer than `min_kept_fraction` of them: then
    the most confident fraction is kept (a poorly calibrated confidence still maps)."""
    valid = confidence_mask(conf, min_confidence, min_kept_fraction)
    if depth is not None:
        if K is None:
            raise ValueError("K is needed to unproject depth")
        metric = unproject_depth(depth.to(torch.float32), K.to(torch.float32))
        ratio = depth / points[..., 2].clamp_min(1e-6)
        scales = scales * ratio[..., None]
        points = metric
        valid = depth > 0
    elif ray_aligned:
        if K is None:
            raise ValueError("K is needed for ray-aligned surfels")
        z = points[..., 2]
        points = unproject_depth(z.clamp_min(0).to(torch.float32), K.to(torch.float32))
        valid = valid & (z > 0)
    return {"means": points, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
            "valid": valid & torch.isfinite(points).all(-1)}


def confidence_mask(conf: torch.Tensor, min_confidence: float, min_kept_fraction: float = 0.0) -> torch.Tensor:
    """[H,W] bool: conf >= min_confidence, widened to the top `min_kept_fraction` of pixels by confidence."""
    valid = conf >= min_confidence
    if min_kept_fraction > 0 and float(valid.float().mean()) < min_kept_fraction:
        floor = torch.quantile(conf.reshape(-1).float(), 1.0 - min_kept_fraction)
        valid = valid | (conf >= floor)
    return valid
