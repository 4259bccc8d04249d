"""LIBERO-format suites: a registry of names and `load_suite(name, source)`.

source "tiny": a small suite generated offline (bench.suites.synthetic), cached on disk.
source "hub": the real LIBERO dataset from a local root or the Hugging Face cache
(bench.suites.libero). source "sim": scripted demonstrations in real LIBERO scenes, generated
once with the `libero` extra (bench.sim.demos) and cached. Either way the data is read back
through `LeRobotDataset`.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bench.progress import ProgressSink
from bench.suites import libero, synthetic
from bench.table import Table
from ondisk.libero_format import ACTION_KEY, IMAGE_KEYS, STATE_KEY
from bench.suites.base import Suite, SuiteUnavailable

SOURCES = ("tiny", "hub", "sim")
FINGERPRINT_IMAGE_SAMPLES = 32  # hub suites: frames whose image bytes enter the fingerprint


@dataclass(frozen=True)
class SuiteSpec:
    name: str
    hub_repo_id: str
    has_tiny: bool  # a synthetic stand-in exists


SUITES: Table[SuiteSpec] = Table("suite", "suites")
for _name, _repo_id in libero.LIBERO_REPO_IDS.items():
    SUITES.register(SuiteSpec(_name, _repo_id, _name in synthetic.SUITE_PARAMS))


def load_suite(name: str, source: str, root: str | Path | None = None,
               sim_spec=None, *, progress: ProgressSink) -> Suite:
    """Load suite `name` from `source` ("tiny" | "hub" | "sim"); `root`: optional local folder;
    `sim_spec`: the sim source's bench.sim.demos.DemoSpec (default: its DEFAULT_SPECS entry);
    `progress`: where generating a sim suite on first use (minutes) reports (bench.progress)."""
    SUITES.get_entry(name)  # an unknown name: ValueError, one line
    if source == "tiny":
        if not SUITES[name].has_tiny:
            tiny = sorted(n for n, s in SUITES.items() if s.has_tiny)
            raise ValueError(f"suite {name!r} has no tiny (synthetic) version; use one of {tiny} "
                             "or source='hub'")
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        path = synthetic.tiny_suite_path(name, progress=progress)
        ds = LeRobotDataset(synthetic.repo_id(name), root=path)
        libero.validate_features(ds.features, synthetic.repo_id(name))
        return suite_from_dataset(name, ds, images_in_memory=True)
    if source == "hub":
        return suite_from_dataset(name, libero.open_dataset(name, root), images_in_memory=False)
    if source == "sim":
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        from bench.sim import demos

        path = _sim_suite_path(name, root, sim_spec, progress=progress)
        ds = LeRobotDataset(demos.repo_id(name), root=path)
        libero.validate_features(ds.features, demos.repo_id(name))
        return suite_from_dataset(name, ds, images_in_memory=True)
    raise ValueError(f"unknown suite source {source!r}; choose one of {list(SOURCES)}")


def _sim_suite_path(name: str, root: str | Path | None = None, spec=None, *,
                    progress: ProgressSink) -> Path:
    """Folder of the generated "sim" suite `name` (generated on first use; needs the extra)."""
    from bench.sim import demos
    from bench.sim import env as sim_env

    if name not in demos.DEFAULT_SPECS:
        raise ValueError(f"suite {name!r} has no simulated version; choose one of "
                         f"{sorted(demos.DEFAULT_SPECS)}")
    spec = spec or demos.DEFAULT_SPECS[name]
    path = Path(root) if root is not None else demos.suite_path(spec)
    if (path / "meta" / "info.json").is_file():
        return path
    if not sim_env.libero_available():
        raise SuiteUnavailable(f"sim suite {name!r} is not generated at {path} and the LIBERO "
                               f"simulator is missing; {sim_env.INSTALL_HINT}, then "
                               f"`.venv/bin/python -m bench.sim.demos --suite {name}`")
    return demos.generate(spec, path, progress)


def _columns(hf_dataset, keys: list[str]) -> dict[str, np.ndarray]:
    return hf_dataset.with_format("numpy", columns=keys)[:]


def _check_contiguous(repo_id: str, episode_index: np.ndarray, frame_index: np.ndarray) -> None:
    """Episodes must be stored as contiguous runs with frame_index 0..len-1 (windows rely on it)."""
    starts = np.r_[True, episode_index[1:] != episode_index[:-1]]
    run_id = np.cumsum(starts) - 1
    expected = np.arange(len(frame_index)) - np.flatnonzero(starts)[run_id]
    if len(np.unique(episode_index)) != int(starts.sum()) or not np.array_equal(frame_index, expected):
        raise SuiteUnavailable(f"{repo_id}: frames are not stored episode by episode in order; "
                               "re-export the dataset sorted by (episode_index, frame_index)")


def suite_from_dataset(name: str, ds, images_in_memory: bool,
                       camera_keys: tuple[str, ...] = IMAGE_KEYS) -> Suite:
    """A Suite from a loaded LeRobotDataset (global frame index = row of its hf_dataset), its
    cameras `camera_keys` (LIBERO's unless given: a dataset of your own, bench.suites.user)."""
    hf = ds.hf_dataset
    cols = _columns(hf, [STATE_KEY, ACTION_KEY, "episode_index", "frame_index", "task_index"])
    _check_contiguous(ds.repo_id, cols["episode_index"], cols["frame_index"])
    tasks_df = ds.meta.tasks.sort_values("task_index")
    tasks = [str(t) for t in tasks_df.index]
    if list(tasks_df["task_index"]) != list(range(len(tasks))):
        raise SuiteUnavailable(f"{ds.repo_id}: task indices are not 0..{len(tasks) - 1}")
    image_shape = libero.image_shape_chw(ds.features[camera_keys[0]])
    hasher = hashlib.sha256()
    for key in (STATE_KEY, ACTION_KEY, "episode_index", "frame_index", "task_index"):
        hasher.update(np.ascontiguousarray(cols[key]).tobytes())
    hasher.update("\n".join(tasks).encode())

    if images_in_memory:
        # Small suites: decode every image once, keep (N, 3, H, W) uint8.
        stored = {cam: torch.from_numpy(_columns(hf, [cam])[cam]).permute(0, 3, 1, 2).contiguous()
                  for cam in camera_keys}
        for cam in camera_keys:
            hasher.update(stored[cam].numpy().tobytes())

        def image_loader(frames: torch.Tensor) -> dict[str, torch.Tensor]:
            return {cam: stored[cam][frames] for cam in camera_keys}
    else:
        image_loader = _dataset_image_loader(ds, camera_keys)
        n = len(cols["action"])
        sample = torch.as_tensor(np.unique(np.linspace(0, n - 1, FINGERPRINT_IMAGE_SAMPLES).astype(int)))
        for cam, image in image_loader(sample).items():
            hasher.update(cam.encode())
            hasher.update((image * 255).round().to(torch.uint8).numpy().tobytes())

    return Suite(
        name=name,
        repo_id=ds.repo_id,
        root=str(ds.root),
        fps=int(ds.fps),
        fingerprint=hasher.hexdigest()[:16],
        camera_keys=tuple(camera_keys),
        image_shape=image_shape,
        state=torch.from_numpy(np.asarray(cols[STATE_KEY], dtype=np.float32)),
        action=torch.from_numpy(np.asarray(cols[ACTION_KEY], dtype=np.float32)),
        episode_index=torch.from_numpy(cols["episode_index"].astype(np.int64)),
        frame_index=torch.from_numpy(cols["frame_index"].astype(np.int64)),
        task_index=torch.from_numpy(cols["task_index"].astype(np.int64)),
        tasks=tasks,
        stats=ds.meta.stats,
        image_loader=image_loader,
    )


def _dataset_image_loader(ds, camera_keys=IMAGE_KEYS):
    """frames -> {camera: (B, 3, H, W) float32 [0, 1]} decoded from the dataset on demand."""
    video = any(ds.features[cam]["dtype"] == "video" for cam in camera_keys)

    def image_loader(frames: torch.Tensor) -> dict[str, torch.Tensor]:
        if video:  # LeRobot decodes video frames itself (needs FFmpeg)
            items = [ds[int(f)] for f in frames]
            return {cam: torch.stack([it[cam] for it in items]) for cam in camera_keys}
        rows = ds.hf_dataset.select_columns(list(camera_keys))[frames.tolist()]
        return {cam: torch.stack(list(rows[cam])) for cam in camera_keys}

    return image_loader


__all__ = ["SUITES", "SOURCES", "SuiteSpec", "Suite", "SuiteUnavailable", "load_suite"]
