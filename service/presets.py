"""What each engine preset is for and which input suits it, for clients: GET /v1/presets and the session schema.

The names are `protocol.presets.PresetName`; the presets themselves live in `worker.config.PRESETS` (tests keep
the lists equal). `auto` is no preset of its
own: the worker chooses one from the session's input and its machine (`worker.settings_choice`).
"""

from __future__ import annotations

from protocol.presets import PRESET_NAMES, PresetName

__all__ = ["INPUT_MODES", "PRESET_INFO", "PresetName", "preset_field_description", "preset_list"]
# name -> (what it is for, which input it suits)
PRESET_INFO: dict[str, tuple[str, str]] = {
    "auto": ("the default (a session that names no preset): the worker chooses at the session's first frame from "
             "what it receives (depth, device poses, frame size, live or recorded) and its machine: `paper` where "
             "a CUDA GPU and trained weights exist, else `rgbd` (on a GPU, mapped there); a live stream "
             "(`skip_frames`) with frames over 320 px is tracked and mapped at 320 px on a CPU (on a GPU, RGB-D is "
             "tracked at 320 px and mapped whole). The session's `settings` says what was "
             "chosen and why; `auto_choices` here what this fleet's workers choose", "any input"),
    "paper": ("the paper's settings: paper-size model, 512-pixel images, on a CUDA GPU; needs weights converted "
              "from CUT3R (`flashmono convert-cut3r`)", "RGB only (monocular), any input on a GPU"),
    "default": ("the paper's mapping settings (20 refinement iterations over 5 keyframes) on whatever device is "
                "there; the shipped small model only where no geometric pose source applies", "any input"),
    "fast": ("CPU-friendly: 224-pixel images, fewer refinement iterations; with depth, surfels come from the depth",
             "RGB-D frames (phones with LiDAR), with or without device poses"),
    "rgbd": ("best maps on a CPU: surfels from the depth (the sensor's, or multi-view stereo on the tracked poses), "
             "a final refinement over every keyframe at finish (tens of seconds; 28.9 dB PSNR on ICL)",
             "every input on a CPU: RGB-D with or without device poses, posed RGB (ARKit/ARCore without LiDAR), RGB "
             "only"),
    "test": ("unit tests only: tiny images, few iterations, single-threaded", "anything (not for real use)"),
}

INPUT_MODES = (
    "The input mode follows from the fields the session's first frame carries and holds for the whole session: "
    "`pose` -> posed (device poses are the odometry; refined as priors, or kept as sent with pose_mode fixed; "
    "without `depth`, surfels come from multi-view stereo); `depth` without `pose` -> RGB-D (dense RGB-D "
    "odometry); neither -> monocular (visual odometry: the scale is arbitrary, the focal length is estimated unless "
    "intrinsics are given, surfels come from multi-view stereo). Tracking losses and recoveries arrive as "
    "`tracking_lost` / `relocalized` messages. Later frames must carry the same fields and have the same size."
)


assert tuple(PRESET_INFO) == PRESET_NAMES, "every preset name needs its description"


def preset_list() -> list[dict[str, str]]:
    """[{name, purpose, input}] for GET /v1/presets."""
    return [{"name": name, "purpose": purpose, "input": suits} for name, (purpose, suits) in PRESET_INFO.items()]


def preset_field_description() -> str:
    """The `preset` field's description in the session schema: one line per preset."""
    lines = [f"- `{name}`: {purpose}. Suits: {suits}." for name, (purpose, suits) in PRESET_INFO.items()]
    return ("Engine preset (GET /v1/presets lists them); omitted: `auto`, chosen from the input and the worker's "
            "machine.\n"
            + "\n".join(lines) + "\n" + INPUT_MODES)
