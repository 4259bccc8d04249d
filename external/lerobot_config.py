"""LeRobot's PreTrainedConfig.from_pretrained, for the adapters and the graft plugin alike."""

from __future__ import annotations

import tempfile


def config_from_pretrained(source: str, revision: str | None = None):
    """PreTrainedConfig.from_pretrained(source, revision=revision), less the file it leaves
    behind: LeRobot 0.6.1 dumps the config into a NamedTemporaryFile(delete=False) for draccus
    and never removes it (a test run left ~140 in /tmp). Its temp files go to a private folder,
    removed on return."""
    from lerobot.configs import PreTrainedConfig

    with tempfile.TemporaryDirectory(prefix="graftbench-config-") as private:
        before, tempfile.tempdir = tempfile.tempdir, private
        try:
            return PreTrainedConfig.from_pretrained(source, revision=revision)
        finally:
            tempfile.tempdir = before
