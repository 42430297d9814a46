"""Model configurations (`tiny` ... `paper`) and the parameter tally grouped as in the paper's Table 7.

The `paper` configuration is CUT3R-512 (793,307,858 parameters; see cut3r_spec.md section 5) plus what Flash-Mono
needs for 2DGS, which brings it to the paper's 795.7 M:

* CUT3R's RGB DPT (`dpt_rgb`, 3 output channels) becomes the Gaussian DPT `dpt_gs` with 10 output channels
  (colour 3, opacity 1, rotation 4, 2D scale 2): +129 * 7 = 903 parameters. Its colour rows are initialised
  from CUT3R's RGB head on conversion; the other 7 rows are new.
* A residual token adapter `gs_adapter` (MLP 768 -> 1536 -> 768, last layer zero-initialised) in front of the
  Gaussian DPT, so the 2DGS attributes can specialise away from the tokens shared with the means head:
  768*1536 + 1536 + 1536*768 + 768 = 2,361,600 parameters.

Total 793,307,858 + 903 + 2,361,600 = 795,670,361 (795.7 M); encoder 303,098,880 (303.1 M); decoder (both decoders
and the pose memory) 380,762,112 (380.8 M); heads and tokens (ray-map branch, tokens, DPTs, adaLN final transform,
pose MLP, GS adapter) 111,809,369 (111.8 M).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from torch import nn

GAUSSIAN_CHANNELS = 10  # colour 3, opacity 1, rotation (wxyz) 4, 2D scale 2


@dataclass(frozen=True)
class FrontendConfig:
    """Every size of the recurrent feed-forward model. Field names follow CUT3R's where one exists."""

    name: str
    enc_dim: int
    enc_depth: int
    enc_heads: int
    dec_dim: int
    dec_depth: int
    dec_heads: int
    state_dec_heads: int
    state_size: int
    memory_size: int
    memory_heads: int
    memory_depth: int = 2  # read blocks and write blocks each
    ray_enc_depth: int = 2
    final_transform_depth: int = 2
    mlp_ratio: float = 4.0
    patch_size: int = 16
    rope_base: float = 100.0
    dpt_layer_dims: tuple[int, int, int, int] = (96, 192, 384, 768)
    dpt_feature_dim: int = 256
    dpt_last_dim: int = 128
    gs_adapter_hidden: int = 1536
    image_long_side: int = 512
    # Gaussian colour = sigmoid(logit(input pixel colour) + raw) instead of sigmoid(raw): each per-pixel surfel starts
    # from its own pixel's colour and the head learns a residual. Off for `paper` (CUT3R's RGB head loads exactly).
    color_skip: bool = False

    def __post_init__(self) -> None:
        if self.enc_dim % self.enc_heads or self.dec_dim % self.dec_heads or self.dec_dim % self.state_dec_heads:
            raise ValueError(f"config {self.name}: widths must be divisible by their head counts")
        if (2 * self.dec_dim) % self.memory_heads:
            raise ValueError(f"config {self.name}: pose-memory width {2 * self.dec_dim} not divisible by heads")
        for dim, heads in ((self.enc_dim, self.enc_heads), (self.dec_dim, self.dec_heads),
                           (self.dec_dim, self.state_dec_heads)):
            if (dim // heads) % 4:
                raise ValueError(f"config {self.name}: 2D RoPE needs a head dimension divisible by 4")
        if self.dec_depth < 4:
            raise ValueError(f"config {self.name}: the DPT hooks need at least 4 decoder layers")
        if self.image_long_side % self.patch_size:
            raise ValueError(f"config {self.name}: image_long_side must be a multiple of the patch size")

    @property
    def dpt_hooks(self) -> tuple[int, int, int]:
        """Decoder layers feeding the DPT heads besides the encoder output (6, 9, 12 for 12 layers)."""
        return self.dec_depth // 2, (3 * self.dec_depth) // 4, self.dec_depth

    def to_dict(self) -> dict:
        d = asdict(self)
        d["dpt_layer_dims"] = list(self.dpt_layer_dims)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> FrontendConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config fields: {sorted(unknown)}")
        d = dict(d)
        if "dpt_layer_dims" in d:
            d["dpt_layer_dims"] = tuple(int(x) for x in d["dpt_layer_dims"])
        return cls(**d)


CONFIGS: dict[str, FrontendConfig] = {
    # CUT3R-512 plus the 2DGS head (module docstring).
    "paper": FrontendConfig(
        name="paper", enc_dim=1024, enc_depth=24, enc_heads=16, dec_dim=768, dec_depth=12, dec_heads=12,
        state_dec_heads=16, state_size=768, memory_size=256, memory_heads=12,
    ),
    "base": FrontendConfig(
        name="base", enc_dim=768, enc_depth=12, enc_heads=12, dec_dim=512, dec_depth=8, dec_heads=8,
        state_dec_heads=8, state_size=512, memory_size=128, memory_heads=8, ray_enc_depth=1,
        dpt_layer_dims=(64, 128, 256, 512), dpt_feature_dim=128, dpt_last_dim=64, gs_adapter_hidden=1024,
        image_long_side=512,
    ),
    "small": FrontendConfig(
        name="small", enc_dim=384, enc_depth=8, enc_heads=6, dec_dim=256, dec_depth=6, dec_heads=8,
        state_dec_heads=8, state_size=256, memory_size=64, memory_heads=8, ray_enc_depth=1,
        dpt_layer_dims=(48, 96, 192, 256), dpt_feature_dim=64, dpt_last_dim=32, gs_adapter_hidden=512,
        image_long_side=384, color_skip=True,
    ),
    # Trainable on 2 CPU cores; 224-wide frames (224x160: about 1.7 GFLOP per step).
    "tiny": FrontendConfig(
        name="tiny", enc_dim=192, enc_depth=4, enc_heads=3, dec_dim=128, dec_depth=4, dec_heads=4,
        state_dec_heads=4, state_size=64, memory_size=16, memory_heads=4, ray_enc_depth=1,
        dpt_layer_dims=(16, 32, 64, 128), dpt_feature_dim=16, dpt_last_dim=8, gs_adapter_hidden=256,
        image_long_side=224, color_skip=True,
    ),
}


def get_config(name: str) -> FrontendConfig:
    """The named configuration; ValueError listing the known names otherwise."""
    try:
        return CONFIGS[name]
    except KeyError:
        raise ValueError(f"unknown frontend config {name!r}; known: {sorted(CONFIGS)}") from None


ENCODER_PREFIXES = ("patch_embed.", "enc_blocks.", "enc_norm.")
DECODER_PREFIXES = (
    "decoder_embed.", "dec_blocks.", "dec_norm.", "decoder_embed_state.", "dec_blocks_state.", "dec_norm_state.",
    "pose_retriever.",
)


def parameter_tally(model: nn.Module) -> dict[str, int]:
    """Parameter counts grouped as in the paper's Table 7: encoder, decoder (both decoders and the pose memory),
    heads_and_tokens (everything else), and total. Works on meta-device models."""
    tally = {"encoder": 0, "decoder": 0, "heads_and_tokens": 0}
    for name, p in model.named_parameters():
        if name.startswith(ENCODER_PREFIXES):
            tally["encoder"] += p.numel()
        elif name.startswith(DECODER_PREFIXES):
            tally["decoder"] += p.numel()
        else:
            tally["heads_and_tokens"] += p.numel()
    tally["total"] = sum(tally.values())
    return tally
