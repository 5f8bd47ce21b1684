"""SLAM back end: odometry, keyframes, loop closures, GTSAM pose graph, marginals, trajectory formats and
metrics (SPEC section 1: knows nothing of maps)."""
