"""Renders of a stored map, for a session that localizes in it (`localize`: the map is what the user sees)."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import torch

from protocol.map_package import MapPackage
from worker.mapping import GaussianMap, MapConfig

from .package import load_gaussian_map


class StoredMapRenderer:
    """The stored map as a GaussianMap, loaded on the first render; renders as the mapping stage does."""

    def __init__(self, package: MapPackage) -> None:
        self.package = package
        self._map: GaussianMap | None = None
        self._lock = threading.Lock()

    def _loaded(self) -> GaussianMap:
        with self._lock:
            if self._map is None:  # no photos needed for renders: the map lets them go at once
                self._map = load_gaussian_map(self.package, config=MapConfig(archived_images=0))
            return self._map

    def render(self, pose_c2w: np.ndarray, K: torch.Tensor, width: int, height: int,
               as_captured_at: int | None = None) -> Any:
        """The stored map seen from `pose_c2w` (in the map's world); `as_captured_at` has no meaning here (the
        map's exposure-normalised colours)."""
        gmap = self._loaded()
        with self._lock, torch.no_grad():
            return gmap.render(torch.as_tensor(pose_c2w), K, width, height)
