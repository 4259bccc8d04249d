"""The loops every measurement runs, shared by releases, cells, robustness and rollouts: training
(train), image augmentation (augment), scoring on held-out windows (evaluate), and images to
pooled features (encode)."""
