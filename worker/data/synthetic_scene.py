"""Procedural indoor scenes rendered exactly by ray casting: RGB, metric depth, poses and intrinsics.

A scene is a box-shaped room (seen from inside) with furniture: yawed boxes, vertical cylinders and spheres. Every
surface has a procedural texture (checker, stripes or smooth noise, tinted per face) under Lambertian shading from
one fixed directional light plus ambient, so the colour of a surface point does not depend on the viewpoint (the
photometric consistency SLAM and 2DGS assume). Depth is the exact z-depth of the first hit along each pixel-centre
ray. World frame: z up, floor at z = 0, room centred on the origin; cameras follow OpenCV (x right, y down, z fwd).

Seeds: 0 <= seed < HELD_OUT_SEED_START are for training; seeds >= HELD_OUT_SEED_START are held out for evaluation
and tests of generalisation, and must never be used to train.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from worker.geometry import Intrinsics

HELD_OUT_SEED_START = 10_000
_EPS = 1e-4


def is_held_out_seed(seed: int) -> bool:
    """True for seeds reserved for evaluation (never train on them)."""
    return seed >= HELD_OUT_SEED_START


@dataclass(frozen=True)
class Material:
    """A procedural texture: kind 'checker' | 'stripes' | 'noise', two colours, a spatial period (metres), a
    per-face tint [6, 3] and random plane waves (directions [K, 2], frequencies [K], phases [K]) for fine detail."""

    kind: str
    color_a: np.ndarray
    color_b: np.ndarray
    period: float
    face_tint: np.ndarray
    wave_dirs: np.ndarray
    wave_freqs: np.ndarray
    wave_phases: np.ndarray

    def albedo(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        """RGB albedo in [0, 1] [N, 3] at surface coordinates uv [N, 2] (metres) on faces [N]."""
        detail = np.sin((uv @ self.wave_dirs.T) * self.wave_freqs + self.wave_phases).mean(axis=1)
        if self.kind == "checker":
            cells = np.floor(uv / np.float32(self.period)).sum(axis=1)
            mix = np.mod(cells, np.float32(2.0))
        elif self.kind == "stripes":
            mix = np.float32(0.5) + np.float32(0.5) * np.sin(np.float32(2 * np.pi / self.period) * uv[:, 0])
        else:
            mix = np.clip(np.float32(0.5) + np.float32(1.2) * detail, 0.0, 1.0)
        color = self.color_a + (self.color_b - self.color_a) * mix[:, None]
        color *= self.face_tint[face] * (np.float32(1.0) + np.float32(0.12) * detail[:, None])
        return np.clip(color, 0.0, 1.0)


@dataclass(frozen=True)
class SceneLayout:
    """Geometry of one scene. Boxes: centres [B, 3], half sizes [B, 3], yaws [B] (box 0 is the room, seen from
    inside). Cylinders: base centres [C, 3], radii [C], heights [C]. Spheres: centres [S, 3], radii [S]."""

    box_centers: np.ndarray
    box_halves: np.ndarray
    box_yaws: np.ndarray
    cyl_bases: np.ndarray
    cyl_radii: np.ndarray
    cyl_heights: np.ndarray
    sphere_centers: np.ndarray
    sphere_radii: np.ndarray
    path_radii: tuple[float, float]
    path_height: float


def _random_material(rng: np.random.Generator) -> Material:
    kind = ["checker", "stripes", "noise"][rng.integers(3)]
    color_a = rng.uniform(0.1, 0.9, 3)
    offset = rng.normal(size=3)
    color_b = np.clip(color_a + rng.uniform(0.35, 0.6) * offset / np.linalg.norm(offset), 0.05, 0.95)
    k = 6
    angles = rng.uniform(0, np.pi, k)
    f32 = np.float32
    return Material(
        kind=kind, color_a=color_a.astype(f32), color_b=color_b.astype(f32), period=float(rng.uniform(0.15, 0.6)),
        face_tint=rng.uniform(0.75, 1.15, (6, 3)).astype(f32),
        wave_dirs=np.stack([np.cos(angles), np.sin(angles)], axis=1).astype(f32),
        wave_freqs=rng.uniform(4.0, 30.0, k).astype(f32), wave_phases=rng.uniform(0, 2 * np.pi, k).astype(f32),
    )


def _footprint_clear_of_path(center: np.ndarray, radius: float, path_radii: tuple[float, float], margin: float) -> bool:
    """True when a disc (centre xy, radius) stays `margin` away from the camera's elliptical path."""
    theta = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    path = np.stack([path_radii[0] * np.cos(theta), path_radii[1] * np.sin(theta)], axis=1)
    return bool(np.min(np.linalg.norm(path - center[:2], axis=1)) > radius + margin)


def generate_layout(rng: np.random.Generator) -> SceneLayout:
    """A random room with furniture kept clear of the camera path (an ellipse around the room centre)."""
    length, width, height = rng.uniform(4.5, 7.5), rng.uniform(4.0, 7.0), rng.uniform(2.5, 3.2)
    path_radii = (0.22 * length, 0.22 * width)
    boxes = [(np.array([0.0, 0.0, height / 2]), np.array([length / 2, width / 2, height / 2]), 0.0)]
    cylinders, spheres = [], []
    margin = 0.55
    for _ in range(60):
        if len(boxes) + len(cylinders) + len(spheres) >= 14:
            break
        shape = rng.choice(["box", "box", "cylinder", "sphere"])
        # Either near the walls (outside the path) or near the centre (inside it).
        if rng.uniform() < 0.25:
            xy = rng.uniform(-0.5, 0.5, 2) * np.array(path_radii)
        else:
            xy = rng.uniform(-0.45, 0.45, 2) * np.array([length, width])
        if shape == "box":
            half = np.array([rng.uniform(0.15, 0.7), rng.uniform(0.15, 0.7), rng.uniform(0.2, 1.0)])
            z = half[2] if rng.uniform() < 0.8 else rng.uniform(half[2], height - half[2])  # mostly on the floor
            center = np.array([xy[0], xy[1], z])
            reach = float(np.hypot(half[0], half[1]))
            if _footprint_clear_of_path(center, reach, path_radii, margin):
                boxes.append((center, half, float(rng.uniform(0, np.pi))))
        elif shape == "cylinder":
            radius, cyl_height = rng.uniform(0.1, 0.4), rng.uniform(0.4, 2.0)
            base = np.array([xy[0], xy[1], 0.0])
            if _footprint_clear_of_path(base, radius, path_radii, margin):
                cylinders.append((base, radius, cyl_height))
        else:
            radius = rng.uniform(0.15, 0.45)
            center = np.array([xy[0], xy[1], rng.uniform(radius, 1.8)])
            if _footprint_clear_of_path(center, radius, path_radii, margin):
                spheres.append((center, radius))
    for _ in range(int(rng.integers(4, 9))):  # flat panels (pictures, shelves) on the walls
        wall = int(rng.integers(4))
        along = rng.uniform(-0.4, 0.4) * (width if wall < 2 else length)
        half = np.array([0.03, rng.uniform(0.2, 0.6), rng.uniform(0.15, 0.5)])
        z = rng.uniform(0.8, height - 0.6)
        if wall < 2:  # walls at x = -+length/2, panel thin along x
            center = np.array([(length / 2 - half[0]) * (1 if wall else -1), along, z])
            boxes.append((center, half, 0.0))
        else:
            center = np.array([along, (width / 2 - half[0]) * (1 if wall == 3 else -1), z])
            boxes.append((center, half, np.pi / 2))
    return SceneLayout(
        box_centers=np.array([b[0] for b in boxes]), box_halves=np.array([b[1] for b in boxes]),
        box_yaws=np.array([b[2] for b in boxes]),
        cyl_bases=np.array([c[0] for c in cylinders]).reshape(-1, 3), cyl_radii=np.array([c[1] for c in cylinders]),
        cyl_heights=np.array([c[2] for c in cylinders]),
        sphere_centers=np.array([s[0] for s in spheres]).reshape(-1, 3), sphere_radii=np.array([s[1] for s in spheres]),
        path_radii=path_radii, path_height=float(rng.uniform(1.2, min(1.7, height - 0.6))),
    )


def look_at_c2w(position: np.ndarray, forward: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes) at `position` looking along `forward`, world z up, rolled by `roll` rad."""
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll), math.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = position
    return pose


class SyntheticScene:
    """A deterministic procedural room. `render(pose_c2w, intrinsics) -> (rgb uint8 [H,W,3], depth float32 [H,W])`."""

    def __init__(self, seed: int) -> None:
        if int(seed) != seed or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.seed = int(seed)
        rng = np.random.default_rng(self.seed)
        self.layout = generate_layout(rng)
        count = len(self.layout.box_yaws) + len(self.layout.cyl_radii) + len(self.layout.sphere_radii)
        self.materials = [_random_material(rng) for _ in range(count)]
        self.room_materials = {"walls": self.materials[0], "floor": _random_material(rng),
                               "ceiling": _random_material(rng)}
        light = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 1.0])
        self.light_dir = (light / np.linalg.norm(light)).astype(np.float32)
        self._path_phase = float(rng.uniform(0, 2 * np.pi))
        self._look_out = float(rng.uniform(0.35, 0.9))
        self._wobble = rng.uniform(0, 2 * np.pi, 3)

    # ---- camera paths -------------------------------------------------------------------------------------------
    def camera_path(self, num_frames: int, revisit: bool = True) -> np.ndarray:
        """Camera-to-world poses [num_frames, 4, 4] along the room's ellipse.

        revisit=True goes once around and about 10% further, so the last frames see again what the first frames saw
        (a loop closure); revisit=False covers 60% of the ellipse and never comes back.
        """
        if num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        sweep = 2 * np.pi * (1.1 if revisit else 0.6)
        poses = np.empty((num_frames, 4, 4))
        rx, ry = self.layout.path_radii
        for i in range(num_frames):
            u = i / max(num_frames - 1, 1)
            theta = self._path_phase + sweep * u
            position = np.array([rx * math.cos(theta), ry * math.sin(theta),
                                 self.layout.path_height + 0.1 * math.sin(2 * theta + self._wobble[0])])
            tangent = np.array([-rx * math.sin(theta), ry * math.cos(theta), 0.0])
            yaw_wobble = 0.25 * math.sin(3 * theta + self._wobble[1])
            look = _rotate_z(tangent / np.linalg.norm(tangent), -(self._look_out + yaw_wobble))
            look[2] = -0.15 + 0.08 * math.sin(2 * theta + self._wobble[2])
            poses[i] = look_at_c2w(position, look, roll=0.04 * math.sin(theta + self._wobble[2]))
        return poses

    # ---- rendering ----------------------------------------------------------------------------------------------
    def render(self, pose_c2w: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Exact RGB (uint8 [H, W, 3]) and z-depth (float32 [H, W], metres) seen from pose_c2w."""
        pose = np.asarray(pose_c2w, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError("pose_c2w must be a finite 4x4 matrix")
        H, W = intrinsics.height, intrinsics.width
        xs = (np.arange(W, dtype=np.float32) + 0.5 - intrinsics.cx) / intrinsics.fx
        ys = (np.arange(H, dtype=np.float32) + 0.5 - intrinsics.cy) / intrinsics.fy
        d_cam = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.float32(1.0)), axis=-1).reshape(-1, 3)
        R = pose[:3, :3].astype(np.float32)
        origin = pose[:3, 3].astype(np.float32)
        dirs = d_cam @ R.T  # world directions scaled so that t is the camera z-depth
        visible = self._in_frustum(pose, intrinsics)
        t, prim = self._nearest_hit(origin, dirs, visible)
        rgb = self._shade(origin, dirs, t, prim)
        return (np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8).reshape(H, W, 3),
                t.astype(np.float32).reshape(H, W))

    def _bounding_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres [P, 3] and radii [P] enclosing every primitive (room first, then boxes, cylinders, spheres)."""
        L = self.layout
        cyl_centres = L.cyl_bases + np.stack([0 * L.cyl_heights, 0 * L.cyl_heights, L.cyl_heights / 2], axis=1)
        centres = np.concatenate([L.box_centers, cyl_centres, L.sphere_centers])
        radii = np.concatenate([np.linalg.norm(L.box_halves, axis=1), np.hypot(L.cyl_radii, L.cyl_heights / 2),
                                L.sphere_radii])
        return centres, radii

    def _in_frustum(self, pose: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """Which primitives may be seen [P] (bounding sphere against the four side planes and the image plane)."""
        centres, radii = self._bounding_spheres()
        local = (centres - pose[:3, 3]) @ pose[:3, :3]  # camera frame
        x_min, x_max = -intrinsics.cx / intrinsics.fx, (intrinsics.width - intrinsics.cx) / intrinsics.fx
        y_min, y_max = -intrinsics.cy / intrinsics.fy, (intrinsics.height - intrinsics.cy) / intrinsics.fy
        normals = np.array([[1.0, 0.0, -x_min], [-1.0, 0.0, x_max], [0.0, 1.0, -y_min], [0.0, -1.0, y_max]])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        visible = np.all(local @ normals.T >= -radii[:, None], axis=1) & (local[:, 2] >= -radii)
        visible[0] = True  # the room surrounds the camera
        return visible

    def _nearest_hit(self, origin: np.ndarray, dirs: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each ray [N] (as z-depth) to its first hit and the primitive hit [N]."""
        d = np.ascontiguousarray(dirs.T)  # [3, N]: per-axis rows keep the inner loops contiguous
        n_box, n_cyl = len(self.layout.box_yaws), len(self.layout.cyl_radii)
        boxes = np.flatnonzero(visible[1:n_box]) + 1
        cylinders = np.flatnonzero(visible[n_box:n_box + n_cyl])
        spheres = np.flatnonzero(visible[n_box + n_cyl:])
        t_all = np.concatenate([self._room_hits(origin, d), self._box_hits(origin, d, boxes),
                                self._cylinder_hits(origin, d, cylinders), self._sphere_hits(origin, d, spheres)])
        ids = np.concatenate([[0], boxes, cylinders + n_box, spheres + n_box + n_cyl])
        best = np.argmin(t_all, axis=0)
        t = np.take_along_axis(t_all, best[None], axis=0)[0]
        if not np.all(np.isfinite(t)):
            raise RuntimeError("a ray left the room: the camera is outside the scene")
        return t, ids[best]

    def _room_hits(self, origin: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Exit distance [1, N] from inside the room (box 0, axis-aligned)."""
        centre, half = self.layout.box_centers[0], self.layout.box_halves[0]
        t = np.full(d.shape[1], np.inf, np.float32)
        with np.errstate(divide="ignore"):
            for k in range(3):
                wall = np.where(d[k] > 0, centre[k] + half[k], centre[k] - half[k]).astype(np.float32)
                t = np.minimum(t, np.where(d[k] != 0, (wall - origin[k]) / d[k], np.inf))
        return t[None]

    def _box_hits(self, origin: np.ndarray, d: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """Entry distances [len(indices), N] (inf for misses) into furniture boxes (yawed about z)."""
        L = self.layout
        if not len(indices):
            return np.zeros((0, d.shape[1]), np.float32)
        yaws, centres, halves = L.box_yaws[indices], L.box_centers[indices], L.box_halves[indices].astype(np.float32)
        c, s = np.cos(yaws).astype(np.float32)[:, None], np.sin(yaws).astype(np.float32)[:, None]
        rel = (origin[None, :] - centres).astype(np.float32)
        o_local = [c[:, 0] * rel[:, 0] + s[:, 0] * rel[:, 1], -s[:, 0] * rel[:, 0] + c[:, 0] * rel[:, 1], rel[:, 2]]
        d_local = [c * d[0] + s * d[1], -s * d[0] + c * d[1], np.broadcast_to(d[2], (len(yaws), d.shape[1]))]
        t_near = np.full((len(yaws), d.shape[1]), -np.inf, np.float32)
        t_far = np.full_like(t_near, np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                inv = np.float32(1.0) / d_local[k]
                t1 = (-halves[:, k:k + 1] - o_local[k][:, None]) * inv
                t2 = (halves[:, k:k + 1] - o_local[k][:, None]) * inv
                t_near = np.maximum(t_near, np.minimum(t1, t2))
                t_far = np.minimum(t_far, np.maximum(t1, t2))
        return np.where((t_near <= t_far) & (t_near > _EPS), t_near, np.inf).astype(np.float32)

    def _cylinder_hits(self, origin: np.ndarray, d: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """Distances [len(indices), N] to vertical cylinders (side or top cap)."""
        L = self.layout
        if not len(indices):
            return np.zeros((0, d.shape[1]), np.float32)
        rel = (origin[None, :] - L.cyl_bases[indices]).astype(np.float32)
        ox, oy, oz = rel[:, 0:1], rel[:, 1:2], rel[:, 2:3]
        radii = L.cyl_radii[indices].astype(np.float32)[:, None]
        heights = L.cyl_heights[indices].astype(np.float32)[:, None]
        dx, dy, dz = d[0][None], d[1][None], d[2][None]
        a = dx * dx + dy * dy
        b = 2 * (ox * dx + oy * dy)
        c = ox * ox + oy * oy - radii ** 2
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            t_side = (-b - np.sqrt(disc)) / (2 * a)
            z_side = oz + t_side * dz
            side_ok = (disc >= 0) & (t_side > _EPS) & (z_side >= 0) & (z_side <= heights)
            t_cap = (heights - oz) / dz
            cap_x, cap_y = ox + t_cap * dx, oy + t_cap * dy
            cap_ok = (t_cap > _EPS) & (cap_x * cap_x + cap_y * cap_y <= radii ** 2)
        return np.minimum(np.where(side_ok, t_side, np.inf), np.where(cap_ok, t_cap, np.inf)).astype(np.float32)

    def _sphere_hits(self, origin: np.ndarray, d: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """Distances [len(indices), N] to spheres."""
        L = self.layout
        if not len(indices):
            return np.zeros((0, d.shape[1]), np.float32)
        rel = (origin[None, :] - L.sphere_centers[indices]).astype(np.float32)
        a = (d * d).sum(axis=0)[None]
        b = 2 * (rel[:, 0:1] * d[0] + rel[:, 1:2] * d[1] + rel[:, 2:3] * d[2])  # not BLAS: same bits when culled
        c = ((rel * rel).sum(axis=1) - L.sphere_radii[indices].astype(np.float32) ** 2)[:, None]
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore"):
            t = (-b - np.sqrt(disc)) / (2 * a)
        return np.where((disc >= 0) & (t > _EPS), t, np.inf).astype(np.float32)

    def _shade(self, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, prim: np.ndarray) -> np.ndarray:
        L = self.layout
        n_box, n_cyl = len(L.box_yaws), len(L.cyl_radii)
        rgb = np.empty((len(t), 3), np.float32)
        for index in np.unique(prim):
            mask = prim == index
            points = origin[None, :] + t[mask, None] * dirs[mask]
            if index < n_box:
                normal, uv, face = self._box_surface(index, points, dirs[mask])
            elif index < n_box + n_cyl:
                normal, uv, face = self._cylinder_surface(index - n_box, points)
            else:
                normal, uv, face = self._sphere_surface(index - n_box - n_cyl, points)
            albedo = self._room_albedo(uv, face) if index == 0 else self.materials[index].albedo(uv, face)
            lambert = np.abs(normal @ self.light_dir) if index == 0 else np.clip(normal @ self.light_dir, 0, 1)
            rgb[mask] = albedo * (0.45 + 0.55 * lambert)[:, None]
        return rgb

    def _room_albedo(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Walls, floor (face 4: -z) and ceiling (face 5: +z) each have their own material."""
        albedo = self.room_materials["walls"].albedo(uv, face)
        for name, face_id in (("floor", 4), ("ceiling", 5)):
            on = face == face_id
            if on.any():
                albedo[on] = self.room_materials[name].albedo(uv[on], face[on])
        return albedo

    def _box_surface(self, index: int, points: np.ndarray, dirs: np.ndarray):
        L = self.layout
        c, s = np.float32(math.cos(L.box_yaws[index])), np.float32(math.sin(L.box_yaws[index]))
        rel = points - L.box_centers[index].astype(np.float32)
        lx, ly, lz = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]
        hx, hy, hz = L.box_halves[index].astype(np.float32)
        rx, ry, rz = np.abs(lx) / hx, np.abs(ly) / hy, np.abs(lz) / hz
        axis = np.where((rx >= ry) & (rx >= rz), 0, np.where(ry >= rz, 1, 2))
        positive = np.choose(axis, [lx, ly, lz]) > 0
        sign = np.where(positive, np.float32(1), np.float32(-1))
        if index == 0:
            sign = -sign  # the room is seen from inside: its normals point inwards
        nx, ny, nz = (axis == 0) * sign, (axis == 1) * sign, (axis == 2) * sign
        normal = np.stack([c * nx - s * ny, s * nx + c * ny, nz], axis=1)
        u = np.choose(axis, [ly + hy, lx + hx, lx + hx])
        v = np.choose(axis, [lz + hz, lz + hz, ly + hy])
        return normal, np.stack([u, v], axis=1), axis * 2 + positive

    def _cylinder_surface(self, index: int, points: np.ndarray):
        L = self.layout
        rel = points - L.cyl_bases[index].astype(np.float32)
        on_cap = rel[:, 2] >= L.cyl_heights[index] - 1e-3
        radial = rel[:, :2] / max(L.cyl_radii[index], 1e-9)
        up = np.array([0.0, 0.0, 1.0], np.float32)
        normal = np.where(on_cap[:, None], up, np.concatenate([radial, 0 * rel[:, :1]], 1))
        azimuth = np.arctan2(rel[:, 1], rel[:, 0]) * np.float32(L.cyl_radii[index])
        uv = np.where(on_cap[:, None], rel[:, :2], np.stack([azimuth, rel[:, 2]], axis=1))
        return normal, uv, on_cap.astype(np.int64)

    def _sphere_surface(self, index: int, points: np.ndarray):
        L = self.layout
        radius = np.float32(L.sphere_radii[index])
        rel = points - L.sphere_centers[index].astype(np.float32)
        normal = rel / radius
        uv = np.stack([np.arctan2(rel[:, 1], rel[:, 0]) * radius, rel[:, 2]], axis=1)
        return normal, uv, np.zeros(len(points), np.int64)


def _rotate_z(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """The synthetic camera: square pixels, about 64 degrees horizontal field of view, centred principal point."""
    focal = 0.8 * width
    return Intrinsics(focal, focal, width / 2.0, height / 2.0, width, height)
