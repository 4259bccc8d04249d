"""Encoders from a user's own module: `--encoders PKG.MODULE:FACTORY` (e.g. `mypkg.enc:make`).

The contract, the least the harness needs to feed, cache and record an encoder honestly:

    # mypkg/enc.py, importable: its folder on PYTHONPATH
    class Net(torch.nn.Module):
        input_size = 224                 # int: images are resized to input_size x input_size
        mean = (0.485, 0.456, 0.406)     # 3 floats: subtracted per channel after the resize
        std = (0.229, 0.224, 0.225)      # 3 floats: then divided by, per channel
        channels = 384                   # int: C of the grid forward returns
        weights_id = "mynet-v1"          # str: names the weights (see below)

        def forward(self, x):            # (B, 3, input_size, input_size) float32, normalised
            ...                          #   -> (B, channels, h, w) feature grid

    def make():                          # or make(source): "tiny" or "hub", the profile's source
        return Net()

- The part before ':' is a module path when it contains '.', or when it is importable and not
  a registered prefix ("timm"). It is imported with `importlib.import_module`, as any module on
  your PYTHONPATH; no file is exec'd and no remote code is fetched.
- FACTORY is called with no arguments, or as FACTORY(source=...) when it has a `source`
  parameter; once per (name, source) per process (a later build returns the same module),
  under a forked CPU RNG seeded with 0: a random-init factory gives the same weights in every
  run and leaves the global RNG alone.
- `weights_id` is the promise "same id, same weights": the feature cache key and the record's
  `encoder_weights` carry it (beside the name, input size and mean/std). Change it whenever the
  weights change, or the cache serves features of the old ones.
- The harness feeds it as it feeds timm encoders (resize, normalise), freezes it (no gradients,
  eval mode for good) and runs one probe forward of a zero image, so a missing attribute or a
  wrong grid fails in one line at start-up, before any cell trains.
- The hub preflight lists no artifact for it: where its weights come from is its module's call.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import re
from typing import Callable

import torch
from graftcore.encoder import FrozenEncoder  # what a timm encoder is, frozen
from torch import Tensor

from encoders.base import PRETRAINED, Encoder, EncoderSpec, UnknownEncoder

FACTORY_SEED = 0
CONTRACT = ("input_size: int, mean and std: 3 floats each, channels: int, weights_id: str; "
            "see encoders/user_encoders.py")
_DOTTED = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")
_BUILT: dict[tuple[str, str], "ModuleEncoder"] = {}


class UserEncoderError(ValueError):
    """A MODULE:FACTORY encoder whose module, factory or returned object breaks the contract."""


def is_module_path(prefix: str) -> bool:
    """Whether the part of an encoder name before ':' names a module to import."""
    if not _DOTTED.fullmatch(prefix):
        return False
    try:
        return "." in prefix or importlib.util.find_spec(prefix) is not None
    except (ImportError, ValueError):  # e.g. a module in sys.modules without a spec
        return False


def _flat(text: str, limit: int = 300) -> str:
    flat = " ".join(str(text).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def load_factory(name: str) -> Callable:
    """The FACTORY callable of "PKG.MODULE:FACTORY"; one-line errors for a module that does not
    import and for a factory it does not define."""
    module_path, factory_name = name.split(":", 1)
    try:
        module = importlib.import_module(module_path)
    except ModuleNotFoundError as err:
        if err.name and (module_path + ".").startswith(err.name + "."):  # it, or a parent
            raise UnknownEncoder(
                f"encoder {name!r}: no module {module_path!r} to import; put the folder that "
                f"holds it on PYTHONPATH, or fix the name") from None
        raise UserEncoderError(f"encoder {name!r}: importing {module_path!r} failed "
                               f"({_flat(err)}); install what it imports") from err
    except Exception as err:  # the user's module raised at import
        raise UserEncoderError(f"encoder {name!r}: importing {module_path!r} raised "
                               f"{type(err).__name__}: {_flat(err)}; fix that module") from err
    factory = getattr(module, factory_name, None)
    if not callable(factory):
        where = getattr(module, "__file__", None) or module_path
        found = sorted(n for n, v in vars(module).items()
                       if callable(v) and not n.startswith("_")
                       and getattr(v, "__module__", None) == module.__name__)
        what = "has no" if factory is None else "has a non-callable"
        raise UnknownEncoder(
            f"encoder {name!r}: module {module_path!r} ({where}) {what} factory "
            f"{factory_name!r}; define `def {factory_name}():` returning the encoder there, or "
            f"name one it defines ({', '.join(found) or 'it defines none'})")
    return factory


def _call(factory: Callable, name: str, source: str):
    try:
        takes_source = "source" in inspect.signature(factory).parameters
    except (TypeError, ValueError):  # no signature to read (a C callable): call it bare
        takes_source = False
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(FACTORY_SEED)
        try:
            return factory(source=source) if takes_source else factory()
        except Exception as err:
            raise UserEncoderError(f"encoder {name!r}: the factory raised {type(err).__name__}: "
                                   f"{_flat(err)}; fix the factory") from err


def _numbers(value, count: int) -> tuple[float, ...] | None:
    if not isinstance(value, (tuple, list)) or len(value) != count:
        return None
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        return None
    return tuple(float(v) for v in value)


def declared(obj, name: str) -> dict:
    """The contract's five attributes of what FACTORY returned, checked; one-line errors."""
    module_path, factory_name = name.split(":", 1)
    made = f"{module_path}.{factory_name}() returned a {type(obj).__name__}"
    if not isinstance(obj, torch.nn.Module):
        raise UserEncoderError(f"encoder {name!r}: {made}, not a torch.nn.Module; return the "
                               f"module itself, declaring {CONTRACT}")
    missing = [a for a in ("input_size", "mean", "std", "channels", "weights_id")
               if not hasattr(obj, a)]
    if missing:
        raise UserEncoderError(f"encoder {name!r}: {made} without {', '.join(missing)}; set "
                               f"{'it' if len(missing) == 1 else 'them'} on it ({CONTRACT})")
    found = {"input_size": obj.input_size, "channels": obj.channels,
             "mean": _numbers(obj.mean, 3), "std": _numbers(obj.std, 3),
             "weights_id": obj.weights_id}
    bad = [a for a in ("input_size", "channels")
           if isinstance(found[a], bool) or not isinstance(found[a], int) or found[a] < 1]
    bad += [a for a in ("mean", "std") if found[a] is None]
    bad += [] if found["std"] is None or all(s > 0 for s in found["std"]) else ["std"]
    if not isinstance(found["weights_id"], str) or not found["weights_id"].strip():
        bad.append("weights_id")
    if bad:
        shown = ", ".join(f"{a}={getattr(obj, a)!r}" for a in dict.fromkeys(bad))
        raise UserEncoderError(f"encoder {name!r}: {made} with {shown}; need {CONTRACT} "
                               f"(std positive, sizes at least 1)")
    return found


class ModuleEncoder(FrozenEncoder, Encoder):
    """A user's module, frozen and fed like a timm encoder.
    forward: (B, 3, H, W) float in [0,1] -> (B, channels, h, w) float32."""

    def __init__(self, spec: EncoderSpec, module: torch.nn.Module, channels: int, weights_id: str):
        super().__init__(spec, spec.input_size, weights_id)
        self.module = module
        self.channels = channels
        self.freeze()

    @torch.no_grad()
    def forward(self, images: Tensor) -> Tensor:
        return self.module(self.normalised(images)).float().contiguous()


def _probe(encoder: ModuleEncoder, name: str) -> None:
    """One zero image through the encoder: the grid must be (1, channels, h, w)."""
    tensors = (*encoder.module.parameters(), *encoder.module.buffers())
    device = tensors[0].device if tensors else torch.device("cpu")
    size = encoder.input_size
    encoder.to(device)
    try:
        grid = encoder(torch.zeros(1, 3, size, size, device=device))
    except Exception as err:
        raise UserEncoderError(f"encoder {name!r}: forward of a (1, 3, {size}, {size}) image "
                               f"raised {type(err).__name__}: {_flat(err)}; fix its forward"
                               ) from err
    shape = tuple(grid.shape) if isinstance(grid, Tensor) else type(grid).__name__
    if not isinstance(grid, Tensor) or grid.ndim != 4 or grid.shape[:2] != (1, encoder.channels):
        raise UserEncoderError(
            f"encoder {name!r}: forward of a (1, 3, {size}, {size}) image returned {shape}, "
            f"expected (1, channels={encoder.channels}, h, w); return a (B, C, h, w) grid and "
            f"declare C as channels")


def build_module_encoder(name: str, source: str) -> ModuleEncoder:
    """The frozen encoder "PKG.MODULE:FACTORY" returns for `source`, checked against the contract
    (built once per name and source per process)."""
    if (name, source) in _BUILT:
        return _BUILT[(name, source)]
    factory = load_factory(name)
    obj = _call(factory, name, source)
    found = declared(obj, name)
    module_path, factory_name = name.split(":", 1)
    where = getattr(inspect.getmodule(factory), "__file__", None) or module_path
    spec = EncoderSpec(
        name=name, timm_name=None, input_size=found["input_size"], mean=found["mean"],
        std=found["std"], layout="map",
        description=f"user encoder {module_path}.{factory_name}() ({where}): "
                    f"{found['channels']} ch at {found['input_size']} px, weights "
                    f"{found['weights_id']!r}",
        weights=PRETRAINED)  # a team's own encoder is one of its candidates
    encoder = ModuleEncoder(spec, obj, found["channels"], found["weights_id"])
    _probe(encoder, name)
    _BUILT[(name, source)] = encoder
    return encoder
