"""A cell's policy as a closed-loop controller: `act(raw observation) -> raw action chunk`.

The rollout engine (bench.sim.rollout) steps LIBERO and asks `act` for the next chunk; `act` runs
the SAME path as offline scoring (the backbone's own pre-processor, its sampler with the graft
spliced in, its own un-normaliser), so success and offline MSE measure one policy.

Sampler noise is a function of the observation (state bytes and task string, per row): cells
that see the same observation draw the same noise (common random numbers in closed loop too),
and a rerun of the same cell is bit-identical without any counter to keep in step.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from bench.progress import ProgressSink
from bench.results.provenance import stable_seed
from ondisk.libero_format import LIBERO_ACTION_DIM, STATE_KEY
from bench.loops.evaluate import executed_steps, sample_grafted
from bench.grid.kinds import NO_CLOSED_LOOP, ZERO
from ondisk.libero_format import LIBERO_SUITES

# A function of one observation's images {camera: (B, 3, H, W)} (features, or other images).
ObservationFn = Callable[[dict[str, Tensor]], dict[str, Tensor]]


@dataclass(frozen=True)
class LoopGraft:
    """What a graft splices into the policy in closed loop: its feed (projector; for
    native_wrapped the policy's own tower through the wrapper), and, for an encoder graft, the
    encoder that turns each rendered frame into features pooled to `grid`."""

    feed: object
    encoder: object = None
    grid: tuple | None = None


def observation_noise(raw: dict, chunk: int, width: int, seed: int) -> Tensor:
    """(B, chunk, width) standard normal noise, row b seeded by (seed, task_b, state_b bytes)."""
    states = raw[STATE_KEY].detach().float().cpu().contiguous()
    rows = []
    for b in range(states.shape[0]):
        key = stable_seed(seed, raw["task"][b], states[b].numpy().tobytes().hex())
        rows.append(torch.randn((chunk, width), generator=torch.Generator().manual_seed(key)))
    return torch.stack(rows)


def make_act(backbone, *, noise_seed: int, feed=None, features_from_images: ObservationFn | None = None,
             images_transform: ObservationFn | None = None) -> Callable[[dict], Tensor]:
    """The closed-loop controller of a cell.

    feed: the cell's GraftFeed (None for native cells); features_from_images: pixels -> pooled
    graft features {camera: (B, h*w, C)} (None when the feed runs a tower itself);
    images_transform: applied to the observed images first (zero_image controls).
    """
    info = backbone.info
    device = next(backbone.policy.parameters()).device
    cameras = backbone.camera_keys

    @torch.no_grad()
    def act(raw_obs: dict) -> Tensor:
        missing = [k for k in (*cameras, STATE_KEY, "task") if k not in raw_obs]
        if missing:
            raise KeyError(f"observation lacks {missing}; the policy reads {[*cameras, STATE_KEY]}")
        n = raw_obs[STATE_KEY].shape[0]
        images = {k: raw_obs[k].float() for k in cameras}
        if images_transform is not None:
            images = images_transform(images)
        raw = {**raw_obs, **images,
               # The pre-processors expect the training keys; the sampler never reads them.
               "action": torch.zeros((n, info.chunk_size, LIBERO_ACTION_DIM)),
               "action_is_pad": torch.zeros((n, info.chunk_size), dtype=torch.bool)}
        batch = backbone.preprocess(raw)
        noise = observation_noise(raw_obs, info.chunk_size, info.max_action_dim, noise_seed)
        features = features_from_images(images) if feed is not None and features_from_images \
            else None
        pred = sample_grafted(backbone, batch, noise.to(device), feed, features)
        pred = pred[..., :LIBERO_ACTION_DIM].float()
        return backbone.unnormalize_actions(pred).float().cpu()

    return act


ROLLOUT_SEED = 0  # env seeds of rollout episodes (init states are fixed by the episode index)

def cell_act(cell, backbone, *, noise_seed: int, graft: LoopGraft | None = None,
             perturb: ObservationFn | None = None):
    """`make_act` for a cell: native cells sample as released; grafts encode live pixels.
    `perturb`: applied to every rendered frame before the policy or its encoder sees it (the
    robustness tier in closed loop: bench.robust.closed_loop)."""
    zero = cell.spec.eval_inputs == ZERO
    transform = (lambda images: {k: torch.zeros_like(v) for k, v in images.items()}) if zero else None
    if perturb is not None:
        transform = perturb if transform is None else (lambda images: transform(perturb(images)))
    if graft is None:
        return make_act(backbone, noise_seed=noise_seed, images_transform=transform)
    feed, encoder, grid = graft.feed, graft.encoder, graft.grid
    if feed.tower is not None:  # native_wrapped: the feed runs the policy's own tower itself
        return make_act(backbone, noise_seed=noise_seed, feed=feed, images_transform=transform)
    from bench.loops.encode import encode_pooled

    return make_act(backbone, noise_seed=noise_seed, feed=feed, images_transform=transform,
                    features_from_images=lambda images: encode_pooled(encoder, images, grid))


def rollout_spec(suite, episodes_per_task: int, n_action_steps: int, descriptions=None):
    """The RolloutSpec of a LIBERO-backed suite: every task the suite's data holds, matched to
    LIBERO's task ids by instruction text (`descriptions`: suite -> instructions, LIBERO's)."""
    from bench.sim import env as sim_env
    from bench.sim.rollout import RolloutSpec

    if suite.name not in sim_env.LIBERO_SUITES:
        raise ValueError(f"suite {suite.name!r} has no LIBERO scene to roll out in; "
                         f"choose one of {sorted(sim_env.LIBERO_SUITES)}")
    texts = (descriptions or sim_env.task_descriptions)(suite.name)
    ids = {text.strip().lower(): i for i, text in enumerate(texts)}
    unknown = [t for t in suite.tasks if t.strip().lower() not in ids]
    if unknown:
        raise ValueError(f"suite {suite.name!r} ({suite.repo_id}) has tasks that are not LIBERO "
                         f"{sim_env.LIBERO_SUITES[suite.name]} instructions: {unknown[:3]}; "
                         "rollouts need the LIBERO-backed suite (--profile sim or paper)")
    tasks = tuple(sorted({ids[t.strip().lower()] for t in suite.tasks}))
    return RolloutSpec(suite=suite.name, tasks=tasks, episodes_per_task=episodes_per_task,
                       seed=ROLLOUT_SEED, max_steps=LIBERO_SUITES[suite.name].max_steps,
                       n_action_steps=n_action_steps)


def policy_identity(measured, **more) -> str:
    """What names a cell's policy for its episode log: what it was measured under (a record's
    MeasuredUnder) and `more`, without the grid file's provenance: its text is a study's notes
    (a comment edited between sittings restarted 33 episodes of a resumed item), what it sets
    is in the protocol and the checkpoint already."""
    from dataclasses import asdict

    fields = {k: v for k, v in asdict(measured).items() if k != "grid_file"}
    return json.dumps({"measured": fields, **more} if more else fields, sort_keys=True,
                      default=str)


def policy_fingerprint(backbone, feed, identity: str) -> str:
    """sha256 naming the policy a cell rolls out: `identity` (its checkpoint and protocol, as
    recorded) and the parameters it trained (projector, LoRA). Episodes resumed from an episode
    log must come from this very policy; a retrained one that differs starts over."""
    digest = hashlib.sha256(identity.encode())
    trained = sorted(feed.projector.state_dict().items()) if feed is not None else []
    trained += sorted((n, p) for n, p in backbone.policy.named_parameters() if "lora_" in n)
    for name, tensor in trained:
        digest.update(name.encode())
        digest.update(tensor.detach().float().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def rollout_log_key(spec, render, policy: str) -> str:
    """What an episode log's episodes belong to: the spec, the render settings, the policy."""
    from dataclasses import asdict

    blob = json.dumps({"spec": asdict(spec), "render": asdict(render), "policy": policy},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def cell_rollouts(cell, suite, backbone, episodes_per_task: int, *,
                  graft: LoopGraft | None = None, progress: ProgressSink, store=None,
                  policy: str = "", scenes=None, batching=None, perturb=None,
                  log_id: str | None = None, kept: dict | None = None) -> dict:
    """Roll the cell's policy out in LIBERO; the dict stored under the record's "rollouts".

    With a results `store`, every finished episode is kept in the cell's episode log (under
    the spec, render settings and `policy`, a policy_fingerprint) and a rerun after a kill
    resumes from it. `scenes`: bench.sim.rollout.Scenes (LIBERO's unless a test passes one);
    `batching`: bench.sim.rollout.Batching (None: in-process), the same episodes whatever it is,
    so the episode log's key leaves it out. `perturb` (cell_act) and
    `log_id` (the episode log's name, default the cell id): the robustness tier's rollouts.
    `kept`: a stored record's rollouts of this policy at fewer episodes per task (bench.cell.
    extend), whose episodes are kept, not rolled out again; another spec or render is refused."""
    if cell.spec.eval_inputs in NO_CLOSED_LOOP:
        return {"skipped": NO_CLOSED_LOOP[cell.spec.eval_inputs]}
    from dataclasses import asdict

    from bench.sim.rollout import IN_PROCESS, LIBERO, run_rollouts

    scenes = scenes or LIBERO
    spec = rollout_spec(suite, episodes_per_task, executed_steps(backbone), scenes.descriptions)
    render = suite_render(suite)
    act = cell_act(cell, backbone, noise_seed=spec.seed, graft=graft, perturb=perturb)
    log = (store.episode_log(log_id or cell.id, rollout_log_key(spec, render, policy))
           if store else None)
    finished = kept_episodes(kept, spec, render) + (log.finished() if log else [])
    out = run_rollouts(act, spec, progress=progress, render=render, finished=finished,
                       on_episode=log.add if log else None, scenes=scenes,
                       batching=batching or IN_PROCESS)
    # Each task's instruction, so an episode's LIBERO task id meets the record's task name
    # (per-task success against per-task MSE: bench.analysis.offline_measures).
    texts = scenes.descriptions(spec.suite)
    return {**out, "spec": asdict(spec), "task_names": {str(t): texts[t] for t in spec.tasks}}


def kept_episodes(kept: dict | None, spec, render) -> list[dict]:
    """The episodes of stored rollouts `kept` (None: none) that `spec` begins with: the same spec
    but for fewer episodes per task, the same render settings; ValueError naming the difference
    otherwise (their episodes are other scenes: the cell must be measured again)."""
    from dataclasses import asdict

    if not kept or not kept.get("episodes"):
        return []
    def as_stored(value):  # as a record holds it (JSON: tuples are lists)
        return json.loads(json.dumps(value))

    want = {**asdict(spec), "episodes_per_task": kept["spec"]["episodes_per_task"]}
    have_render = (kept.get("settings") or {}).get("render")
    if (as_stored(kept["spec"]) != as_stored(want)
            or have_render is not None and as_stored(have_render) != as_stored(render.as_dict())):
        raise ValueError(f"the stored rollouts ({kept['spec']}, render {have_render}) are not "
                         f"the first episodes of {asdict(spec)} (render {render.as_dict()}): "
                         "measure the cell again (--rerun)")
    return [e for e in kept["episodes"] if int(e["episode"]) < spec.episodes_per_task]


def suite_render(suite):
    """Render settings matching the suite's frames: a generated sim suite's own, else LIBERO's
    defaults at the dataset's image size (the policy must see images like its training data)."""
    from pathlib import Path

    from bench.sim import demos
    from bench.sim.env import RenderSettings

    if (Path(suite.root) / demos.SUITE_FILE).is_file() and "render" in demos.suite_info(suite.root):
        return demos.render_settings(suite.root)
    return RenderSettings(image_size=suite.image_shape[-1])
