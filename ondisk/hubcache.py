"""The Hugging Face cache as graftbench reads it: the offline switch, cached files at a pinned
revision, the resolved commit, and the one `hf download` fix line every missing-artifact message
names (policies, datasets, timm weights). Below every adapter, encoder and suite loader.
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path


def hub_offline() -> bool:
    """HF_HUB_OFFLINE as set now (env) or as huggingface_hub read it at import."""
    from huggingface_hub import constants

    flag = os.environ.get("HF_HUB_OFFLINE", "").strip().upper() in {"1", "ON", "YES", "TRUE"}
    return flag or bool(constants.HF_HUB_OFFLINE)


def cached_file(repo_id: str, filename: str, revision: str | None = None) -> Path | None:
    """The cached path of `filename` in `repo_id` at `revision` (default main), or None."""
    from huggingface_hub import try_to_load_from_cache

    found = try_to_load_from_cache(repo_id, filename, revision=revision)
    return Path(found) if isinstance(found, str) else None


def resolved_revision(repo_id: str, revision: str | None = None, repo_type: str = "model") -> str | None:
    """The commit sha the cache holds for `repo_id` at `revision` (a sha stays itself)."""
    from huggingface_hub import constants

    if revision and len(revision) == 40 and all(c in "0123456789abcdef" for c in revision):
        return revision
    folder = Path(constants.HF_HUB_CACHE) / f"{repo_type}s--{repo_id.replace('/', '--')}"
    ref = folder / "refs" / (revision or "main")
    return ref.read_text().strip() if ref.is_file() else None


def snapshot_dir(hub_cache: Path, repo_id: str, revision: str | None,
                 repo_type: str = "model") -> Path:
    """hub_cache/<type>s--ORG--NAME/snapshots/<rev>/ with refs/main -> rev, created (the layout
    huggingface_hub reads; a `revision` of None: forty zeros). Writes the offline hub world."""
    sha = revision or "0" * 40
    folder = Path(hub_cache) / f"{repo_type}s--{repo_id.replace('/', '--')}"
    (folder / "refs").mkdir(parents=True, exist_ok=True)
    (folder / "refs" / "main").write_text(sha)
    snap = folder / "snapshots" / sha
    snap.mkdir(parents=True, exist_ok=True)
    return snap


def download_command(repo_id: str, revision: str | None = None, include: tuple[str, ...] = (),
                     repo_type: str = "model", files: tuple[str, ...] = ()) -> str:
    """The `hf download` line that puts `repo_id` (or just `files` of it) into the Hugging Face
    cache graftbench reads. One owner for every fix message (policies, datasets, timm weights).

    One `--include` per pattern: the hf CLI (huggingface_hub 1.x) takes one value per option and
    reads further words as file names, which then override every pattern
    (tests/test_startup.py parses every command the preflight prints with the CLI's own parser)."""
    if files and include:
        raise ValueError(f"hf download {repo_id}: give files {files} or include patterns "
                         f"{include}, not both (the CLI ignores --include beside file names)")
    parts = ["hf download"]
    if repo_type != "model":
        parts.append(f"--repo-type {repo_type}")
    parts += [repo_id, *files]
    if revision:
        parts.append(f"--revision {revision}")
    parts += [f'--include "{p}"' for p in include]
    return " ".join(parts)


def hub_artifact(kind: str, repo_id: str, files: tuple[str, ...], needed_by: str,
                 revision: str | None = None, include: tuple[str, ...] = (), note: str = ""):
    """An Artifact for `files` of `repo_id` at `revision` in the Hugging Face cache."""
    from huggingface_hub import constants

    from ondisk.artifacts import Artifact

    missing = [f for f in files if cached_file(repo_id, f, revision) is None]
    if missing:
        at = f"@{revision}" if revision else ""
        where = f"{constants.HF_HUB_CACHE} lacks {repo_id}{at}: {', '.join(missing)}"
        fix = download_command(repo_id, revision, include)
    else:
        where, fix = str(cached_file(repo_id, files[0], revision).parent), ""
    return Artifact(kind, repo_id, needed_by, not missing, where, fix, revision, note)


def folder_revision(folder: str | os.PathLike) -> str | None:
    """A saved policy folder's revision: "sha256:<16 hex>" of its model.safetensors (a folder has
    no commit; its weights name it), None without one. Hashed once per file version."""
    weights = Path(folder) / "model.safetensors"
    if not weights.is_file():
        return None
    return f"sha256:{_file_sha256(str(weights), weights.stat().st_mtime_ns)[:16]}"


def file_sha256(path: str | os.PathLike) -> str:
    """sha256 (hex) of a file, symlinks followed (a hub snapshot links into blobs/), hashed once
    per file version in a process."""
    resolved = Path(path).resolve()
    return _file_sha256(str(resolved), resolved.stat().st_mtime_ns)


@functools.lru_cache(maxsize=None)
def _file_sha256(path: str, mtime_ns: int) -> str:
    hasher = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 22), b""):
            hasher.update(block)
    return hasher.hexdigest()
