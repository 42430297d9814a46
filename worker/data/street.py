"""A procedural street for driving-like motion: a long canyon of facades seen from a car moving forward.

worker.data.synthetic_scene's renderer draws it: the "room" is a street 14-20 m wide and 400 m long whose walls
are the facades, its floor the road and its ceiling a high sky plane; along the kerbs stand parked cars (boxes),
poles and bins (cylinders), and facade details (thin boxes). The camera drives along the street at car height,
1-1.5 m per frame (36-54 km/h at 10 frames/s), drifting slowly across the lane and yawing a few degrees: forward
motion, a large depth range and few close points, the hard case for odometry. Exact depth and poses as for rooms.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from worker.data.synthetic_scene import Material, SceneLayout, SyntheticScene, _random_material, look_at_c2w

STREET_LENGTH = 400.0
SKY_HEIGHT = 30.0


def _coarser(material: Material, factor: float, kind: str | None = None) -> Material:
    return dataclasses.replace(material, period=material.period * factor, kind=kind or material.kind,
                               wave_freqs=(material.wave_freqs / factor).astype(np.float32))


def generate_street(rng: np.random.Generator) -> SceneLayout:
    """Facades at y = +-width/2, road at z = 0, objects along both kerbs, the lane along the x axis."""
    width = float(rng.uniform(14.0, 20.0))
    boxes = [(np.array([0.0, 0.0, SKY_HEIGHT / 2]), np.array([STREET_LENGTH / 2, width / 2, SKY_HEIGHT / 2]), 0.0)]
    cylinders = []
    kerb = width / 2 - 2.5
    x = -STREET_LENGTH / 2 + 5.0
    while x < STREET_LENGTH / 2 - 5.0:
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        kind = rng.uniform()
        if kind < 0.5:  # a parked car
            half = np.array([rng.uniform(1.8, 2.4), rng.uniform(0.8, 1.0), rng.uniform(0.6, 0.8)])
            boxes.append((np.array([x, side * (kerb - half[1]), half[2]]), half, float(rng.normal(0, 0.03))))
        elif kind < 0.75:  # a pole or a bin
            cylinders.append((np.array([x, side * (kerb + 0.8), 0.0]), float(rng.uniform(0.1, 0.4)),
                              float(rng.uniform(0.8, 5.0))))
        else:  # a doorway, shop front or balcony on the facade
            half = np.array([rng.uniform(1.0, 3.0), 0.3, rng.uniform(1.0, 3.0)])
            z = rng.uniform(half[2], 12.0)
            boxes.append((np.array([x, side * (width / 2 - half[1]), z]), half, 0.0))
        x += float(rng.uniform(3.0, 9.0))
    return SceneLayout(
        box_centers=np.array([b[0] for b in boxes]), box_halves=np.array([b[1] for b in boxes]),
        box_yaws=np.array([b[2] for b in boxes]),
        cyl_bases=np.array([c[0] for c in cylinders]).reshape(-1, 3), cyl_radii=np.array([c[1] for c in cylinders]),
        cyl_heights=np.array([c[2] for c in cylinders]),
        sphere_centers=np.zeros((0, 3)), sphere_radii=np.zeros(0),
        path_radii=(1.2, 0.0), path_height=1.5,
    )


class StreetScene(SyntheticScene):
    """A deterministic street (see the module docstring); renders like `SyntheticScene`."""

    def __init__(self, seed: int) -> None:
        if int(seed) != seed or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.seed = int(seed)
        rng = np.random.default_rng(self.seed + 7_000_000)  # streets and rooms of one seed are unrelated
        self.layout = generate_street(rng)
        count = len(self.layout.box_yaws) + len(self.layout.cyl_radii)
        # Coarser textures than a room's: facades and cars are seen from tens of metres.
        # The road, the facades and the sky are aperiodic (a perfect checker road would alias a car's motion).
        self.materials = [_coarser(_random_material(rng), 4.0, "noise" if k == 0 else None) for k in range(count)]
        self.room_materials = {"walls": self.materials[0], "floor": _coarser(_random_material(rng), 2.0, "noise"),
                               "ceiling": _coarser(_random_material(rng), 8.0, "noise")}
        light = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 1.0])
        self.light_dir = (light / np.linalg.norm(light)).astype(np.float32)
        self._speed = float(rng.uniform(1.0, 1.5))
        self._phase = rng.uniform(0, 2 * np.pi, 2)

    def camera_path(self, num_frames: int, revisit: bool = True) -> np.ndarray:
        """Forward along the street from its start (`revisit` is ignored: a drive does not come back)."""
        if num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        if (num_frames - 1) * self._speed > STREET_LENGTH - 40.0:
            raise ValueError(f"a street holds at most {int((STREET_LENGTH - 40) / self._speed)} frames")
        poses = np.empty((num_frames, 4, 4))
        lane = self.layout.path_radii[0]
        for i in range(num_frames):
            x = -STREET_LENGTH / 2 + 15.0 + self._speed * i
            y = lane * math.sin(0.02 * i + self._phase[0])
            yaw = 0.06 * math.sin(0.03 * i + self._phase[1])
            forward = np.array([math.cos(yaw), math.sin(yaw), -0.03])
            poses[i] = look_at_c2w(np.array([x, y, self.layout.path_height]), forward)
        return poses
