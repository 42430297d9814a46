"""Camera corrections trained with the map: one small rigid motion per refinement view.

A view's world-to-camera matrix is used as exp(xi) @ viewmat, xi = (rho, omega) in the camera frame (rotation by
omega, then translation by rho; `worker.geometry.se3_exp`). The rasterizer's gradient with respect to the viewmat
flows to xi, so the refinement moves a keyframe's camera where the map's render fits its photo better, as
photometric bundle adjustment does. Each view's rotation and translation are parameters of their own: the optimiser
steps only the view just rendered (a parameter without a gradient is skipped), so views seen rarely do not drift
on momentum between their turns.
"""

from __future__ import annotations

import torch

from worker.geometry import se3_exp


class ViewPoseCorrections(torch.nn.Module):
    """Trainable camera-frame corrections of `count` views, all starting at the identity."""

    def __init__(self, count: int, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        super().__init__()
        self.translations = torch.nn.ParameterList(
            [torch.nn.Parameter(torch.zeros(3, dtype=dtype, device=device)) for _ in range(count)])
        self.rotations = torch.nn.ParameterList(
            [torch.nn.Parameter(torch.zeros(3, dtype=dtype, device=device)) for _ in range(count)])

    def correction(self, index: int) -> torch.Tensor:
        """The 4x4 camera-frame correction of view `index` (differentiable)."""
        return se3_exp(torch.cat([self.translations[index], self.rotations[index]]))

    def viewmat(self, index: int, viewmat: torch.Tensor) -> torch.Tensor:
        """View `index`'s corrected world-to-camera matrix."""
        return self.correction(index).to(viewmat.dtype) @ viewmat

    def corrections(self) -> list[torch.Tensor]:
        """Every view's correction, detached, float64."""
        with torch.no_grad():
            return [self.correction(i).to(torch.float64) for i in range(len(self.translations))]
