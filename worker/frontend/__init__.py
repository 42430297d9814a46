"""The recurrent feed-forward frontend: model, configs, checkpoints, image handling and the submap tracker."""

from .configs import CONFIGS, FrontendConfig, get_config, parameter_tally
from .model import FeedForwardModel, build_model
from .types import HiddenState, StepOutput

__all__ = [
    "CONFIGS", "FeedForwardModel", "FrontendConfig", "HiddenState", "StepOutput", "build_model", "get_config",
    "parameter_tally",
]
