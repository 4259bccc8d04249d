"""Measuring a cell: the workspace, released checkpoints, the feature store, the inputs, training, scoring."""
