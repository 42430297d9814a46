"""Pose sources: where a frame's camera pose comes from (device, RGB-D odometry, visual odometry, the model).

`worker.tracking.base` defines what every source returns; `worker.tracking.sources.build_pose_source` picks one for a
session from its config and first frame.
"""
