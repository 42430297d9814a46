"""The recurrent feed-forward frontend: model, configs, checkpoints, image handling and the submap tracker."""

from .types import HiddenState, StepOutput

__all__ = ["HiddenState", "StepOutput"]
