"""Surfel -> screen projection in pure torch (differentiable by autograd): the reference backend's first stage.

The compiled CPU path runs the same maths in C++ (`csrc/raster_cpu.cpp`, float64 internally).

For each surfel it builds gsplat 1.5.3's ray transform T = K [s_u R_c[:,0] | s_v R_c[:,1] | mu_c] (rows T0, T1, T2;
T (u, v, 1) = (x w, y w, w) for the surfel-local point (u, v)), the screen centre and per-axis radius of the r = 1
conic's bounding box, the camera-frame normal flipped towards the camera, and culls what gsplat culls.

The compositors do not use T directly but its adjugate rows ("uv planes") A = T1 x T2, B = T2 x T0, C = T0 x T1:
for a pixel centre (x, y) the homogeneous surfel coordinates are p = x A + y B + C and (u, v) = (p0 / p2, p1 / p2),
the same point as the cross product (x T2 - T0) x (y T2 - T1) of the two pixel planes.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from worker.geometry import quat_to_rotmat

NEAR_PLANE = 0.01
FAR_PLANE = 1e10
RADIUS_SIGMAS = 3.33  # gsplat: radius = ceil(3.33 * half-extent of the r = 1 conic), ~sqrt(2 ln 255)
TILE_SIZE = 16


class ProjectedSurfels(NamedTuple):
    """The visible surfels of one view, compacted (M of the N input surfels)."""

    ids: torch.Tensor  # [M] int64 index into the input surfels
    ray_transforms: torch.Tensor  # [M, 3, 3] T (rows T0, T1, T2)
    uv_planes: torch.Tensor  # [M, 3, 3] rows A, B, C (see module docstring)
    means2d: torch.Tensor  # [M, 2] conic centre in pixels (also the low-pass filter centre)
    depths: torch.Tensor  # [M] camera z of the surfel centre
    normals: torch.Tensor  # [M, 3] camera-frame unit normal facing the camera
    radii: torch.Tensor  # [M, 2] int32 per-axis pixel radius (tile binning only)


def _ray_transforms(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmat: torch.Tensor,
                    K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(T [N,3,3], mu_c [N,3], R_c [N,3,3]) for every surfel."""
    R_cw, t_cw = viewmat[:3, :3], viewmat[:3, 3]
    mean_c = means @ R_cw.T + t_cw
    R_c = R_cw @ quat_to_rotmat(quats)
    WH = torch.stack([R_c[:, :, 0] * scales[:, :1], R_c[:, :, 1] * scales[:, 1:2], mean_c], dim=-1)
    return K @ WH, mean_c, R_c


def _conic_box(T: torch.Tensor, r2: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centre [N,2], half extents [N,2] (unclamped squares) and the denominator d of the radius-r conic's AABB.

    Closed form of the tangent lines x T2 - T0 (and y T2 - T1) to the disc u^2 + v^2 = r^2; exact while the disc
    lies in front of the camera (d < 0).
    """
    T0, T1, T2 = T[:, 0], T[:, 1], T[:, 2]
    r2 = torch.as_tensor(r2, dtype=T.dtype, device=T.device)
    t = torch.stack([r2.expand(T.shape[0]), r2.expand(T.shape[0]), -torch.ones_like(T[:, 0, 0])], dim=-1)
    d = (t * T2 * T2).sum(-1)
    f = t / torch.where(d == 0, torch.ones_like(d), d)[:, None]
    centre = torch.stack([(f * T0 * T2).sum(-1), (f * T1 * T2).sum(-1)], dim=-1)
    half_sq = centre * centre - torch.stack([(f * T0 * T0).sum(-1), (f * T1 * T1).sum(-1)], dim=-1)
    return centre, half_sq, d


def project_surfels(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmat: torch.Tensor,
                    K: torch.Tensor, width: int, height: int) -> ProjectedSurfels:
    """Project and cull surfels for one camera (gsplat 1.5.3 `fully_fused_projection_2dgs` semantics)."""
    with torch.no_grad():  # depth cull first: it needs only the centres, and a map is mostly out of view
        z = means @ viewmat[2, :3] + viewmat[2, 3]
        candidates = ((z > NEAR_PLANE) & (z < FAR_PLANE)).nonzero()[:, 0]
    T, mean_c, R_c = _ray_transforms(means[candidates], quats[candidates], scales[candidates], viewmat, K)
    centre, half_sq, d = _conic_box(T, 1.0)
    with torch.no_grad():
        radii = torch.ceil(RADIUS_SIGMAS * half_sq.detach().clamp_min(1e-4).sqrt())
        visible = d != 0
        visible &= (centre[:, 0] + radii[:, 0] > 0) & (centre[:, 0] - radii[:, 0] < width)
        visible &= (centre[:, 1] + radii[:, 1] > 0) & (centre[:, 1] - radii[:, 1] < height)
        keep = visible.nonzero()[:, 0]
    T, mean_c, R_c, centre = T[keep], mean_c[keep], R_c[keep], centre[keep]
    T0, T1, T2 = T[:, 0], T[:, 1], T[:, 2]
    planes = torch.stack([torch.cross(T1, T2, dim=-1), torch.cross(T2, T0, dim=-1), torch.cross(T0, T1, dim=-1)], 1)
    normals = R_c[:, :, 2]
    facing = torch.where((normals * mean_c).sum(-1) < 0, 1.0, -1.0).to(normals.dtype).detach()
    return ProjectedSurfels(candidates[keep], T, planes, centre, T[:, 2, 2], normals * facing[:, None],
                            radii[keep].to(torch.int32))
