"""The outside world as graftbench reads it, below every other package: the Hugging Face cache
(hubcache), graftbench's own cache folder (paths), the artifacts a run needs from outside
(artifacts) and LeRobot's LIBERO dataset format (libero_format). Imports nothing of graftbench's.
"""
