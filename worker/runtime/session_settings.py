"""A session's engine settings as the worker decides them: named by the client, or chosen at its first frame.

The decision is written to the session record (`settings`: preset, overrides, tracking side, reasons) once, and a
worker that takes the session over before any snapshot reads it back from there, so a session keeps the settings
it started with even on a different machine.
"""

from __future__ import annotations

import functools
import json
from typing import Any

from worker.data.frame import Frame
from worker.settings_choice import AUTO, Machine, SessionInput, SettingsChoice, choose_settings, named_settings


@functools.cache
def this_machine(checkpoint: str = "") -> Machine:
    """The worker's machine (detected once per process)."""
    return Machine.detect(checkpoint or None)


def named_preset(session: dict[str, Any]) -> str | None:
    """The preset the client named at creation (None: none, or `auto`)."""
    preset = session.get("preset") or None
    return None if preset in (None, AUTO) else preset


def received_input(session: dict[str, Any], frame: Frame | None) -> SessionInput:
    """What the session receives, from its record (live or not, frame rate) and its first frame (None: unknown)."""
    rate = float(session.get("frame_rate") or 0) or None
    live = session.get("skip_frames") == "1"
    if frame is None:
        return SessionInput(frame_rate=rate, live=live)
    height, width = frame.image.shape[:2]
    return SessionInput(depth=frame.depth is not None, device_poses=frame.pose is not None, width=width,
                        height=height, frame_rate=rate, live=live)


def session_settings(session: dict[str, Any], frame: Frame | None, machine: Machine) -> SettingsChoice:
    """The settings recorded for the session, else those its named preset gives, else the decision for its input."""
    recorded = session.get("settings")
    if recorded:
        return SettingsChoice(**json.loads(recorded))
    named = named_preset(session)
    if named is not None:
        return named_settings(named)
    return choose_settings(received_input(session, frame), machine)
