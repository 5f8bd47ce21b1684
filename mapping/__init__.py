"""Gaussian-process occupancy mapping (O'Callaghan & Ramos, IJRR 2012), the occupancy-grid baseline and map
metrics (SPEC section 1: knows nothing of bags or GTSAM)."""
