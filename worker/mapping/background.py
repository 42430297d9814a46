"""What a view sees where the map has no surface: colour by world direction (a cube map), as a sky box.

Multi-view stereo gives no depth to the sky, to surfaces too far for any parallax, or to plain regions; renders were
black there, and the refinement, whose target there is bright, grew nearby surfels into the empty pixels (floaters
and smears across the sky of a street). The background remembers, per world direction, the colour keyframes saw where
the map left their pixels uncovered, and every render (refinement, held-out views, the service's images) composites
it behind the surfels: colour = surfels + (1 - alpha) * background. Depth and alpha stay the surfels' own, so holes
are still measured as holes and depth is never invented.

The cube map's six faces hold a running mean of exposure-normalised colour per cell (sum and weight) and how often
keyframes saw the map there instead. A direction belongs to the background only where keyframes mostly saw through
the map (the sky: always): a keyframe's border band, which stereo leaves without depth but the next keyframes cover,
stays a hole the refinement fills with surfels, as before. Directions never seen through the map render black.
Directions are in the world frame: the background stands for things at infinity, so it does not move with the
camera's position.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from worker.geometry import pixel_grid

# Cells per cube-face side: 90 degrees / 64 = 1.4 degrees a cell (the sky is smooth; a snapshot carries 6 x 64 x 64 x
# 5 floats, 492 KB).
FACE_CELLS = 64
# Pixels whose map coverage (alpha) is below this count as seeing the background.
UNCOVERED_ALPHA = 0.5


def pixel_directions(pose_c2w: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H, W, 3] unit world directions of the rays through the pixel centres (x + 0.5, y + 0.5) of a camera."""
    K = K.to(torch.float64).cpu()
    uv = pixel_grid(width, height, torch.float64)
    rays = torch.stack([(uv[..., 0] - K[0, 2]) / K[0, 0], (uv[..., 1] - K[1, 2]) / K[1, 1],
                        torch.ones(height, width, dtype=torch.float64)], -1)
    R = pose_c2w.to(torch.float64).cpu()[:3, :3]
    R = R / torch.linalg.norm(R[:, 0])  # a Sim(3) pose's scale does not turn a direction
    world = rays @ R.T
    return world / torch.linalg.norm(world, dim=-1, keepdim=True)


def cube_coordinates(directions: torch.Tensor, face_cells: int = FACE_CELLS) -> tuple[torch.Tensor, torch.Tensor,
                                                                                  torch.Tensor]:
    """(face, row, col) of unit directions [..., 3] on a cube map of `face_cells` cells a side: the face is the
    dominant axis and its sign, row and col (continuous, cell centres at whole numbers) the other two coordinates
    over the dominant one."""
    absolute = directions.abs()
    axis = absolute.argmax(-1)
    negative = torch.gather(directions, -1, axis.unsqueeze(-1)).squeeze(-1) < 0
    face = 2 * axis + negative.long()
    major = torch.gather(absolute, -1, axis.unsqueeze(-1)).squeeze(-1).clamp_min(1e-12)
    u = torch.gather(directions, -1, torch.where(axis == 0, 1, 0).unsqueeze(-1)).squeeze(-1) / major
    v = torch.gather(directions, -1, torch.where(axis == 2, 1, 2).unsqueeze(-1)).squeeze(-1) / major
    return face, (v + 1) * 0.5 * face_cells - 0.5, (u + 1) * 0.5 * face_cells - 0.5


def cube_cells(directions: torch.Tensor, face_cells: int = FACE_CELLS) -> torch.Tensor:
    """[...] flat index (face * n * n + row * n + col) of the cell each unit direction [..., 3] falls in."""
    face, row, col = cube_coordinates(directions, face_cells)
    row = torch.round(row).long().clamp(0, face_cells - 1)
    col = torch.round(col).long().clamp(0, face_cells - 1)
    return (face * face_cells + row) * face_cells + col


class DirectionalBackground:
    """The map's background: mean colour per world direction of what keyframes saw through the map's holes."""

    def __init__(self, face_cells: int = FACE_CELLS) -> None:
        self.face_cells = face_cells
        cells = 6 * face_cells * face_cells
        self.colour_sum = torch.zeros(cells, 3, dtype=torch.float32)
        self.weight = torch.zeros(cells, dtype=torch.float32)  # pixels that saw through the map
        self.covered = torch.zeros(cells, dtype=torch.float32)  # pixels that saw the map

    def _background_cells(self) -> torch.Tensor:
        """[cells] float: 1 where keyframes saw through the map more often than they saw the map."""
        return ((self.weight > 0) & (self.weight > self.covered)).to(torch.float32)

    @property
    def cells_seen(self) -> int:
        """Cells that belong to the background."""
        return int(self._background_cells().sum())

    def observe(self, pose_c2w: torch.Tensor, K: torch.Tensor, image: torch.Tensor, alpha: torch.Tensor) -> int:
        """Add a keyframe's colours (exposure-normalised, [H, W, 3] in [0, 1]) at the pixels the map leaves
        uncovered (`alpha` [H, W] below UNCOVERED_ALPHA); returns how many pixels were taken."""
        height, width = image.shape[:2]
        uncovered = (alpha.detach().cpu() < UNCOVERED_ALPHA)
        all_cells = cube_cells(pixel_directions(pose_c2w, K, width, height), self.face_cells)
        seen_map = all_cells[~uncovered]
        self.covered.index_add_(0, seen_map, torch.ones(len(seen_map), dtype=torch.float32))
        if not bool(uncovered.any()):
            return 0
        cells = all_cells[uncovered]
        colours = image.detach().cpu().to(torch.float32)[uncovered]
        self.colour_sum.index_add_(0, cells, colours)
        self.weight.index_add_(0, cells, torch.ones(len(cells), dtype=torch.float32))
        return int(len(cells))

    def image(self, pose_c2w: torch.Tensor, K: torch.Tensor, width: int, height: int,
              device: torch.device | str = "cpu") -> torch.Tensor | None:
        """[H, W, 3] background colours a camera sees (black in directions outside the background); None while the
        background is empty. Looked up on a grid of pixels about half a cube cell apart (a cell spans several
        pixels of a keyframe-sized view) and scaled up bilinearly: refinement asks for every view it renders."""
        seen = self._background_cells()
        if not bool(seen.any()):
            return None
        K = K.to(torch.float64).cpu()
        cell_pixels = float(K[0, 0]) * (math.pi / 2) / self.face_cells
        step = max(1, int(cell_pixels / 2))
        if step == 1:
            return self._lookup(seen, pose_c2w, K, width, height).to(device)
        coarse_width, coarse_height = -(-width // step), -(-height // step)
        coarse_K = K.clone()
        coarse_K[:2, :2] /= step
        coarse_K[:2, 2] = (K[:2, 2] + 0.5) / step - 0.5  # pixel centres stay where they were
        coarse = self._lookup(seen, pose_c2w, coarse_K, coarse_width, coarse_height)
        fine = F.interpolate(coarse.permute(2, 0, 1).unsqueeze(0), size=(coarse_height * step, coarse_width * step),
                             mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
        return fine[:height, :width].contiguous().to(device)

    def _lookup(self, seen: torch.Tensor, pose_c2w: torch.Tensor, K: torch.Tensor, width: int, height: int
                ) -> torch.Tensor:
        """[H, W, 3] background colours at the pixel centres of a camera, bilinear between the four nearest cell
        centres of the face, over the cells that belong to the background (`seen`)."""
        colour = self.colour_sum / self.weight.clamp_min(1e-6).unsqueeze(-1)
        n = self.face_cells
        face, row, col = cube_coordinates(pixel_directions(pose_c2w, K, width, height), n)
        row0, col0 = torch.floor(row), torch.floor(col)
        total = torch.zeros(height, width, 3, dtype=torch.float32)
        norm = torch.zeros(height, width, dtype=torch.float32)
        for dr in (0, 1):
            for dc in (0, 1):
                weight = ((1 - (row - row0 - dr).abs()) * (1 - (col - col0 - dc).abs())).to(torch.float32)
                r = (row0 + dr).long().clamp(0, n - 1)
                c = (col0 + dc).long().clamp(0, n - 1)
                cell = (face * n + r) * n + c
                weight = weight * seen[cell]
                total += weight.unsqueeze(-1) * colour[cell]
                norm += weight
        return total / norm.clamp_min(1e-6).unsqueeze(-1)

    def state_dict(self) -> dict:
        return {"face_cells": self.face_cells, "colour_sum": self.colour_sum.numpy(), "weight": self.weight.numpy(),
                "covered": self.covered.numpy()}

    @classmethod
    def from_state(cls, state: dict) -> DirectionalBackground:
        background = cls(int(state["face_cells"]))
        colour_sum = torch.from_numpy(np.array(state["colour_sum"], np.float32)).reshape(-1, 3)
        weight = torch.from_numpy(np.array(state["weight"], np.float32)).reshape(-1)
        covered = torch.from_numpy(np.array(state["covered"], np.float32)).reshape(-1)
        if colour_sum.shape != background.colour_sum.shape or weight.shape != background.weight.shape or \
                covered.shape != weight.shape:
            raise ValueError("background state does not match its cube map's size")
        background.colour_sum, background.weight, background.covered = colour_sum, weight, covered
        return background


def composite(rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor | None) -> torch.Tensor:
    """Surfel colour [H, W, 3] (rendered over black) with `background` [H, W, 3] behind it (None: as it is)."""
    if background is None:
        return rgb
    return rgb + (1.0 - alpha).unsqueeze(-1).to(rgb.dtype) * background.to(rgb.dtype)
