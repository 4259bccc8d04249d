"""One loaded tiny world per test session: workspaces that lend each other what they loaded.

A workspace loads suites, splits, released policies and encoders on first use (seconds each;
a release not yet in the cache is trained first: minutes). Tests that need a workspace of their
own (another step count, a private results store) get one that lends the loaded parts of the
first workspace of the same world, so each is loaded once per process (once per xdist worker;
the disk caches below them are shared and locked across processes).

Lent parts are read-only by contract (bench.resources.workspace: the LoRA control copies its
backbone); each workspace keeps its own profile, store and progress.
"""

from __future__ import annotations

import dataclasses

from bench.progress import QUIET
from bench.resources.workspace import Workspace
from ondisk.paths import cache_dir

_WORLDS: dict[tuple, Workspace] = {}  # world key -> the workspace whose loaded parts are lent


def world_key(profile) -> tuple:
    """What a workspace's loaded parts depend on: all of the profile but the projector steps
    and the grid selection, and the cache folder."""
    return (profile.protocol.replace(steps=0), profile.source, profile.data_source,
            profile.datasets, profile.policies, profile.camera_map, str(cache_dir()))


def lent_workspace(profile, store, **fields) -> Workspace:
    """A workspace for `profile` writing to `store` (`fields`: progress, rollouts,
    feature_dtype), lending the loaded parts of its world's first workspace."""
    key = world_key(profile)
    if key not in _WORLDS:
        _WORLDS[key] = Workspace(profile, store, progress=QUIET)
    own = {"progress": False, **fields}
    return dataclasses.replace(_WORLDS[key], profile=profile, store=store, **own)
