"""LPIPS (Zhang et al. 2018, v0.1, AlexNet backbone), computed only when its weights are already on disk.

Two files are needed and neither ships on PyPI with this project: the ImageNet AlexNet backbone that torchvision
downloads into the torch hub cache (`<torch hub dir>/checkpoints/alexnet-owt-7be5be79.pth`) and the LPIPS linear
heads (`alex.pth`, shipped inside the `lpips` and `torchmetrics` packages, or placed as
`<torch hub dir>/checkpoints/lpips_alex_v0.1.pth`). When either is missing, `Lpips.load()` returns an instance with
`available == False` and a `reason`, and calling it returns None: a random-backbone LPIPS would not be comparable
with published numbers, so none is computed. Files are read with `torch.load(weights_only=True)`.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .images import as_image_batch

BACKBONE_FILE = "alexnet-owt-7be5be79.pth"
HEADS_FILE = "lpips_alex_v0.1.pth"
_CHANNELS = (64, 192, 384, 256, 256)
_CONV_INDICES = (0, 3, 6, 8, 10)  # torchvision alexnet.features indices of the five convolutions
_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)


class AlexNetFeatures(nn.Module):
    """The five ReLU outputs of AlexNet's convolutional trunk (torchvision layout and parameter names)."""

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        )

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        for index, layer in enumerate(self.features):
            x = layer(x)
            if index - 1 in _CONV_INDICES:  # right after each convolution's ReLU
                taps.append(x)
        return taps


def candidate_head_files() -> list[Path]:
    """Where the LPIPS AlexNet linear heads may be, in order of preference."""
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    paths = [hub / HEADS_FILE]
    packaged = (("lpips", "weights/v0.1/alex.pth"), ("torchmetrics", "functional/image/lpips_models/alex.pth"))
    for package, relative in packaged:
        spec = importlib.util.find_spec(package)  # locate without importing (lpips imports torchvision)
        if spec is not None and spec.submodule_search_locations:
            paths.extend(Path(loc) / relative for loc in spec.submodule_search_locations)
    return paths


class Lpips:
    """LPIPS distance between two RGB images (channels-last, uint8 or float in [0, 1]); lower is more similar."""

    def __init__(self, backbone: AlexNetFeatures | None, heads: list[torch.Tensor] | None, reason: str = "") -> None:
        self.backbone = backbone
        self.heads = heads
        self.reason = reason

    @property
    def available(self) -> bool:
        return self.backbone is not None and self.heads is not None

    @classmethod
    def load(cls, backbone_path: str | Path | None = None, heads_path: str | Path | None = None) -> Lpips:
        """Load from the given files or the default locations; never downloads anything."""
        default_backbone = Path(torch.hub.get_dir()) / "checkpoints" / BACKBONE_FILE
        backbone_path = Path(backbone_path) if backbone_path else default_backbone
        if not backbone_path.is_file():
            return cls(None, None, f"LPIPS not available: AlexNet backbone weights not found at {backbone_path}")
        if heads_path is None:
            heads_path = next((p for p in candidate_head_files() if p.is_file()), None)
            if heads_path is None:
                return cls(None, None, "LPIPS not available: linear heads (alex.pth) not found in "
                                       + ", ".join(str(p) for p in candidate_head_files()))
        heads_path = Path(heads_path)
        if not heads_path.is_file():
            return cls(None, None, f"LPIPS not available: linear heads not found at {heads_path}")
        backbone = AlexNetFeatures()
        state = torch.load(backbone_path, map_location="cpu", weights_only=True)
        trunk = {k: v for k, v in state.items() if k.startswith("features.")}
        missing = backbone.load_state_dict(trunk, strict=False).missing_keys
        if missing:
            raise ValueError(f"{backbone_path} is not an AlexNet checkpoint: missing {missing}")
        head_state = torch.load(heads_path, map_location="cpu", weights_only=True)
        heads = []
        for k, channels in enumerate(_CHANNELS):
            weight = head_state.get(f"lin{k}.model.1.weight")
            if weight is None or tuple(weight.shape) != (1, channels, 1, 1):
                raise ValueError(f"{heads_path} has no lin{k}.model.1.weight of shape (1, {channels}, 1, 1)")
            heads.append(weight.float())
        backbone.eval()
        return cls(backbone, heads)

    @torch.no_grad()
    def __call__(self, prediction, target) -> float | None:
        """The LPIPS distance, or None when the weights are not available."""
        if not self.available:
            return None
        pred, gt = as_image_batch(prediction).float(), as_image_batch(target).float()
        if pred.shape != gt.shape:
            raise ValueError(f"images differ in shape: {tuple(pred.shape)} vs {tuple(gt.shape)}")
        feats_p = self.backbone((pred * 2 - 1 - _SHIFT) / _SCALE)
        feats_t = self.backbone((gt * 2 - 1 - _SHIFT) / _SCALE)
        total = torch.zeros(pred.shape[0])
        for fp, ft, head in zip(feats_p, feats_t, self.heads):
            fp = fp / (fp.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            ft = ft / (ft.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total += F.conv2d((fp - ft) ** 2, head).mean(dim=(1, 2, 3))
        return float(total.mean())
