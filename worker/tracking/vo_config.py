"""Settings of monocular visual odometry (`worker.tracking.visual_odometry.VisualOdometry`).

Frames are tracked by optical flow (pixel noise of one pixel); ORB features serve relocalisation, where thresholds
in pixels are for the finest pyramid level and grow with each keypoint's octave. Nothing here is tuned to one
sequence: the defaults are the usual values of monocular SLAM front ends for images of 320 to 640 pixels, and the
bench (`python -m bench visual_odometry`) shows their neighbourhood on real and synthetic sequences.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class VisualOdometryConfig(BaseModel):
    """Features, initialisation, tracking, keyframes, bundle adjustment and relocalisation of monocular VO."""

    model_config = ConfigDict(extra="forbid")

    # ORB features (keyframes and relocalisation)
    n_features: int = Field(1000, ge=50, description="ORB keypoints per image (spread over a grid)")
    n_levels: int = Field(6, ge=1, le=12, description="pyramid levels")
    scale_factor: float = Field(1.2, gt=1.0, le=2.0, description="pyramid scale step")
    fast_threshold: int = Field(7, ge=1, description="FAST corner threshold")
    clahe_clip: float = Field(3.0, ge=0.0, description="contrast equalisation (CLAHE) clip limit; 0: off")
    grid_cell: int = Field(32, ge=8, description="side of the grid cells that spread keypoints, pixels")
    min_features: int = Field(60, ge=10, description="fewer keypoints than this: a lost frame is not searched")

    # two-view initialisation
    init_min_matches: int = Field(80, ge=20, description="matches (tracks) needed to try initialising")
    init_min_points: int = Field(60, ge=20, description="triangulated points needed to accept an initialisation")
    init_min_parallax_deg: float = Field(2.0, gt=0.0, description="median triangulation angle needed, degrees")
    init_max_frames: int = Field(30, ge=2, description="frames kept while waiting; older references are replaced")
    match_ratio: float = Field(0.8, gt=0.0, lt=1.0, description="Lowe ratio for descriptor matching")
    max_hamming: int = Field(64, ge=1, le=256, description="largest descriptor distance of an accepted match")

    # optical-flow tracks
    max_tracks: int = Field(500, ge=50, description="points followed by optical flow at the most")
    corner_min_distance: float = Field(0.025, gt=0.0, lt=0.5, description="smallest distance between two tracks, "
                                                                          "as a share of max(W, H)")
    corner_quality: float = Field(0.001, gt=0.0, lt=1.0, description="Shi-Tomasi quality of a new corner (share of "
                                                                      "the best corner's)")
    flow_window: int = Field(21, ge=5, description="Lucas-Kanade window side, pixels")
    flow_levels: int = Field(3, ge=0, le=6, description="Lucas-Kanade pyramid levels above the image")
    flow_refine_px: float = Field(1.0, ge=0.0, description="a track is re-matched against the last keyframe's image "
                                                            "when that moves it at most this far (0: off), px")
    flow_refine_zoom: float = Field(0.05, ge=0.0, description="... and when its image scale differs from the "
                                                              "keyframe's by at most this share")
    flow_fb_px: float = Field(0.75, gt=0.0, description="largest forward-backward flow error of a kept track, px")

    # tracking
    min_tracked: int = Field(25, ge=6, description="pose inliers below this: tracking is lost")
    min_survival: float = Field(0.25, ge=0.0, lt=1.0, description="share of the last frame's tracked points that "
                                                                   "must be found again (less: a sudden change)")
    chi2_px: float = Field(5.991, gt=0.0, description="squared reprojection error (in sigmas) of an inlier")

    # keyframes and the local map
    keyframe_tracked_ratio: float = Field(0.8, gt=0.0, lt=1.0,
                                          description="new keyframe when tracked points fall below this share "
                                                      "of the last keyframe's")
    keyframe_max_gap: int = Field(20, ge=1, description="frames between keyframes at the most (while moving)")
    keyframe_min_gap: int = Field(1, ge=1, description="frames between keyframes at the least")
    keyframe_baseline: float = Field(0.06, gt=0.0, description="new keyframe when the baseline to the last one "
                                                                "exceeds this share of the median depth")
    min_parallax_deg: float = Field(1.0, gt=0.0, description="smallest triangulation angle of a new point")
    window: int = Field(8, ge=2, description="keyframes the windowed bundle adjustment moves")
    fixed_keyframes: int = Field(2, ge=1, description="older keyframes kept fixed in the adjustment (they anchor "
                                                      "pose and scale) and in the local map")
    ba_iterations: int = Field(10, ge=1, description="Levenberg-Marquardt iterations of the windowed adjustment")
    covisibility_ba: bool = Field(True, description="the adjustment moves the `window` keyframes sharing the most "
                                                    "points with the newest one and holds the keyframes that also "
                                                    "observe their points (ORB-SLAM's local mapping); off: the last "
                                                    "`window` keyframes move, the `fixed_keyframes` before them hold")
    map_keyframes: int = Field(16, ge=3, description="keyframes the local map keeps for the covisibility window")
    reobserve_points: bool = Field(False, description="a new keyframe's ORB features are matched to the local map's "
                                                      "points no track follows (search by projection): a place seen "
                                                      "again joins the covisibility window")
    reobserve_radius_px: float = Field(4.0, gt=0.0, description="... within this many pixels of the projection")
    reobserve_max_hamming: int = Field(50, ge=1, le=256, description="... at this descriptor distance at most")
    reobserve_snap_px: float = Field(2.0, ge=0.0, description="... a candidate track this close to the keypoint "
                                                              "takes the point (else a new track starts there)")
    # 4 held keyframes gave 0.53 % of the path on the synthetic street (ICL 1.68 cm), 2 gave 0.15 % (ICL 1.73 cm).
    covisible_fixed: int = Field(2, ge=1, description="keyframes held still around the covisible ones, at the most")
    huber_sigmas: float = Field(2.45, gt=0.0, description="Huber kernel width, in pixel sigmas")

    # turns faster than points can be triangulated
    rotation_bridge: bool = Field(True, description="a frame whose tracks measure too few map points is tracked by "
                                                    "the rotation its tracks agree on (position from the map points "
                                                    "left, else held) while that rotation explains them; a "
                                                    "`rotation_only` event says so, quality at most 0.5")
    rotation_min_tracks: int = Field(40, ge=10, description="... tracks that must agree on the rotation")
    rotation_min_share: float = Field(0.7, gt=0.0, le=1.0, description="... share of the followed tracks they "
                                                                        "must be (else: parallax, not a rotation)")
    rotation_tolerance_px: float = Field(1.5, gt=0.0, description="... largest disagreement of a track, pixels")
    rotation_position_points: int = Field(8, ge=3, description="... map points needed to measure the position")
    rotation_max_step: float = Field(0.2, gt=0.0, description="... a measured move above this share of the scene "
                                                             "depth is not believed (the position is held)")
    rotation_keyframe_share: float = Field(0.6, gt=0.0, le=1.0, description="... a VO keyframe (no engine "
                                                                             "keyframe) when fewer tracks than this "
                                                                             "share of the last keyframe's are left")

    # turns over walls too plain or too striped for point tracks (worker/tracking/direct_rotation.py)
    direct_fallback: bool = Field(True, description="a frame neither the tracks nor their rotation can place is "
                                                    "aligned to the last tracked frame by whole-image intensities: "
                                                    "the turn measured, the position from the constant-velocity "
                                                    "motion; a `rotation_only` event with method `photometric` "
                                                    "says so, quality at most 0.4")
    direct_max_frames: int = Field(60, ge=1, description="... frames one such run may last (the position is a guess)")
    direct_prior_deg: float = Field(2.0, gt=0.0, description="... standard deviation of the predicted turn per axis "
                                                             "(the axes the image does not measure stay there)")
    direct_min_correlation: float = Field(0.75, gt=0.0, le=1.0, description="... zero-normalised correlation of "
                                                                             "the aligned images, at least")
    direct_max_axis_sigma_deg: float = Field(0.25, gt=0.0, description="... the image must measure the turn about "
                                                                       "one camera axis at least this well")
    # object orbits from photos step 0.09-0.23 of the scene depth a frame (the fox), the synthetic rooms' walk
    # 0.044-0.055
    direct_max_baseline: float = Field(0.075, gt=0.0, description="... only while the predicted move per frame is "
                                                                   "at most this share of the scene depth (a turn: "
                                                                   "the plane the fit assumes hides little parallax)")
    direct_max_correction_deg: float = Field(6.0, gt=0.0, description="... a fit further than this from the "
                                                                      "predicted turn is refused (outside the basin "
                                                                      "of a local alignment)")
    direct_translation_sigma: float = Field(0.01, ge=0.0, description="... when the fit with the predicted move "
                                                                      "fails, it is tried again with the move free "
                                                                      "within this share of the scene depth (the "
                                                                      "turn kept, quality at most 0.2; 0: not)")
    direct_track_tolerance_px: float = Field(4.0, gt=0.0, description="... a track followed into the frame is kept "
                                                                      "within this distance of where the alignment "
                                                                      "puts it")

    # relocalisation
    recover_share: float = Field(0.6, gt=0.0, le=1.0, description="share of the last tracked frame's map points "
                                                                  "that a lost frame must show to take up its tracks")
    reloc_keyframes: int = Field(60, ge=1, description="keyframes remembered for place recognition")
    reloc_candidates: int = Field(5, ge=1, description="places verified geometrically per lost frame")
    place_radius_px: float = Field(1.5, gt=0.0, description="an ORB keypoint of a keyframe stands for the map point "
                                                             "observed this close to it, pixels")
    reloc_min_inliers: int = Field(30, ge=10, description="PnP inliers needed to relocalise")
    reinit_after_loss: bool = Field(True, description="while lost, also restart the map from a two-view "
                                                      "reconstruction anchored at the last tracked frame")
    reinit_min_parallax_deg: float = Field(1.0, gt=0.0, description="median triangulation angle a restarted map "
                                                                     "needs, degrees (ORB-SLAM's; its pose and "
                                                                     "scale come from the anchor)")
    reinit_min_matches: int = Field(50, ge=20, description="tracks shared with the anchor needed to restart")
    new_map_after_lost: int = Field(2, ge=0, description="lost frames (nothing above found the old map) after which "
                                                         "a new map starts from a two-view initialisation, placed at "
                                                         "the last pose with the old map's scene depth until a loop "
                                                         "joins the two (ORB-SLAM3's new map in its atlas; 0: never)")
    join_maps: bool = Field(True, description="a map restarted after a loss is joined to the older map, scale "
                                              "included, when one of its keyframes recognises an older keyframe "
                                              "(a Sim(3) edge: `maps_merged`)")
    join_max_keyframes: int = Field(40, ge=1, description="... tried at this many keyframes of the new map at most")
    join_min_pairs: int = Field(10, ge=3, description="... measured by at least this many of the place's points that "
                                                      "lie on the new map's points too (their depth ratio)")
    join_max_spread: float = Field(0.15, gt=0.0, description="... when the depth ratios of the shared points agree "
                                                             "(median absolute deviation of their log)")
    learned_relocalisation: bool = Field(True, description="while lost, match XFeat features of the last tracked "
                                                           "frame's map points (optical flow and ORB failed)")
    learned_reloc_frames: int = Field(30, ge=1, description="... for this many frames after it")
    learned_reloc_every: int = Field(3, ge=1, description="... on every n-th lost frame (the first one included)")
    learned_keypoints: int = Field(1024, ge=64, description="XFeat keypoints per lost frame")
    # The network runs on the tracking thread: a frame's XFeat work is bounded so that a loss never stalls the
    # stream (before: up to 9 passes in the first lost frame, 1-6 s on 2 busy cores; see bench/RESULTS.md).
    learned_passes_per_frame: int = Field(3, ge=2, description="XFeat network passes one frame may run at most "
                                                               "(its own, the last tracked frame's, remembered "
                                                               "keyframes not described yet: those left over are "
                                                               "described on later lost frames and then cached)")
    learned_threads: int = Field(1, ge=1, le=64, description="torch threads of an XFeat pass (one: two threads "
                                                             "on 2 busy cores wait for each other, 3-30x slower)")
    learned_min_similarity: float = Field(0.82, gt=0.0, lt=1.0, description="cosine similarity of an XFeat match "
                                                                             "(XFeat's default)")
    learned_candidates: int = Field(3, ge=1, description="remembered keyframes matched by XFeat per try: this many "
                                                        "nearest the last pose, and this many most alike in ORB words")
    # Several candidates make a chance pose more likely than against one frame: a fast turn then walk (synthetic,
    # tests/tracking/test_rotation_only.py) gave one with 36 inliers 11 cm off; the ICL jump back finds 156.
    learned_keyframe_min_inliers: int = Field(50, ge=10, description="... PnP inliers a remembered keyframe needs")
    learned_places: int = Field(24, ge=0, description="remembered keyframes that keep their image for XFeat (the "
                                                      "newest; the map's own keyframes always do)")
    # Off by default: a try takes seconds outside the per-frame pass budget, which live streams need; offline runs
    # (`flashmono run` without --live-pacing) turn it on, recorded frames can wait.
    learned_glue: bool = Field(False, description="where no remembered keyframe verifies by XFeat's mutual nearest "
                                                  "neighbours, match them by LighterGlue (keypoints detected at twice "
                                                  "the image size): wide baselines of 30 degrees and more; a pair "
                                                  "costs 2-3 s of a loaded 2-core CPU at 270x480 (an XFeat pass on "
                                                  "the enlarged image and the matcher), a place's keypoints are "
                                                  "cached")
    learned_glue_every: int = Field(10, ge=1, description="... at most on one lost frame in this many (a try that "
                                                          "finds nothing costs up to `learned_glue_candidates` pairs)")
    learned_glue_keypoints: int = Field(2048, ge=64, description="... XFeat keypoints per image for LighterGlue")
    learned_glue_min_confidence: float = Field(0.1, gt=0.0, lt=1.0, description="... a match's LighterGlue score")
    # On the fox the place that verifies was the third of six (the nearest to a pose held over a 44-degree jump
    # do not overlap), and mutual-NN match counts at chance level do not rank them: all are tried, in order.
    learned_glue_candidates: int = Field(6, ge=1, description="... against at most this many of the remembered "
                                                              "keyframes XFeat tried, in their order, up to the "
                                                              "first that verifies")
    learned_glue_point_inliers: int = Field(12, ge=6, description="... PnP inliers on the keyframe's map points, "
                                                                  "when all the pair's matches hold an essential "
                                                                  "matrix with `learned_keyframe_min_inliers` "
                                                                  "inliers and agree with the PnP pose")
    learned_join: bool = Field(True, description="a keyframe of a restarted map that ORB finds no older place for is "
                                                 "matched to older places by XFeat (wide baselines)")
    learned_join_reach: float = Field(0.8, gt=0.0, description="... against the places whose viewing direction "
                                                               "(radians) plus distance (median scene depths) from "
                                                               "the keyframe is at most this (a network pass each "
                                                               "keyframe that has one: 150-200 ms of CPU)")

    # the final bundle adjustment (worker/tracking/global_adjustment.py)
    final_adjustment: bool = Field(True, description="at the session's end, every keyframe and point is adjusted "
                                                     "together, the points a revisit sees again joined to the "
                                                     "first visit's (ORB-SLAM's loop fusion and global bundle "
                                                     "adjustment); the trajectory and the map follow")
    # TUM fr1/xyz (788 frames, 125 keyframes): 7.8 s on 2 cores; played twice (254 keyframes) 31 s
    final_adjustment_keyframes: int = Field(300, ge=0, description="... keyframes kept for it, the newest (the "
                                                                  "oldest two of them hold still; 0: off)")
    fuse_min_gap: int = Field(3, ge=1, description="... a keyframe looks for the points of keyframes at least this "
                                                   "many keyframes older (the younger share its tracks already)")
    fuse_max_distance: float = Field(0.3, gt=0.0, description="... within this share of the map's scene depth")
    fuse_max_angle_deg: float = Field(25.0, gt=0.0, description="... and this many degrees of viewing direction")
    fuse_candidates: int = Field(40, ge=1, description="... this many of them at most, the nearest")
    fuse_min_inliers: int = Field(20, ge=6, description="... a pair's ORB matches must place the keyframe on the "
                                                        "older one's points (PnP) with this many inliers")
    fuse_search_share: float = Field(0.1, gt=0.0, description="... where its own pose puts them within this share "
                                                               "of the image's larger side")
    fuse_pnp_px: float = Field(2.0, gt=0.0, description="... within this many pixels")
    # Without revisits it measured slightly worse than the windowed adjustments' poses (ICL 1.21 -> 1.28 cm,
    # KITTI 00's first 200 frames 1.30 -> 1.36 m): it runs only where revisits tie the map together.
    fuse_min_pairs: int = Field(5, ge=1, description="... pairs needed to run the adjustment at all")
    final_adjustment_rounds: int = Field(3, ge=1, description="... rounds, observations far off dropped after each")
    final_adjustment_iterations: int = Field(40, ge=1, description="... Levenberg-Marquardt iterations a round")

    # unknown intrinsics
    focal_guess: float = Field(0.9, gt=0.1, lt=5.0, description="focal guess as a share of max(W, H)")
    self_calibrate: bool = Field(True, description="estimate the focal length from the first frames' geometry")

    # coming back: no new engine keyframe where an old one already sees the view
    reuse_keyframes: int = Field(256, ge=0, description="engine keyframe poses remembered to come back to (0: off)")
    reuse_min_age: int = Field(30, ge=1, description="a keyframe is a place to come back to once this many frames "
                                                     "old (younger ones are the camera's current stretch)")
    # Tighter than RGB-D odometry's (whose switch is verified by alignment): on ICL, 15 % and 15 degrees vetoed 4
    # keyframes of the single forward pass (a nearby pass, not a return) and cost 1 dB of PSNR.
    reuse_distance: float = Field(0.05, gt=0.0, description="an old keyframe is near within this share of the "
                                                             "median depth ...")
    reuse_rotation_deg: float = Field(10.0, gt=0.0, description="... and this many degrees")
    reuse_overlap: float = Field(0.8, gt=0.0, le=1.0, description="... and when it sees this share of the frame's "
                                                                  "tracked map points: the frame needs no keyframe")
