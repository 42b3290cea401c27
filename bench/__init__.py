"""Benchmarks for cellcal's solvers against baselines (run from the repository root)."""
