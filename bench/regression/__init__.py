"""Baselines: save a run's records, compare a run with them, fail on regressions."""
