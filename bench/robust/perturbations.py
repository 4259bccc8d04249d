"""Perturbations of held-out images (the robustness tier): ONE table, one entry per kind.

A kind is one `register_perturbation(Perturbation(...))`: its name, what it does, its parameters
at severities 1, 2 and 3, and the function that applies them. Severity 0 is every kind's identity
(the images are returned as they are: the clean record's bits). A perturbation is deterministic
per window: whatever it draws (a noise field, a shift direction, a patch position) comes from
`stable_seed(PERTURBATION_SEED, kind, severity, frame, camera)`, never from the cell, so every
cell of a suite sees the same perturbed frames and comparisons stay paired.

`--robustness KIND[:SEVERITIES],...` and the grid file's `robustness = [...]` name entries of this
table (`parse_robustness`); a record stores each perturbation's parameters (`Applied.to_json`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F
import torchvision.transforms.v2.functional as TF

from bench.results.provenance import stable_seed
from bench.table import Table

SEVERITIES = (0, 1, 2, 3)
DEFAULT_SEVERITIES = (1, 2, 3)
# Fixed, so the perturbed frames are the same in every run; part of each stored perturbation.
PERTURBATION_SEED = 2024
# Bump when an entry's function changes what it draws or computes (stored records then rerun).
PERTURBATIONS_VERSION = "1"

# apply(images (B, 3, H, W) float32 in [0, 1], params, per-image seeds (B,)) -> same shape
ApplyFn = Callable[[torch.Tensor, dict, list[int]], torch.Tensor]


@dataclass(frozen=True)
class Perturbation:
    """One kind: `levels[s - 1]` are its parameters at severity s (1..3)."""

    name: str
    summary: str  # one line: what changes in the scene (--help, report)
    levels: tuple[dict, dict, dict]
    apply: ApplyFn

    def params(self, severity: int) -> dict:
        return {} if severity == 0 else dict(self.levels[severity - 1])


PERTURBATIONS: Table[Perturbation] = Table("perturbation kind", "kinds")


def register_perturbation(kind: Perturbation) -> Perturbation:
    if len(kind.levels) != len(DEFAULT_SEVERITIES):
        raise ValueError(f"perturbation {kind.name!r}: give parameters for severities "
                         f"{DEFAULT_SEVERITIES}")
    return PERTURBATIONS.register(kind)


@dataclass(frozen=True)
class Applied:
    """A kind at a severity, as a record stores it (with its parameters and seed)."""

    kind: str
    severity: int

    @property
    def label(self) -> str:
        return f"{self.kind}:{self.severity}"

    @property
    def params(self) -> dict:
        return PERTURBATIONS[self.kind].params(self.severity)

    def to_json(self) -> dict:
        return {"kind": self.kind, "severity": self.severity, "params": self.params,
                "seed": PERTURBATION_SEED, "version": PERTURBATIONS_VERSION}

    def images(self, images_by_camera: dict[str, torch.Tensor],
               frames: torch.Tensor) -> dict[str, torch.Tensor]:
        """{camera: (B, 3, H, W) in [0, 1]} of windows starting at global `frames` (B,),
        perturbed; severity 0 returns the same tensors."""
        if self.severity == 0:
            return images_by_camera
        kind, params = PERTURBATIONS[self.kind], self.params
        out = {}
        for camera, images in images_by_camera.items():
            seeds = [stable_seed(PERTURBATION_SEED, self.kind, self.severity, int(f), camera)
                     for f in torch.as_tensor(frames).reshape(-1).tolist()]
            out[camera] = kind.apply(images.float(), params, seeds).clamp_(0.0, 1.0)
        return out


def parse_robustness(values, where: str) -> tuple[Applied, ...]:
    """["brightness", "blur:1,3", "all"] -> the (kind, severity) pairs, table order, each once.
    A bare kind means severities 1-3; ValueError, one line naming `where`, otherwise."""
    wanted: set[tuple[str, int]] = set()
    for value in values:
        name, _, given = str(value).strip().partition(":")
        if name != "all" and name.lower() == "all":  # keywords are lower case, on every option
            raise ValueError(f"{where}: {name}: keywords are lower case; give all")
        names = list(PERTURBATIONS) if name == "all" else [name]
        if name != "all" and name not in PERTURBATIONS:
            raise ValueError(f"{where}: {PERTURBATIONS.refusal(name)} (or all), each as KIND "
                             "or KIND:SEVERITIES, e.g. blur:1,3")
        severities = DEFAULT_SEVERITIES
        if given:
            parts = [s.strip() for s in given.replace("+", ",").split(",") if s.strip()]
            bad = [s for s in parts if not s.isdigit() or int(s) not in SEVERITIES]
            if bad or not parts:
                raise ValueError(f"{where}: {value!r}: severity {','.join(bad) or '(none)'} out "
                                 f"of range; give severities in {SEVERITIES[0]}..{SEVERITIES[-1]} "
                                 f"(0: no change), e.g. {name}:1,2,3")
            severities = tuple(int(s) for s in parts)
        wanted |= {(n, s) for n in names for s in severities}
    order = list(PERTURBATIONS)
    return tuple(Applied(k, s) for k, s in sorted(wanted, key=lambda p: (order.index(p[0]), p[1])))


# --- the kinds ---------------------------------------------------------------------------------

def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _brightness(images, params, seeds):
    return images * params["gain"]


def _contrast(images, params, seeds):
    grey = images.mean(dim=(1, 2, 3), keepdim=True)
    return (images - grey) * params["factor"] + grey


def _colour(images, params, seeds):
    return TF.adjust_saturation(TF.adjust_hue(images, params["hue"]), params["saturation"])


def _noise(images, params, seeds):
    draws = torch.stack([torch.randn(images.shape[1:], generator=_generator(s)) for s in seeds])
    return images + params["sigma"] * draws.to(images.device)


def _blur(images, params, seeds):
    sigma = params["sigma_frac"] * max(images.shape[-2:])
    size = 2 * math.ceil(3 * sigma) + 1
    return TF.gaussian_blur(images, [size, size], [sigma, sigma])


def _camera_shift(images, params, seeds):
    """Each image moved by `shift_frac` of its side in a direction drawn per window, and turned
    by `degrees` either way (edges replicated, as bench.loops.augment's shift)."""
    n = len(seeds)
    theta = torch.zeros((n, 2, 3))
    for i, seed in enumerate(seeds):
        draw = torch.rand(2, generator=_generator(seed))
        direction = 2 * math.pi * float(draw[0])
        turn = math.radians(params["degrees"]) * (1.0 if float(draw[1]) < 0.5 else -1.0)
        cos, sin = math.cos(turn), math.sin(turn)
        # affine_grid's coordinates span [-1, 1]: a shift of f of the side is 2f
        theta[i] = torch.tensor([[cos, -sin, 2 * params["shift_frac"] * math.cos(direction)],
                                 [sin, cos, 2 * params["shift_frac"] * math.sin(direction)]])
    grid = F.affine_grid(theta.to(images.device), list(images.shape), align_corners=False)
    return F.grid_sample(images, grid, mode="bilinear", padding_mode="border",
                         align_corners=False)


def _occlusion(images, params, seeds):
    """A grey square of `side_frac` of the image side, at a position drawn per window."""
    out = images.clone()
    h, w = images.shape[-2:]
    side = max(1, round(params["side_frac"] * min(h, w)))
    for i, seed in enumerate(seeds):
        y, x = (torch.rand(2, generator=_generator(seed)) * torch.tensor([h - side, w - side]))
        y, x = int(y), int(x)
        out[i, :, y:y + side, x:x + side] = params["grey"]
    return out


register_perturbation(Perturbation(
    "brightness", "a dimmer scene: every pixel times a gain",
    ({"gain": 0.8}, {"gain": 0.6}, {"gain": 0.4}), _brightness))
register_perturbation(Perturbation(
    "contrast", "flatter lighting: pixels pulled towards the image's mean grey",
    ({"factor": 0.75}, {"factor": 0.5}, {"factor": 0.3}), _contrast))
register_perturbation(Perturbation(
    "colour", "another white balance: hue turned (fraction of a turn), saturation lowered",
    ({"hue": 0.05, "saturation": 0.8}, {"hue": 0.1, "saturation": 0.6},
     {"hue": 0.2, "saturation": 0.4}), _colour))
register_perturbation(Perturbation(
    "noise", "sensor noise: Gaussian, std in [0, 1] pixel units, a fixed draw per window",
    ({"sigma": 0.02}, {"sigma": 0.05}, {"sigma": 0.1}), _noise))
register_perturbation(Perturbation(
    "blur", "defocus: Gaussian blur, std as a fraction of the image side",
    ({"sigma_frac": 0.005}, {"sigma_frac": 0.01}, {"sigma_frac": 0.02}), _blur))
register_perturbation(Perturbation(
    "camera_shift", "the camera moved: shifted by a fraction of the side and turned a few degrees",
    ({"shift_frac": 0.03, "degrees": 2.0}, {"shift_frac": 0.06, "degrees": 4.0},
     {"shift_frac": 0.1, "degrees": 6.0}), _camera_shift))
register_perturbation(Perturbation(
    "occlusion", "clutter: a grey square of a fraction of the side, placed per window",
    ({"side_frac": 0.15, "grey": 0.5}, {"side_frac": 0.25, "grey": 0.5},
     {"side_frac": 0.35, "grey": 0.5}), _occlusion))
