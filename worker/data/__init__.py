"""Frame sources (video, image folders, datasets) and the synthetic scene generator."""

from .frame import Frame, FrameResult
from .sources import DatasetError, FrameSource, SourceOptions, detect_format, open_source

__all__ = ["DatasetError", "Frame", "FrameResult", "FrameSource", "SourceOptions", "detect_format", "open_source"]
