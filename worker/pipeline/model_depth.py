"""The learned model's single-view depth of a keyframe, at the frame's resolution: the filler for pixels that
multi-view stereo leaves without a confident depth (`input.mvs_fill = "model"`).

The model runs once per keyframe from a fresh state (no recurrence: one view), so it costs one forward pass per
keyframe rather than one per frame. Its depth is in its own units; the caller scales it to the confident
multi-view depth (worker.depth.scale_to_confident) before use.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from worker.frontend.preprocess import prepare_image, resample_for


class ModelDepth:
    """`depth(image) -> float32 [H, W]` (0 outside the model's centre crop) from a feed-forward model."""

    def __init__(self, model, long_side: int) -> None:
        self.model, self.long_side = model, long_side

    @torch.no_grad()
    def depth(self, image: np.ndarray) -> np.ndarray:
        h, w = image.shape[:2]
        prep = prepare_image(image, None, long_side=self.long_side, resample=resample_for(self.model))
        out = self.model.step(prep.tensor, self.model.init_state(), update=False)
        z = out.points_cam[0, ..., 2].float().clamp_min(0).cpu().numpy()
        left, top, crop_w, crop_h = prep.crop
        resized = np.zeros((round(h * prep.scale), round(w * prep.scale)), np.float32)
        resized[top:top + crop_h, left:left + crop_w] = z
        return cv2.resize(resized, (w, h), interpolation=cv2.INTER_NEAREST)
