"""Our own checkpoints: safetensors with the model configuration (and user metadata) in the header."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from .configs import FrontendConfig
from .model import FeedForwardModel, build_model

CONFIG_KEY = "flashmono.frontend_config"
NAME_KEY = "flashmono.config_name"
USER_KEY = "flashmono.metadata"


def save_checkpoint(model: FeedForwardModel, path: str | Path, metadata: dict | None = None) -> Path:
    """Write the model's weights and configuration to `path` (.safetensors). `metadata` must be JSON-serialisable."""
    try:
        user = json.dumps(metadata or {})
    except TypeError as exc:
        raise ValueError(f"checkpoint metadata must be JSON-serialisable: {exc}") from None
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    header = {
        NAME_KEY: model.config.name,
        CONFIG_KEY: json.dumps(model.config.to_dict()),
        USER_KEY: user,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(path), metadata=header)
    return path


def read_checkpoint_metadata(path: str | Path) -> tuple[FrontendConfig, dict]:
    """The configuration and the user metadata stored in a checkpoint, without loading its tensors."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"checkpoint not found: {path}")
    try:
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
    except Exception as exc:  # safetensors raises its own error types for malformed files
        raise ValueError(f"{path} is not a safetensors checkpoint: {exc}") from None
    if CONFIG_KEY not in header:
        raise ValueError(f"{path} has no Flash-Mono frontend configuration in its header")
    config = FrontendConfig.from_dict(json.loads(header[CONFIG_KEY]))
    return config, json.loads(header.get(USER_KEY, "{}"))


def load_checkpoint(path: str | Path, device: torch.device | str = "cpu") -> FeedForwardModel:
    """Build the model from the configuration stored in the checkpoint and load its weights (strictly)."""
    config, user = read_checkpoint_metadata(path)
    model = build_model(config, device="meta")
    state = {}
    with safe_open(str(path), framework="pt", device=str(device)) as f:
        for key in f.keys():
            state[key] = f.get_tensor(key)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise ValueError(f"checkpoint {path} does not match config {config.name!r}: missing {missing[:5]}, "
                         f"unexpected {unexpected[:5]}")
    for key, value in state.items():
        if value.shape != expected[key].shape:
            raise ValueError(f"{key}: checkpoint shape {tuple(value.shape)} != model {tuple(expected[key].shape)}")
    model.load_state_dict(state, assign=True)
    model.downstream_head.to(memory_format=torch.channels_last)
    model.checkpoint_metadata = user
    return model.eval()
