"""Conversion between our 4x4 similarities and `gtsam.Similarity3`.

GTSAM stores Similarity3(R, t, s) as the map p -> s (R p + t) (matrix [R t; 0 1/s]), while ours is
p -> s R p + t. So our translation is GTSAM's times s.
"""

from __future__ import annotations

import gtsam
import numpy as np
import torch

from .transforms import make_sim3, sim3_decompose


def sim3_to_gtsam(T: torch.Tensor | np.ndarray) -> gtsam.Similarity3:
    """Our [4,4] similarity as a gtsam.Similarity3 describing the same map."""
    s, R, t = sim3_decompose(torch.as_tensor(T, dtype=torch.float64))
    return gtsam.Similarity3(gtsam.Rot3(R.numpy()), (t / s).numpy(), float(s))


def sim3_from_gtsam(S: gtsam.Similarity3) -> torch.Tensor:
    """A gtsam.Similarity3 as our [4,4] float64 similarity."""
    s = float(S.scale())
    R = torch.from_numpy(np.asarray(S.rotation().matrix(), dtype=np.float64))
    t = torch.from_numpy(np.asarray(S.translation(), dtype=np.float64)) * s
    return make_sim3(R, t, s)
