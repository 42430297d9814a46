"""One decision of a session's engine settings from what it receives and the machine it runs on.

Every entry point that names no preset ends here: a session created over REST, the SDK, `flashmono stream`, the
capture page and the demo (the worker decides at the session's first frame, when the input is known), and
`flashmono run` (before its first frame, from the source). A named preset overrides the decision.

The rule, in order:
1. A CUDA GPU and trained weights (a checkpoint that is not the shipped toy model, `FLASHMONO_CHECKPOINT`):
   the paper's settings (`paper`), the only place they are chosen.
2. Otherwise the CPU mapping settings (`rgbd`: surfels from the sensor's depth or from multi-view stereo on the
   tracked poses, a final refinement at finish), for every input mode: the learned model's path needs trained
   weights to be worth its cost. On a GPU without trained weights the same settings run their mapping on the GPU.
3. A live stream (frames skipped when tracking falls behind) from a camera whose long side is over
   `LIVE_WORKING_SIDE`, mapped on a CPU, is worked on at that side: its frames are tracked and mapped at 320 px
   (the map renders at any size). On 2 cores a 640x480 live map falls behind and never gets its final refinement:
   measured through the service on ICL at 30 frames/s (bench/results/out_of_box), 640x480 frames mapped whole gave
   19.1-26.1 dB and finishes of 27-44 s, with 2.5-3.4 GB of worker memory, where 320x240 gave 27.8-30.1 dB and
   23.5-25.6 s. Recordings (every frame tracked) keep their size.
4. On a GPU without trained weights (mapping keeps up there), a live RGB-D stream over `LIVE_TRACKING_SIDE` is
   tracked at that side and mapped whole: dense RGB-D alignment runs on the CPU and its cost grows with the pixels
   (on 2 cores, ICL 640x480 RGB-D: 197 of 211 frames posed, p95 118 ms at 640 against 207, 78 ms at 320). Without
   depth (visual odometry on features) frames are tracked at their size (ICL RGB only at 640: ATE 1.11 cm, 1.76 at
   320).

5. Frames without depth (RGB only, and posed RGB) on a CPU with at least `MAPPING_PROCESS_CORES` cores: mapping
   (multi-view depth, fusion, refinement) runs in a process of its own beside tracking (`mapping.process`,
   worker.pipeline.mapping_process). Visual odometry's feature tracking is Python-heavy and otherwise waits for
   mapping's share of the interpreter, and posed RGB runs it whenever the device's poses disagree with the images
   (seeded). Measured live through the service (bench/results/out_of_box, 2 cores, 30 frames/s): TUM fr1/xyz RGB
   only 2.33 cm / 18.90 dB against 4.14 cm / 16.74 dB with a mapping thread (offline 1.96 cm); TUM posed RGB
   (seeded) 66-86 % of the frames posed at p95 176-231 ms against 44-58 % at 266-309 ms with the thread, ICL posed
   RGB (the device's poses) 94-96 % posed either way at p95 49-53 ms against 55-70 (journal 68). Frames with depth
   keep a mapping thread: with the process their pose latency p95 rose (ICL 54-98 ms against 33-43, TUM 111-126
   against 62-90) for maps within 0.3 dB of the thread's.

6. A recording (every frame tracked: `skip_frames` false) gets every pass of the final refinement, as `flashmono
   run` does (no time bound: its passes bound it); a live stream's finish stays bounded by
   `mapping.final_refine_budget_s` (25 s, the drain included), so that the phone gets its map in time. Measured
   through the service (bench/results/lens, 2 cores): the fox's 44 photos with COLMAP poses, posed RGB, every 8th
   photo held out, render 18.35 dB held out with the 25 s bound and 22.48 dB with every pass (a 192 s finish under
   a load of 3).

This module is torch-free: the gateway imports it to say what its workers would choose (GET /v1/presets).
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from protocol.presets import AUTO

# Long side live frames are tracked at (pixels). Measured live on 2 cores, ICL at 30 frames/s (bench out_of_box).
LIVE_TRACKING_SIDE = 320
# Long side live frames are worked on (tracked and mapped) at when the map is built on a CPU.
LIVE_WORKING_SIDE = 320
# Cores from which a CPU session maps in a process of its own (worker.pipeline.mapping_process): with one core the
# two processes would only take turns.
MAPPING_PROCESS_CORES = 2
SHIPPED_CHECKPOINT = Path(__file__).parent / "frontend" / "weights" / "tiny.safetensors"


@dataclass(frozen=True)
class SessionInput:
    """What a session receives, as far as it is known (None: not known yet)."""

    depth: bool | None = None
    device_poses: bool | None = None
    width: int | None = None
    height: int | None = None
    frame_rate: float | None = None
    live: bool = False  # frames may be skipped when tracking falls behind (skip_frames)

    @property
    def mode(self) -> str:
        """The input mode's name: rgbd, posed-rgbd, posed-rgb, rgb, or unknown."""
        if self.depth is None or self.device_poses is None:
            return "unknown"
        return {(True, False): "rgbd", (True, True): "posed-rgbd", (False, True): "posed-rgb",
                (False, False): "rgb"}[(self.depth, self.device_poses)]


@dataclass(frozen=True)
class Machine:
    """The machine a session runs on."""

    cpu_cores: int
    cuda: bool = False
    checkpoint: str | None = None  # trained weights (not the shipped toy model), when present

    @property
    def trained_weights(self) -> bool:
        return self.checkpoint is not None

    @classmethod
    def detect(cls, checkpoint: str | None = None) -> Machine:
        """This machine: its usable cores, whether torch sees a CUDA GPU (imports torch: workers and `flashmono
        run` only; the gateway reads what workers publish), and the trained weights given by `checkpoint` or
        FLASHMONO_CHECKPOINT (a missing file, or the shipped toy model, counts as none)."""
        import torch

        cuda = bool(torch.cuda.is_available())
        path = checkpoint or os.environ.get("FLASHMONO_CHECKPOINT") or None
        trained = None
        if path and Path(path).is_file() and Path(path).resolve() != SHIPPED_CHECKPOINT.resolve():
            trained = str(path)
        return cls(cpu_cores=_usable_cores(), cuda=cuda, checkpoint=trained)

    def to_dict(self) -> dict[str, Any]:
        return {"cpu_cores": self.cpu_cores, "cuda": self.cuda, "trained_weights": self.trained_weights}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Machine:
        """A machine as a worker publishes it (`to_dict`); its weights' path stays on that worker."""
        return cls(cpu_cores=int(data.get("cpu_cores", 1)), cuda=bool(data.get("cuda", False)),
                   checkpoint="(on the worker)" if data.get("trained_weights") else None)


@dataclass
class SettingsChoice:
    """A preset, the overrides that go with it, and why."""

    preset: str
    overrides: dict[str, Any] = field(default_factory=dict)
    tracking_side: int | None = None
    working_side: int | None = None  # frames are tracked and mapped at this long side (None: as they come)
    reasons: list[str] = field(default_factory=list)
    decided: str = AUTO  # "auto" (this module) or "named" (the client named the preset)

    def to_record(self) -> dict[str, Any]:
        """The session record's `settings` field."""
        return asdict(self)

    def engine_overrides(self) -> dict[str, Any]:
        """The SlamConfig overrides, the tracking side included."""
        out = {key: dict(value) if isinstance(value, dict) else value for key, value in self.overrides.items()}
        if self.tracking_side:
            out.setdefault("tracking", {})["max_side"] = int(self.tracking_side)
        return out


def choose_settings(received: SessionInput, machine: Machine) -> SettingsChoice:
    """The engine settings for a session that names no preset (see the module docstring for the rule)."""
    if machine.cuda and machine.trained_weights:
        choice = SettingsChoice("paper", {"frontend": {"checkpoint": machine.checkpoint}}, reasons=[
            "a CUDA GPU and trained weights: the paper's settings (paper-size model, 512-pixel images)"])
    else:
        why = ("no CUDA GPU" if not machine.cuda else "a CUDA GPU but no trained weights (FLASHMONO_CHECKPOINT)")
        choice = SettingsChoice("rgbd", reasons=[
            f"{why}: the CPU mapping settings (surfels from "
            + ("the sensor's depth" if received.depth else "multi-view stereo on the tracked poses"
               if received.depth is False else "depth: the sensor's, else multi-view stereo")
            + ", final refinement at finish); the paper's settings need a GPU and trained weights"])
        if machine.cuda:
            choice.overrides["device"] = "cuda"
            choice.reasons.append("mapping on the GPU")
        elif machine.cpu_cores >= MAPPING_PROCESS_CORES and received.depth is False:
            what = "posed RGB" if received.device_poses else "RGB only"
            choice.overrides["mapping"] = {"process": True}
            choice.reasons.append(f"{what} on {machine.cpu_cores} CPU cores: mapping in a process of its own beside "
                                  "visual odometry (tracking keeps an interpreter to itself)")
    long_side = max(received.width or 0, received.height or 0)
    rate = f" at {received.frame_rate:g} frames/s" if received.frame_rate else ""
    if received.live and long_side > LIVE_WORKING_SIDE and not machine.cuda:
        choice.working_side = LIVE_WORKING_SIDE
        choice.reasons.append(f"a live stream{rate} of {received.width}x{received.height} frames mapped on a CPU: "
                              f"tracked and mapped at {LIVE_WORKING_SIDE} px on the long side, so that mapping keeps "
                              "up (the map renders at any size)")
    elif received.live and received.depth and long_side > LIVE_TRACKING_SIDE and choice.preset != "paper":
        choice.tracking_side = LIVE_TRACKING_SIDE
        choice.reasons.append(f"a live RGB-D stream{rate} of {received.width}x{received.height} frames: tracked at "
                              f"{LIVE_TRACKING_SIDE} px on the long side (dense alignment), mapped at full size")
    elif long_side:
        choice.reasons.append(f"{'live' if received.live else 'recorded'} {received.width}x{received.height} "
                              "frames: tracked at their size")
    if not received.live:
        choice.overrides.setdefault("mapping", {})["final_refine_budget_s"] = 0.0
        choice.reasons.append("recorded frames (skip_frames false): the final refinement makes every pass, as "
                              "`flashmono run` does (a live stream's finish is bounded)")
    choice.reasons.append(f"input: {received.mode}; machine: {machine.cpu_cores} cores"
                          + (", CUDA" if machine.cuda else "") + (", trained weights" if machine.trained_weights
                                                                    else ""))
    return choice


def named_settings(preset: str, tracking_side: int | None = None) -> SettingsChoice:
    """The record of a session whose client named its preset (nothing is decided for it)."""
    return SettingsChoice(preset, tracking_side=tracking_side, reasons=[f"preset {preset!r} named by the client"],
                          decided="named")


def choices_by_input(machine: Machine, live: bool = True, width: int = 640, height: int = 480
                     ) -> dict[str, dict[str, Any]]:
    """What `choose_settings` picks on `machine` for each input mode (GET /v1/presets)."""
    out = {}
    for depth, poses in ((True, False), (True, True), (False, True), (False, False)):
        received = SessionInput(depth=depth, device_poses=poses, width=width, height=height, live=live)
        out[received.mode] = choose_settings(received, machine).to_record()
    return out


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1
