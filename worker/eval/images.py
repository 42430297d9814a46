"""Images as the metrics take them: any channels-last RGB brought to one tensor layout."""

from __future__ import annotations

import numpy as np
import torch


def as_image_batch(image: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Channels-last RGB ([H, W, 3] or [B, H, W, 3]; uint8 or float in [0, 1]) as float64 [B, 3, H, W] in [0, 1]."""
    tensor = torch.as_tensor(np.ascontiguousarray(image) if isinstance(image, np.ndarray) else image)
    if tensor.ndim == 3:
        tensor = tensor[None]
    if tensor.ndim != 4 or tensor.shape[-1] != 3:
        raise ValueError(f"images must be channels-last RGB [H, W, 3] or [B, H, W, 3], got {tuple(tensor.shape)}")
    tensor = tensor.detach().cpu()
    tensor = tensor.double() / 255.0 if tensor.dtype == torch.uint8 else tensor.double().clamp(0.0, 1.0)
    return tensor.permute(0, 3, 1, 2)  # a view: SSIM goes back to channels-last for free
