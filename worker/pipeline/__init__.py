"""The SLAM pipeline that `worker.slam.SlamSystem` assembles: a frame flows one way through its stages.

- `tracking_stage` (the caller's thread): pose source -> keyframe decision -> trajectory; hands keyframes on;
- `depth_sources`: where keyframe surfels come from (sensor, multi-view stereo, the model); jobs as data;
- `mapping_stage` (its own thread): keyframe jobs -> the 2DGS map, with load shedding;
- `loop_stage` (its own thread): pose graph, loop detection and verification -> corrections back to tracking;
- `assembly` wires them at a session's first frame; `finish`, `snapshot` and `session_stats` serve the session.
"""
