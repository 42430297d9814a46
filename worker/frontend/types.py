"""The frontend's value types: the recurrent hidden state and one step's output (DESIGN.md contracts)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from protocol.codec import pack, unpack


@dataclass
class HiddenState:
    """Everything that recurs between frames: the state tokens [B, S, D] and the pose memory [B, M, 2D].

    A value object: `clone()` copies it, `to_bytes()`/`from_bytes()` store it (fp16 or fp32), and feeding a past
    state back to `FeedForwardModel.step(..., update=False)` is the loop-frame relocalization of paper 4.2.
    """

    state_tokens: torch.Tensor
    pose_memory: torch.Tensor
    frames_seen: int = 0

    def clone(self) -> HiddenState:
        return HiddenState(self.state_tokens.clone(), self.pose_memory.clone(), self.frames_seen)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> HiddenState:
        return HiddenState(self.state_tokens.to(device=device, dtype=dtype),
                           self.pose_memory.to(device=device, dtype=dtype), self.frames_seen)

    def nbytes(self) -> int:
        return self.state_tokens.nbytes + self.pose_memory.nbytes

    def to_bytes(self, dtype: torch.dtype = torch.float16) -> bytes:
        """msgpack bytes with both tensors cast to `dtype` (float16 or float32)."""
        if dtype not in (torch.float16, torch.float32):
            raise ValueError("hidden states are stored as float16 or float32")
        return pack({
            "state_tokens": self.state_tokens.detach().to("cpu", dtype).numpy(),
            "pose_memory": self.pose_memory.detach().to("cpu", dtype).numpy(),
            "frames_seen": self.frames_seen,
        })

    @classmethod
    def from_bytes(cls, data: bytes, dtype: torch.dtype = torch.float32, device: str = "cpu") -> HiddenState:
        d = unpack(data)
        return cls(
            torch.from_numpy(np.asarray(d["state_tokens"])).to(device=device, dtype=dtype),
            torch.from_numpy(np.asarray(d["pose_memory"])).to(device=device, dtype=dtype),
            int(d["frames_seen"]),
        )


@dataclass
class StepOutput:
    """One forward step f(I_t, M_{t-1}) for a batch of B frames at the model's resolution H x W.

    pose_c2w [B,4,4]: camera-to-world in the frame of the submap's first frame (SE(3)).
    points_cam [B,H,W,3] and conf [B,H,W] (>= 1): per-pixel surfel means in the camera frame and their confidence.
    points_world [B,H,W,3], conf_world [B,H,W]: the world-frame (submap-frame) head CUT3R has.
    opacity [B,H,W] in (0,1), quats [B,H,W,4] wxyz (camera frame), scales [B,H,W,2] > 0, colors [B,H,W,3] in [0,1]:
    the 2DGS attributes. state: M_t (equal to the input state when update=False).
    """

    pose_c2w: torch.Tensor
    points_cam: torch.Tensor
    conf: torch.Tensor
    points_world: torch.Tensor
    conf_world: torch.Tensor
    opacity: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    colors: torch.Tensor
    state: HiddenState
