"""SLAM back end: odometry, keyframes, loop closures, GTSAM pose graph, marginals, trajectory formats and
metrics (SPEC section 1: knows nothing of maps).

The entry point is :func:`slam.system.run_slam` (scans + wheel odometry -> :class:`slam.system.SlamResult`),
configured by :class:`slam.config.SlamConfig`. Modules: ``geometry`` (SE(2)), ``scan_matching`` (grid
matcher), ``odometry``, ``keyframes``, ``loop_closure``, ``graph`` (GTSAM), ``system``, ``metrics``,
``trajectory_io`` (TUM, g2o, covariances), ``figures``.
"""
