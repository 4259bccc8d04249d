"""What graftbench reads and writes on disk outside its results, below every other package: the
Hugging Face cache (hubcache), graftbench's own cache folder and paths (paths), the artifacts a run
needs from outside with their fetch commands (artifacts), LeRobot's LIBERO dataset format
(libero_format), the one LeRobotDataset writer (lerobot_dataset) and a kernel-released file lock
(filelock). Imports nothing of graftbench's (it was `external/`: not vendored code, so renamed).
The graft wrapper and reading a checkpoint's config are the LeRobot plugin distribution's
(graftcore.graft, lerobot_policy_graft.configuration_graft), which an export needs without
graftbench.
"""
