"""Photo registration: incremental structure from motion for RGB-only captures whose images are far apart (a photo
orbit around an object, a slow photo series), where the optical flow of visual odometry cannot follow.

`PhotoRegistration` is the pose source; `IncrementalRegistration` the registration itself (features, matches, PnP,
triangulation, bundle adjustment), usable on its own; `PhotoRegistrationConfig` its settings."""

from .config import PhotoRegistrationConfig
from .features import PhotoFeatures, extract_features
from .incremental import IncrementalRegistration, Registration
from .source import PhotoRegistration

__all__ = ["IncrementalRegistration", "PhotoFeatures", "PhotoRegistration", "PhotoRegistrationConfig", "Registration",
           "extract_features"]
