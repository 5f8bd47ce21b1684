"""Orchestration: configuration, run folders, the stages of a run, re-mapping and progress reporting
(SPEC section 1: holds no algorithms)."""
