"""A non-editable install holds every module: the wheels pip builds from pyproject.toml (graftbench
and the LeRobot plugin) are compared with the source trees. An editable install hides a stale
package list (it maps whole folders), which is how bench.screen went missing from the wheel."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from ondisk.paths import REPO_ROOT

PLUGIN = REPO_ROOT / "plugins" / "lerobot_policy_graft"
# (project folder, its top-level packages): every .py under them must be in its wheel.
PROJECTS = {"graftbench": (REPO_ROOT, ("bench", "backbones", "encoders", "ondisk")),
            "lerobot_policy_graft": (PLUGIN, ("lerobot_policy_graft", "graftcore"))}


SHIPPED = "bench/resources/shipped/"  # data a wheel must hold too: the shipped tiny releases


def _source_modules(root: Path, packages: tuple[str, ...]) -> set[str]:
    return {p.relative_to(root).as_posix() for pkg in packages for p in (root / pkg).rglob("*")
            if "__pycache__" not in p.parts and p.is_file()
            and (p.suffix == ".py" or SHIPPED in p.relative_to(root).as_posix())}


def _wheel_modules(root: Path, packages: tuple[str, ...], out: Path) -> set[str]:
    # Built from a clean copy: setuptools reuses a build/ folder left in the tree, whose stale
    # files would hide a missing package. --no-build-isolation: no registry needed.
    src = out / "src"
    for pkg in packages:
        shutil.copytree(root / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        if (root / name).exists():
            shutil.copy(root / name, src / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(out), str(src)], check=True, capture_output=True, text=True)
    (wheel,) = out.glob("*.whl")
    with zipfile.ZipFile(wheel) as z:
        return {name for name in z.namelist() if name.endswith(".py") or SHIPPED in name}


@pytest.mark.parametrize("project", sorted(PROJECTS))
def test_wheel_holds_every_module_and_nothing_else(project, tmp_path):
    root, packages = PROJECTS[project]
    in_wheel = _wheel_modules(root, packages, tmp_path)
    in_source = _source_modules(root, packages)
    assert in_source - in_wheel == set(), f"{project}: modules or shipped files not in the wheel"
    assert in_wheel - in_source == set(), f"{project}: the wheel holds modules outside its packages"
