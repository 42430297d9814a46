"""The preset names a session may ask for (`preset` of POST /v1/sessions).

The presets themselves are the engine's (`worker.config.PRESETS`, torch-side); tests keep the names equal. `auto`
is no preset of its own: the worker chooses one from the session's input and its machine.
"""

from __future__ import annotations

from typing import Literal, get_args

PresetName = Literal["auto", "paper", "default", "fast", "rgbd", "test"]

AUTO = "auto"
PRESET_NAMES: tuple[str, ...] = get_args(PresetName)
ENGINE_PRESETS: tuple[str, ...] = tuple(name for name in PRESET_NAMES if name != AUTO)
"""The names `worker.config.PRESETS` defines."""


def check_preset(name: str) -> None:
    """Raise ValueError unless `name` is a preset name a session may ask for."""
    if name not in PRESET_NAMES:
        raise ValueError(f"choose one of {sorted(PRESET_NAMES)}")
