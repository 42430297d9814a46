"""Frame sources (video, image folders, datasets) and the synthetic scene generator."""

from .frame import Frame, FrameResult

__all__ = ["Frame", "FrameResult"]
