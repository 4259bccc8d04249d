"""A study in a file: `pytest bench --grid study.toml` reads the grid from TOML, so a study can be
rerun and shared as one file. The file's path, sha256 and text go into every record.

Schema (every key optional; lists are TOML arrays):

    profile = "tiny"                 # the base profile: tiny, tiny-full, paper, sim
    backbones = ["pi05"]             # registry names (backbones/)
    suites = ["spatial"]
    encoders = ["pixels", "blind", "dinov2_s", "timm:resnet18", "mypkg.enc:make"]
    seeds = [0, 1]                   # non-negative integers
    controls = []                    # control kinds (bench/grid/kinds.py), [] runs none; e.g. ["native"]
    control_encoders = ["pixels"]    # encoders the control cells run for
    steps = 60                       # projector steps (the same as [protocol] steps: give one)
    robustness = ["brightness", "blur:1,3"]  # the robustness tier: perturbation kinds (all: every one)
    pack_grafts = 4                  # graft cells trained per backbone pass (a run setting, not the
                                     #   protocol: no record changes identity; bench.cell.pack_run)

    [protocol]                       # any bench.grid.protocol.Protocol field by name, its type kept:
    lr = 0.003                       #   int, float (an int is taken), str, list of str
    batch_size = 16

Precedence: the base profile (`profile`, else tiny) < the file < the command line. `--profile`
replaces the file's base profile and the file's other keys still apply on top of it;
`--backbones`, `--encoders`, `--suites`, `--seeds`, `--controls` and `--steps` each replace the
file's value. Names (backbones, suites, encoders) are checked at collection, as on the command
line; everything else here, each error one line naming the file, the key and the valid choices.

Your own policy and data (bench.grid.user_specs; `--policy`, `--dataset`, `--camera-map` each
replace the file's table):

    [policies]                       # NAME = "REPO_ID_OR_PATH[@REVISION]": backbones of the grid
    mine = "/path/to/checkpoint"     #   (without `backbones`, the grid's backbones are these)
    [datasets]                       # NAME = "REPO_ID_OR_PATH": suites (likewise for `suites`)
    mydata = "data/my_dataset"       #   a relative path is relative to the grid file's folder
    [camera_map]                     # POLICY_CAMERA = "DATASET_CAMERA" (short names allowed)
    front = "top"

A committed study's tiny releases, pinned (bench.grid.pinned_release; checked at start-up):

    [releases]                       # BACKBONE = "FOLDER": <backbone>-<content hash>, relative
    pi05 = "releases/pi05-0123456789abcdef"   # to the grid file's folder; tiny profiles only
    smolvla = ["releases/smolvla-...", "releases/smolvla-..."]  # one per release, in order

Several independently trained tiny releases per backbone (release r trains from seed r; every
cell is measured on each, its id carrying `-rel<r>` for r > 0):

    releases_per_backbone = 3
    sim_demos = 6                    # sim profile: demonstrations per task (--sim-demos replaces it)

Adding a key is one entry in `KEYS` or `TABLES` plus the line of `GridFile.apply` that passes it
on. A key nothing can pass on yet is rejected, never silently ignored.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from bench.grid.kinds import NATIVE, control_kinds
from bench.grid.protocol import (PROFILES, GridFileInfo, Profile, Protocol, range_error,
                                 with_overrides)
from bench.grid.user_specs import parse_camera_map, parse_named, with_user_world


class GridFileError(ValueError):
    """A grid file that cannot be read or breaks the schema: one line naming file and key."""


@dataclass(frozen=True)
class GridFile:
    """A parsed grid file: the base profile's name, Profile fields, steps, Protocol fields."""

    info: GridFileInfo
    profile: str | None
    grid: tuple[tuple[str, tuple], ...]  # (Profile field, value) in file order
    steps: int | None
    protocol: tuple[tuple[str, Any], ...]  # (Protocol field, value)
    # [policies], [datasets], [camera_map] (None: not in the file)
    user_world: tuple[tuple[str, Any], ...] = ()
    # A run setting, not the profile's: bench.options reads it (--pack-grafts replaces it).
    pack_grafts: int | None = None

    def apply(self, base: Profile) -> Profile:
        """`base` with the file's values and its provenance (grid_file) set."""
        with_file = dataclasses.replace(base, protocol=base.protocol.replace(**dict(self.protocol)),
                                        grid_file=self.info)
        with_file = with_user_world(with_file, **dict(self.user_world))
        if dict(self.grid).get("releases") and base.source != "tiny":
            raise _fail(self.info.path, "[releases]", f"pins tiny releases, and profile "
                        f"{base.name!r} loads real checkpoints; drop [releases] or use a tiny "
                        "profile (tiny, tiny-full, sim)")
        if dict(self.grid).get("sim_demos") and base.data_source != "sim":
            raise _fail(self.info.path, "sim_demos", f"sets simulated demonstrations, and profile "
                        f"{base.name!r} has no simulated suites; drop it or use profile sim")
        if dict(self.grid).get("releases_per_backbone", 1) > 1 and base.source != "tiny":
            raise _fail(self.info.path, "releases_per_backbone", f"> 1 trains tiny releases, and "
                        f"profile {base.name!r} loads real checkpoints; name each independently "
                        "trained checkpoint as its own backbone (--policy NAME=PATH) instead")
        return with_overrides(with_file, steps=self.steps, **dict(self.grid))


# --- value checks: (file, key, value) -> the value as the Profile holds it ---------------------

def _fail(where: str, key: str, problem: str) -> GridFileError:
    return GridFileError(f"{where}: {key} {problem}")


def _profile_name(where: str, key: str, value) -> str:
    if value not in PROFILES:
        raise _fail(where, key, f"= {value!r} is not a profile; choose one of {sorted(PROFILES)}")
    return value


# An example value of each list key, for the fix a message gives.
_EXAMPLES = {"backbones": '["pi05"]', "suites": '["spatial"]', "encoders": '["pixels", "dinov2_s"]',
             "control_encoders": '["pixels"]', "controls": f'["{NATIVE}"]',
             "robustness": '["brightness", "blur:1,3"] (or ["all"])'}
# Keys whose empty list means "nothing": [] runs no control / no robustness case. Any other
# empty list would run no cell at all (a run that "passes" with nothing measured): refused.
_MAY_BE_EMPTY = ("controls", "robustness")


def _strings(where: str, key: str, value) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise _fail(where, key, f"= {value!r}: give a list of names, e.g. {key} = "
                                f"{_EXAMPLES.get(key, '[...]')}")
    if not value and key not in _MAY_BE_EMPTY:
        raise _fail(where, key, f"= []: an empty list selects no cell; give e.g. {key} = "
                                f"{_EXAMPLES[key]}, or drop the key for the profile's")
    return tuple(value)


def _seeds(where: str, key: str, value) -> tuple[int, ...]:
    if not isinstance(value, list) or not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value) or not value:
        raise _fail(where, key, f"= {value!r}: give a non-empty list of non-negative integers, "
                                "e.g. seeds = [0, 1, 2]")
    return tuple(value)


def _controls(where: str, key: str, value) -> tuple[str, ...]:
    names = _strings(where, key, value)
    bad = [c for c in names if c not in control_kinds()]
    if bad:
        raise _fail(where, key, f"names unknown control kind(s) {bad}; valid: "
                                f"{', '.join(control_kinds())} ([] runs none)")
    return names


def _steps(where: str, key: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(where, key, f"= {value!r}: give a positive integer number of projector steps")
    problem = range_error("steps", value, where)
    if problem:
        raise GridFileError(problem)
    return value


def _pack_grafts(where: str, key: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise _fail(where, key, f"= {value!r}: give a whole number of grafts per backbone pass "
                                ">= 1, e.g. pack_grafts = 4 (1: one at a time, the default)")
    return value


def _releases_per_backbone(where: str, key: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 16:
        raise _fail(where, key, f"= {value!r}: give a whole number of independently trained "
                                "releases per backbone in [1, 16], e.g. releases_per_backbone = 3")
    return value


def _sim_demos(where: str, key: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 100:
        raise _fail(where, key, f"= {value!r}: give successful scripted demonstrations per task "
                                "in [1, 100] (held-out episodes are drawn from them), e.g. "
                                "sim_demos = 6")
    return value


def _protocol(where: str, key: str, table) -> tuple[tuple[str, Any], ...]:
    if not isinstance(table, dict):
        raise _fail(where, key, f"= {table!r}: give a [protocol] table of Protocol fields")
    defaults = {f.name: f.default for f in dataclasses.fields(Protocol)}
    out = []
    for name, value in table.items():
        if name not in defaults:
            raise _unknown_key(where, f"[protocol] {name}", name, defaults,
                               "top-level" if name in KEYS else None)
        value = _like(where, f"[protocol] {name}", value, defaults[name])
        problem = range_error(name, value, f"{where} [protocol]")  # the one table's ranges
        if problem:
            raise GridFileError(problem)
        if name == "tiny_image_size" and value % (patch := _tiny_patch()):
            low_side = value - value % patch
            raise _fail(where, f"[protocol] {name}", f"= {value} is not a multiple of the tiny "
                        f"patch size {patch}; give {low_side or patch} or {low_side + patch}")
        out.append((name, value))
    return tuple(out)


_KINDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
          tuple: "a list of strings"}


def _like(where: str, key: str, value, default):
    """`value` as a Protocol field of `default`'s type holds it."""
    if isinstance(default, bool) or isinstance(value, bool):
        ok = isinstance(value, bool) and isinstance(default, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float))
        value = float(value) if ok else value
    elif isinstance(default, tuple):
        ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
        value = tuple(value) if ok else value
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise _fail(where, key, f"= {value!r}: expected {_KINDS[type(default)]}, as the "
                                "Protocol field holds")
    return value


def _tiny_patch() -> int:
    """The tiny pi0 / pi0.5's patch size (its build checks the same); imported only here: the
    build's module loads LeRobot, which a start-up check must not wait for."""
    from backbones.tiny_paligemma import TinyPaliGemmaArch

    return TinyPaliGemmaArch.patch_size


def _unknown_key(where: str, key: str, name: str, known, home: str | None = None
                 ) -> GridFileError:
    """`home`: where the key belongs when it is one of another place's (a fix in one move)."""
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    if home:
        hint = f" (it is a {home} key: move it there)"
    return _fail(where, key, f"is not a key here{hint}; known: {', '.join(known)}")


# Top-level keys and their checks; `GridFile.apply` passes on every one.
KEYS: dict[str, Callable] = {
    "profile": _profile_name,
    "backbones": _strings,
    "suites": _strings,
    "encoders": _strings,
    "seeds": _seeds,
    "controls": _controls,
    "control_encoders": _strings,
    "steps": _steps,
    "robustness": _strings,  # perturbations, checked with --robustness's rules (bench.options)
    "pack_grafts": _pack_grafts,  # passed on by bench.options (a run setting), not by `apply`
    "releases_per_backbone": _releases_per_backbone,
    "sim_demos": _sim_demos,
}

def _named_table(where: str, key: str, table) -> tuple[tuple[str, str], ...]:
    if not isinstance(table, dict) or not all(isinstance(v, str) and v for v in table.values()):
        raise _fail(where, key, f"= {table!r}: give a [{key}] table of NAME = \"REPO_ID_OR_PATH\"")
    folder = Path(where).parent
    out = []
    for name, target in table.items():
        local = folder / Path(target).expanduser()
        relative = not Path(target).expanduser().is_absolute() and local.exists()
        out.append(f"{name}={local.resolve() if relative else target}")
    try:
        return parse_named(f"[{key}]", out)
    except ValueError as e:
        raise GridFileError(f"{where}: {e}") from None


def _camera_table(where: str, key: str, table) -> tuple[tuple[str, str], ...]:
    if not isinstance(table, dict) or not all(isinstance(v, str) and v for v in table.values()):
        raise _fail(where, key, f"= {table!r}: give a [{key}] table of POLICY_CAMERA = "
                                "\"DATASET_CAMERA\"")
    try:
        return parse_camera_map(f"[{key}]", ",".join(f"{k}={v}" for k, v in table.items()))
    except ValueError as e:
        raise GridFileError(f"{where}: {e}") from None


def _releases_table(where: str, key: str, table) -> tuple[tuple[str, str], ...]:
    """[releases]: each folder checked now (its content hash), so a tampered pin stops the run
    at start-up instead of measuring on other weights. A list pins releases 0, 1, ... in order."""
    from bench.grid.pinned_release import check_pinned

    def folders(value) -> list | None:
        if isinstance(value, str) and value:
            return [value]
        if isinstance(value, list) and value and all(isinstance(v, str) and v for v in value):
            return value
        return None

    if not isinstance(table, dict) or any(folders(v) is None for v in table.values()):
        raise _fail(where, key, f"= {table!r}: give a [{key}] table of BACKBONE = \"FOLDER\" "
                                "or BACKBONE = [\"FOLDER_0\", \"FOLDER_1\", ...] (one per release)")
    out = []
    for backbone, value in table.items():
        for target in folders(value):
            folder = Path(where).parent / Path(target).expanduser()
            try:
                pinned = check_pinned(backbone, folder, f"{where}: [{key}]")
                out.append((backbone, str(pinned.resolve())))
            except ValueError as e:
                raise GridFileError(str(e)) from None
    return tuple(out)



TABLES: dict[str, Callable] = {"protocol": _protocol, "policies": _named_table,
                               "datasets": _named_table, "camera_map": _camera_table,
                               "releases": _releases_table}
USER_WORLD_TABLES = {"policies": "policies", "datasets": "datasets", "camera_map": "camera_map"}
PROFILE_FIELDS = ("backbones", "suites", "encoders", "seeds", "controls", "control_encoders",
                  "robustness", "releases", "releases_per_backbone", "sim_demos")


def parse_grid(data: dict, info: GridFileInfo) -> GridFile:
    """A GridFile from the TOML document `data` of the file `info` describes."""
    where = info.path
    known = [*KEYS, *(f"[{t}]" for t in TABLES)]
    values = {}
    for key, value in data.items():
        check = KEYS.get(key) or TABLES.get(key)
        if check is None:
            fields = {f.name for f in dataclasses.fields(Protocol)}
            raise _unknown_key(where, key, key, known, "[protocol]" if key in fields else None)
        values[key] = check(where, key, value)
    protocol = values.get("protocol", ())
    _check_release_pins(where, values)
    if "steps" in values and "steps" in dict(protocol):
        raise _fail(where, "steps", "is given twice (top level and [protocol]); keep one")
    return GridFile(info=info, profile=values.get("profile"),
                    grid=tuple((k, values[k]) for k in PROFILE_FIELDS if k in values),
                    steps=values.get("steps"), protocol=protocol,
                    user_world=tuple((field, values[t]) for t, field in USER_WORLD_TABLES.items()
                                     if t in values),
                    pack_grafts=values.get("pack_grafts"))


def _check_release_pins(where: str, values: dict) -> None:
    """Every pinned backbone pins all its releases: a study never mixes pinned releases with
    ones trained on this machine (other kernels give other weights, studies/sim/REBUILD.md)."""
    count = values.get("releases_per_backbone", 1)
    for backbone in dict(values.get("releases", ())):
        pinned = sum(1 for name, _ in values["releases"] if name == backbone)
        if pinned != count:
            raise _fail(where, "[releases]", f"{backbone} pins {pinned} release(s) and "
                        f"releases_per_backbone = {count}; pin one folder per release (a list "
                        "in release order) or set releases_per_backbone to match")


def read_grid_file(path: str | Path) -> GridFile:
    """Read and check a grid file; GridFileError (one line) when it cannot be used."""
    where = str(path)
    try:
        blob = Path(path).read_bytes()
    except FileNotFoundError:
        raise GridFileError(f"--grid {where}: no such file; give the path of a TOML study file "
                            "(schema: bench/grid/gridfile.py)") from None
    except OSError as e:
        raise GridFileError(f"--grid {where}: cannot be read ({e.strerror}); give a readable "
                            "TOML file") from None
    try:
        text = blob.decode("utf-8")
        data = tomllib.loads(text)
    except UnicodeDecodeError:
        raise GridFileError(f"{where}: not UTF-8 text; save the grid file as UTF-8") from None
    except tomllib.TOMLDecodeError as e:
        raise GridFileError(f"{where}: not valid TOML ({' '.join(str(e).split())}); fix the "
                            "file (schema: bench/grid/gridfile.py)") from None
    info = GridFileInfo(path=where, sha256=hashlib.sha256(blob).hexdigest(), text=text)
    return parse_grid(data, info)


def base_profile_of(path: str | Path) -> str | None:
    """The `profile` a grid file names, or None (also when it cannot be read: the plugin then
    reports why). For conftest's offline switch, which runs before any option is parsed."""
    try:
        return tomllib.loads(Path(path).read_text()).get("profile")
    except (OSError, ValueError):
        return None
