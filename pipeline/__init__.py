"""Orchestration: configuration, run folders, the stages of a run, re-mapping and progress reporting
(SPEC section 1: holds no algorithms).

Importing the package first sets the vector width numba compiles for (:mod:`pipeline.simd`), before any
compiled module imports numba."""

from pipeline.simd import prefer_wide_vectors

prefer_wide_vectors()
