"""Settings of photo registration (`worker.tracking.photos`): incremental structure from motion for captures whose
consecutive images are far apart (photos around an object, a slow photo series), where optical flow cannot follow."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class PhotoRegistrationConfig(BaseModel):
    """Features, matching, registration and bundle adjustment of incremental photo registration."""

    model_config = ConfigDict(extra="forbid")

    min_interval_s: float = Field(0.4, ge=0.0, description="RGB-only sessions with `tracking.source` auto: when the "
                                                           "first three frames are each this far apart in time or "
                                                           "more, they are photos and are registered (else video, "
                                                           "for visual odometry); 0: never")
    max_features: int = Field(2000, ge=100, description="SIFT keypoints per photo at the most")
    match_ratio: float = Field(0.8, gt=0.0, lt=1.0, description="Lowe ratio of a descriptor match (both ways)")
    neighbours: int = Field(6, ge=1, description="the latest registered photos a new photo is matched against first")
    view_angle_deg: float = Field(45.0, gt=0.0, le=180.0,
                                  description="once posed, a photo is also matched against every registered photo "
                                              "whose viewing direction is within this angle (a revisit)")
    revisits: int = Field(8, ge=0, description="... the nearest this many of them")
    min_inliers: int = Field(30, ge=6, description="PnP inliers a photo needs to be registered")
    chi2_px: float = Field(5.991, gt=0.0, description="squared reprojection error (in pixel sigmas) of an inlier")
    min_parallax_deg: float = Field(1.5, gt=0.0, description="triangulation angle a new point needs, degrees")
    waiting_photos: int = Field(12, ge=2, description="photos kept while no pair has made the first map (the newest "
                                                      "this many; each new photo is tried against them, oldest "
                                                      "first)")
    retry_photos: int = Field(30, ge=0, description="photos that could not be registered, kept to be tried again "
                                                    "after each photo that is (the newest this many)")
    local_window: int = Field(8, ge=2, description="photos adjusted with a new one (those sharing most points)")
    global_every: float = Field(0.25, gt=0.0, description="all photos adjusted together when their number grew by "
                                                          "this share since the last time")
    ba_iterations: int = Field(15, ge=1, description="Levenberg-Marquardt iterations of one bundle adjustment")
