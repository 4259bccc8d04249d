"""The outside world as graftbench reads it, below every other package: the Hugging Face cache
(hubcache), graftbench's own cache folder (paths), the artifacts a run needs from outside
(artifacts), LeRobot's LIBERO dataset format (libero_format) and dataset loading
(lerobot_dataset), a policy config read from a checkpoint (lerobot_config), the fixed graft
wrapper (graft) and a kernel-released file lock (filelock). Imports nothing of graftbench's.
"""
