"""Flash-Mono worker: the SLAM engine (frontend, loop closure, 2DGS map) and the process that serves it."""
