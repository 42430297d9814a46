"""The 2DGS map primitive set: a struct of arrays with the keyframe each surfel is bound to."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from worker.geometry import quat_multiply, quat_normalize, rotmat_to_quat, sim3_decompose


@dataclass
class Surfels:
    """N 2D Gaussian surfels with activated attributes.

    means [N,3] world (or camera) positions; quats [N,4] wxyz rotations whose third column is the normal;
    scales [N,2] tangent-plane standard deviations (> 0); opacities [N] in (0,1); colors [N,3] RGB in [0,1];
    keyframe_ids [N] int64, the keyframe a surfel is rigidly bound to (-1 when unbound).
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    keyframe_ids: torch.Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 2), "opacities": (n,), "colors": (n, 3),
                    "keyframe_ids": (n,)}
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Surfels.{name} must have shape {shape}, got {got}")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def device(self) -> torch.device:
        return self.means.device

    def tensors(self) -> dict[str, torch.Tensor]:
        """The attributes by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def empty(cls, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> Surfels:
        return cls(
            means=torch.zeros(0, 3, dtype=dtype, device=device),
            quats=torch.zeros(0, 4, dtype=dtype, device=device),
            scales=torch.zeros(0, 2, dtype=dtype, device=device),
            opacities=torch.zeros(0, dtype=dtype, device=device),
            colors=torch.zeros(0, 3, dtype=dtype, device=device),
            keyframe_ids=torch.zeros(0, dtype=torch.int64, device=device),
        )

    def select(self, index: torch.Tensor) -> Surfels:
        """The subset given by a boolean mask or an index tensor."""
        return Surfels(**{k: v[index] for k, v in self.tensors().items()})

    @staticmethod
    def concat(parts: list[Surfels]) -> Surfels:
        """All surfels of `parts`, in order."""
        if not parts:
            return Surfels.empty()
        return Surfels(**{k: torch.cat([p.tensors()[k] for p in parts], dim=0) for k in parts[0].tensors()})

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Surfels:
        """Move to a device and/or cast the float attributes (keyframe ids stay int64)."""
        out = {}
        for k, v in self.tensors().items():
            out[k] = v.to(device=device) if k == "keyframe_ids" else v.to(device=device, dtype=dtype)
        return Surfels(**out)

    def detach(self) -> Surfels:
        return Surfels(**{k: v.detach() for k, v in self.tensors().items()})

    def clone(self) -> Surfels:
        return Surfels(**{k: v.clone() for k, v in self.tensors().items()})

    def transform(self, sim3: torch.Tensor) -> Surfels:
        """Apply one similarity (paper eq. 17): means -> s R mu + t, rotations -> q_R * r, scales -> s * scales."""
        s, R, t = sim3_decompose(sim3.to(self.means.dtype))
        q = rotmat_to_quat(R)
        return Surfels(
            means=self.means @ (s * R).T + t,
            quats=quat_normalize(quat_multiply(q.expand_as(self.quats), self.quats)),
            scales=self.scales * s,
            opacities=self.opacities,
            colors=self.colors,
            keyframe_ids=self.keyframe_ids,
        )

    def transform_per_surfel(self, sim3s: torch.Tensor) -> Surfels:
        """Apply a different similarity [N,4,4] to each surfel (used by loop correction)."""
        s, R, t = sim3_decompose(sim3s.to(self.means.dtype))
        q = rotmat_to_quat(R)
        return Surfels(
            means=(s[:, None, None] * R @ self.means[:, :, None])[..., 0] + t,
            quats=quat_normalize(quat_multiply(q, self.quats)),
            scales=self.scales * s[:, None],
            opacities=self.opacities,
            colors=self.colors,
            keyframe_ids=self.keyframe_ids,
        )
