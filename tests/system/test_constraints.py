"""constraints.txt (the versions make setup installs) agrees with pyproject.toml's ranges and the Makefile's torch."""
from __future__ import annotations

import importlib.metadata as md
import re
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[2]


def _pins() -> dict[str, str]:
    pins = {}
    for n, line in enumerate((ROOT / "constraints.txt").read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([0-9][A-Za-z0-9.+!-]*)", line.strip())
        assert m, f"constraints.txt:{n}: not 'name==version': {line!r}"
        name = canonicalize_name(m.group(1))
        assert name not in pins, f"constraints.txt:{n}: {name} pinned twice"
        pins[name] = m.group(2)
    return pins


def _requirements() -> list[Requirement]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        reqs += [r for r in extra if not r.startswith("blendsr[")]
    return [Requirement(r) for r in reqs]


def _torch_version() -> str:
    m = re.search(r"^TORCH_VERSION := (\S+)$", (ROOT / "Makefile").read_text(), re.M)
    assert m, "Makefile: no TORCH_VERSION"
    return m.group(1)


def test_every_pin_lies_inside_the_range_pyproject_asks_for():
    pins, outside = _pins(), []
    for req in _requirements():
        version = pins.get(canonicalize_name(req.name))
        if version is not None and not req.specifier.contains(version, prereleases=True):
            outside.append(f"{req.name}=={version} (pyproject: {req})")
    assert not outside, outside
    # the pins that matter most are there: bpy's numpy<2 is why the file exists
    assert pins["bpy"] == "5.0.1" and pins["numpy"].startswith("1.")


def test_torch_and_its_build_bound_packages_are_left_to_the_makefile():
    pins = _pins()
    assert not [n for n in pins if n in ("torch", "triton") or n.startswith("nvidia-")], sorted(pins)


def test_the_pinned_torchvision_is_built_for_the_makefiles_torch():
    pinned = _pins().get("torchvision")
    if pinned is None:
        pytest.skip("constraints.txt pins no torchvision")
    try:
        installed = md.version("torchvision")
    except md.PackageNotFoundError:
        pytest.skip("torchvision is not installed (the [video] extra)")
    if installed != pinned:
        pytest.skip(f"torchvision {installed} installed, {pinned} pinned: this environment was not made by make setup")
    wants = [Requirement(r) for r in md.requires("torchvision") or [] if r.startswith("torch")]
    wants = [r for r in wants if canonicalize_name(r.name) == "torch"]
    assert wants and all(r.specifier.contains(_torch_version()) for r in wants), (wants, _torch_version())
