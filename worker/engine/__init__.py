"""Parts of the SLAM engine that `worker.slam.SlamSystem` assembles: trajectory bookkeeping, keyframe selection,
surfel initialisation and the backend mapping thread."""
