"""The outside world as graftbench reads it, below every other package: the Hugging Face cache
(hubcache), graftbench's own cache folder (paths), the artifacts a run needs from outside
(artifacts), LeRobot's LIBERO dataset format (libero_format) and dataset loading
(lerobot_dataset) and a kernel-released file lock (filelock). Imports nothing of graftbench's.
The graft wrapper and reading a checkpoint's config are the LeRobot plugin distribution's
(graftcore.graft, lerobot_policy_graft.configuration_graft), which an export needs without
graftbench.
"""
