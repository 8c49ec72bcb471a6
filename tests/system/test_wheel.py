"""The install the README documents works: a wheel built from the checkout installs into a fresh virtual environment,
``blendsr --help`` runs from it, and it renders and validates a tiny clip of the built-in scene.

Design (about 15 s on 2 cores; marked ``bpy`` and ``wheel``, deselect with ``-m 'not wheel'``):

- the wheel is built by ``pip wheel --no-deps --no-build-isolation`` from a copy of the files git does not ignore
  (a build in the checkout would leave ``build/`` and ``*.egg-info`` there): what a user's build of a clone packs;
- the environment is a fresh ``python -m venv --without-pip``; the wheel is installed into it by this interpreter's
  pip (``pip --python VENV``, ``--no-deps --no-index``): nothing is downloaded;
- the heavy dependencies (bpy is 820 MB) are not reinstalled: one ``.pth`` line appends this interpreter's
  site-packages to the new environment's ``sys.path``, *after* the environment's own site-packages. A path line in a
  ``.pth`` file is not a site directory, so the ``.pth`` files there (among them a development checkout's editable
  install of blendsr) are not run: ``gbuffer_export`` and blendsr's metadata (its entry points) come from the wheel,
  which the test asserts, and the versions of the core's and the ``[render]`` extra's dependencies are checked
  against the wheel's ``Requires-Dist``.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.conftest import REPO, requires_bpy

pytestmark = [pytest.mark.bpy, pytest.mark.wheel, requires_bpy, pytest.mark.timeout(300)]


def _tracked_copy(dest: Path) -> Path:
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                           capture_output=True, check=True).stdout
    names = [n for n in files.decode().split("\0") if n]
    if not names:
        pytest.skip("not a git checkout")
    for name in names:
        src = REPO / name
        if src.is_file() and not name.startswith("tests/"):
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    return dest


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    src = _tracked_copy(tmp / "src")
    dist = tmp / "dist"
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-q", "-w", str(dist), str(src)], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    wheels = list(dist.glob("blendsr-*.whl"))
    assert len(wheels) == 1, wheels
    env_dir = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True, timeout=120)
    py = env_dir / "bin" / "python"
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
                           "-q", str(wheels[0])], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    (site / "zz_heavy_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env["PATH"] = f"{env_dir / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return {"dir": env_dir, "py": py, "site": site, "env": env, "tmp": tmp, "wheel": wheels[0]}


def _run(venv, *args, timeout=240):
    return subprocess.run([*map(str, args)], capture_output=True, text=True, cwd=venv["tmp"], env=venv["env"],
                          timeout=timeout)


def test_the_wheel_is_what_runs_and_its_dependencies_are_met(venv):
    code = ("import json, gbuffer_export, training\n"
            "from importlib import metadata\n"
            "from packaging.requirements import Requirement\n"
            "d = metadata.distribution('blendsr')\n"
            "unmet = []\n"
            "for r in map(Requirement, d.requires or []):\n"
            "    if r.marker and not r.marker.evaluate({'extra': 'render'}):  # what the render below needs\n"
            "        continue\n"
            "    try:\n"
            "        v = metadata.version(r.name)\n"
            "    except metadata.PackageNotFoundError:\n"
            "        v = None\n"
            "    if v is None or not r.specifier.contains(v, prereleases=True):\n"
            "        unmet.append(f'{r} (installed: {v})')\n"
            "print(json.dumps({'core': gbuffer_export.__file__, 'training': training.__file__,\n"
            "                  'dist': str(d.locate_file('')), 'unmet': unmet,\n"
            "                  'weights': sorted(p.name for p in (metadata.files('blendsr') or [])\n"
            "                                    if p.suffix in ('.safetensors', '.toml'))}))\n")
    proc = _run(venv, venv["py"], "-c", code)
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads(proc.stdout)
    for key in ("core", "training", "dist"):
        assert Path(info[key]).resolve().is_relative_to(venv["site"].resolve()), info
    assert not info["unmet"], info["unmet"]
    assert "fusesr_x4.safetensors" in info["weights"] and "blender_manifest.toml" in info["weights"]


def test_blendsr_help_and_a_tiny_render_from_the_wheel(venv):
    blendsr = venv["dir"] / "bin" / "blendsr"
    proc = _run(venv, blendsr, "--help")
    assert proc.returncode == 0, proc.stderr[-3000:]
    for cmd in ("render", "dataset", "train", "export"):
        assert f"\n    {cmd} " in proc.stdout
    clip = venv["tmp"] / "clip"
    proc = _run(venv, blendsr, "render", "-o", clip, "--hr-size", "32x16", "--frames", "1:1", "--hr-spp", "2",
                "--lr-spp", "1", "--gbuffer-spp", "1", "--threads", "1", "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    proc = _run(venv, blendsr, "validate", clip)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
