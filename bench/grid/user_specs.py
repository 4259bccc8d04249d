"""Your own policy and data as values of the grid: `--policy NAME=REPO_ID_OR_PATH[@REVISION]`,
`--dataset NAME=REPO_ID_OR_PATH`, `--camera-map POLICY_CAMERA=DATASET_CAMERA,...` (and the grid
file's [policies], [datasets], [camera_map] tables). Parsing and names only; what they are is
checked at start-up, before collection (bench.resources.user_policies).

With --policy (--dataset) and no --backbones (--suites), the grid's backbones (suites) are the
named policies (datasets). A camera name may be given short: `front` is
`observation.images.front`.
"""

from __future__ import annotations

import dataclasses
import re

from bench.grid.protocol import Profile

NAME_RE = re.compile(r"^[a-z0-9_]+$")
CAMERA_PREFIX = "observation.images."


def camera_key(name: str) -> str:
    """`front` -> `observation.images.front`; a full key is kept."""
    return name if name.startswith("observation.") else CAMERA_PREFIX + name


def parse_named(option: str, values) -> tuple[tuple[str, str], ...]:
    """["mine=/path", ...] -> (("mine", "/path"), ...), each name checked once."""
    out: dict[str, str] = {}
    for value in values or ():
        name, sep, target = str(value).partition("=")
        name, target = name.strip(), target.strip()
        if not sep or not name or not target:
            raise ValueError(f"{option} {value!r}: give NAME=REPO_ID_OR_PATH, e.g. "
                             f"{option} mine=/path/to/checkpoint")
        check_name(option, name)
        if name in out:
            raise ValueError(f"{option}: {name!r} is given twice; give each name once")
        out[name] = target
    return tuple(out.items())


def check_name(option: str, name: str) -> None:
    if not NAME_RE.match(name):
        raise ValueError(f"{option} {name}: a name is lower-case letters, digits and _ (it is "
                         "part of every cell id, where '-' separates fields)")


def parse_camera_map(option: str, text: str | None) -> tuple[tuple[str, str], ...]:
    """"front=top,wrist=hand" -> ((observation.images.front, observation.images.top), ...)."""
    pairs = []
    for item in (text or "").split(","):
        if not item.strip():
            continue
        policy_cam, sep, dataset_cam = item.partition("=")
        if not sep or not policy_cam.strip() or not dataset_cam.strip():
            raise ValueError(f"{option} {text!r}: give POLICY_CAMERA=DATASET_CAMERA pairs, e.g. "
                             f"{option} front=top,wrist=hand")
        pairs.append((camera_key(policy_cam.strip()), camera_key(dataset_cam.strip())))
    policy_cams = [p for p, _ in pairs]
    if len(set(policy_cams)) != len(policy_cams):
        raise ValueError(f"{option} {text!r}: a policy camera is mapped twice; map each once")
    return tuple(pairs)


def with_user_world(profile: Profile, policies=None, datasets=None, camera_map=None) -> Profile:
    """`profile` with the given user policies/datasets/camera map (None: keep the profile's);
    the grid's backbones (suites) become the policies (datasets) when these are given."""
    changes = {}
    if policies is not None:
        changes.update(policies=policies, backbones=tuple(n for n, _ in policies))
    if datasets is not None:
        changes.update(datasets=datasets, suites=tuple(n for n, _ in datasets))
    if camera_map is not None:
        changes["camera_map"] = camera_map
    return dataclasses.replace(profile, **changes)


def split_revision(target: str) -> tuple[str, str | None]:
    """"owner/name@abc123" -> ("owner/name", "abc123"); a path or bare id -> (target, None)."""
    head, sep, rev = target.rpartition("@")
    if sep and head and "/" not in rev:
        return head, rev
    return target, None
