"""Build the installable extension zips with Blender's own extension tooling and validate them.

    python -m blender_addon.build -o dist                      (``make addon``: every platform of PLATFORMS)
    python -m blender_addon.build -o dist --platform linux-x64 (one platform)

Each zip carries the BlendSR library and what Blender's Python lacks as wheels listed in the manifest's ``wheels``
(Blender's mechanism for self-contained extensions: Blender installs them when the extension is enabled), so an
artist installs one file and needs no pip. The wheels are the ``blendsr`` wheel built from this checkout and, from
PyPI (``pip download --only-binary=:all:``), the dependencies of what an artist uses (export, dataset, preview):
``[project].dependencies`` and the ``render`` extra of pyproject.toml, less what Blender ships (bpy and the bpy
wheel's own requirements: numpy, requests, ...), resolved against Blender's numpy. Per-platform wheels make one zip
per platform (``blender_ext.py build --split-platforms``: ``<id>-<version>-<platform>.zip``). torch (the
``train`` extra) is not bundled: the preview runs the ONNX graphs of the shipped networks and non-learned models
(exported here with torch, ``export_graphs``, into the zip's ``onnx/``) through the bundled ``onnxruntime`` wheel
(from the ``export`` extra; left out where PyPI has none for the platform), or torch where the user has it.

Uses ``blender_ext.py`` (its ``build`` and ``validate`` commands), found in the bpy wheel of this Python or given
with ``--blender-ext``; tags are checked against Blender's list of valid tags when it is there. Needs no Blender
binary and does not import bpy. Prints the zips' paths; exit 0, or 2 with a one-line error.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import importlib.util
import io
import json
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from blender_addon import wheel_problem

SOURCE = Path(__file__).resolve().parent
REPO = SOURCE.parent
BL_PKG_CLI = Path("scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")
TAGS = Path("scripts", "modules", "_bpy_internal", "extensions", "tags.py")
#: Blender's Python version (4.2 to 5.0; 5.1 moved to 3.13, hence the manifest's blender_version_max).
PYTHON_VERSION = "3.11"
#: Blender platform -> the pip platform tags its wheels may carry (the oldest system each Blender release runs on;
#: pip does not widen a given tag to older ones, so they are listed).
PLATFORMS = {
    "linux-x64": ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
                  "manylinux2014_x86_64", "manylinux2010_x86_64", "manylinux_2_12_x86_64"),
    "windows-x64": ("win_amd64",),
    "macos-arm64": ("macosx_12_0_arm64", "macosx_11_0_arm64", "macosx_10_9_universal2"),
    "macos-x64": ("macosx_10_15_x86_64", "macosx_10_14_x86_64", "macosx_10_13_x86_64", "macosx_10_9_x86_64",
                  "macosx_10_9_universal2"),
}
#: Bundled where a wheel exists, left out elsewhere: level cameras then use trimesh's own ray engine
#: (gbuffer_export/blender/level_geometry.py), same answers, slower (embreex has no macOS arm64 wheel for 3.11);
#: without onnxruntime the preview needs torch (docs/addon.md).
OPTIONAL = ("embreex", "onnxruntime")
#: The extra whose packages the add-on's export and dataset paths import, besides the base dependencies.
EXTRAS = ("render",)
#: Packages of other extras the zip carries: ONNX Runtime runs the preview's graphs in Blender's Python.
RUNTIME = {"export": ("onnxruntime",)}
WHEEL_CACHE = REPO / "build" / "addon-wheels"
GRAPH_CACHE = REPO / "build" / "addon-onnx"
#: The zip's folder of ONNX graphs (``training.inference.onnx_infer.graph_name``) with their JSON sidecars.
GRAPHS = "onnx"


class BuildError(RuntimeError):
    """The tooling is missing or refused the package; the message is one line."""


def bpy_dir() -> Path | None:
    """The installed bpy package's folder (without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.origin:
        return None
    return Path(spec.origin).parent


def find_blender_ext() -> tuple[Path, Path | None]:
    """(blender_ext.py, tags.py or None) from the bpy wheel: ``bpy/<version>/scripts/...``."""
    root = bpy_dir()
    if root is None:
        raise BuildError("bpy is not installed in this Python; pass --blender-ext PATH/TO/blender_ext.py")
    for ver in sorted((p for p in root.iterdir() if p.is_dir() and p.name[:1].isdigit()), reverse=True):
        ext = ver / BL_PKG_CLI
        if ext.is_file():
            tags = ver / TAGS
            return ext, tags if tags.is_file() else None
    raise BuildError(f"{root}: no {BL_PKG_CLI} inside the bpy package")


def manifest_version(source: Path = SOURCE) -> tuple[str, str]:
    """(id, version) from blender_manifest.toml."""
    import tomllib
    with open(source / "blender_manifest.toml", "rb") as f:
        m = tomllib.load(f)
    return m["id"], m["version"]


def _name(requirement: str) -> str:
    """The normalised project name of a requirement string ('colour-science>=0.4.6' -> 'colour-science')."""
    return re.sub(r"[-_.]+", "-", re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement).group(1)).lower()


def blender_ships() -> tuple[set[str], dict[str, str]]:
    """(names Blender's Python already has, {name: pinned version} for the resolver): bpy and the bpy wheel's own
    requirements (numpy, requests, ...), numpy pinned to the installed one (Blender's)."""
    try:
        reqs = importlib.metadata.requires("bpy") or []
    except importlib.metadata.PackageNotFoundError:
        raise BuildError("bpy is not installed in this Python: its numpy is the one the wheels must match") from None
    names = {"bpy", *(_name(r) for r in reqs if "extra ==" not in r)}
    return names, {"numpy": importlib.metadata.version("numpy")}


def requirements() -> tuple[list[str], list[str]]:
    """(required, optional) requirement strings of the bundled wheels, from pyproject.toml."""
    import tomllib
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    ships, _ = blender_ships()
    extras = project["optional-dependencies"]
    reqs = [*project["dependencies"], *(r for e in EXTRAS for r in extras[e]),
            *(r for e, names in RUNTIME.items() for r in extras[e] if _name(r) in names)]
    reqs = [r for r in reqs if _name(r) not in ships]
    return [r for r in reqs if _name(r) not in OPTIONAL], [r for r in reqs if _name(r) in OPTIONAL]


def _run(cmd: list[str], what: str) -> str:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    out = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0:
        lines = [ln for ln in out.splitlines() if ln.strip() and "is ignored" not in ln]
        raise BuildError(f"{what} failed: {lines[-1] if lines else 'no output'}")
    return out


def _pip_download(platform: str, reqs: list[str], dest: Path, constraints: Path, python: str) -> None:
    cmd = [python, "-m", "pip", "download", "--disable-pip-version-check", "--quiet", "--only-binary=:all:",
           "--python-version", PYTHON_VERSION, "--implementation", "cp", "-c", str(constraints), "-d", str(dest)]
    for tag in PLATFORMS[platform]:
        cmd += ["--platform", tag]
    _run([*cmd, *reqs], f"pip download for {platform} ({', '.join(_name(r) for r in reqs)})")


def cache_lock(cache: Path):
    """One builder at a time per cache folder (``<cache>.lock`` beside it): two builds at once (two test workers,
    two terminals) would otherwise empty the folder under each other."""
    from filelock import FileLock
    cache.parent.mkdir(parents=True, exist_ok=True)
    return FileLock(str(cache) + ".lock")


def dependency_wheels(platform: str, python: str = sys.executable, cache: Path = WHEEL_CACHE) -> list[Path]:
    """The PyPI wheels of ``platform`` (downloaded once into ``cache/<platform>``, kept while the requirements are
    the same), less Blender's own packages."""
    required, optional = requirements()
    ships, pins = blender_ships()
    key = hashlib.sha256(json.dumps([required, optional, sorted(pins.items()), PLATFORMS[platform]]).encode())
    dest = cache / platform
    stamp = dest / "requirements.sha256"
    with cache_lock(dest):
        if not (stamp.is_file() and stamp.read_text() == key.hexdigest()):
            shutil.rmtree(dest, ignore_errors=True)
            dest.mkdir(parents=True)
            constraints = dest / "constraints.txt"
            constraints.write_text("".join(f"{k}=={v}\n" for k, v in pins.items()))
            _pip_download(platform, required, dest, constraints, python)
            for req in optional:
                try:
                    _pip_download(platform, [req], dest, constraints, python)
                except BuildError as exc:
                    print(f"blender_addon.build: {platform}: {_name(req)} left out ({exc})", file=sys.stderr)
            stamp.write_text(key.hexdigest())
    return sorted(w for w in dest.glob("*.whl") if _name(w.name.split("-")[0]) not in ships)


def preview_graphs() -> list[tuple[str, int | None]]:
    """(spec, scale or None for any scale) of every graph the zip carries: the shipped networks and the non-learned
    models, at each scale they take (``gbuffer_export.dataset.buffers.MODEL_SCALES``)."""
    from gbuffer_export.dataset.buffers import MODEL_SCALES
    from training.models import MODELS
    specs = [s for s in MODEL_SCALES if s.startswith("pretrained:") or (s in MODELS and not MODELS[s].learned)]
    return [(s, k) for s in specs for k in (MODEL_SCALES[s] or (None,))]


def graphs_key() -> str:
    """What the graphs depend on: the training package's files (models, weights, export) and torch's version."""
    import torch
    h = hashlib.sha256(torch.__version__.encode())
    for p in sorted((REPO / "training").rglob("*")):
        if p.is_file() and "__pycache__" not in p.parts:
            h.update(str(p.relative_to(REPO)).encode() + b"\0" + p.read_bytes())
    return h.hexdigest()


def export_graphs(cache: Path = GRAPH_CACHE) -> Path:
    """The ONNX graphs of ``preview_graphs`` (``training.inference.export.export_onnx``, each checked against torch),
    exported once into ``cache`` and kept while ``graphs_key`` is the same; the folder."""
    try:
        key = graphs_key()
        from training.inference.export import export_onnx
        from training.inference.loading import load_model
        from training.inference.onnx_infer import graph_name
    except ImportError as exc:
        raise BuildError(f"exporting the preview's ONNX graphs needs blendsr[train,export] in this Python ({exc})"
                         ) from None
    stamp = cache / "training.sha256"
    with cache_lock(cache):
        if stamp.is_file() and stamp.read_text() == key:
            return cache
        shutil.rmtree(cache, ignore_errors=True)
        cache.mkdir(parents=True)
        for spec, scale in preview_graphs():
            path = cache / graph_name(spec, scale)
            report = export_onnx(load_model(spec, scale or 4), path, hr_size=(64, 32))
            if not report["match"]:
                raise BuildError(f"{spec}: ONNX Runtime differs from torch by {report['max_abs_diff']:.3g}")
            sidecar = path.with_suffix(".onnx.json")
            sidecar.write_text(json.dumps({**report, "onnx": path.name}, indent=1) + "\n")  # no build path inside
        stamp.write_text(key)
    return cache


def checkout_copy(dest: Path) -> Path:
    """The checkout's files (git's tracked and untracked-not-ignored ones) copied to ``dest``."""
    try:
        out = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                             capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        raise BuildError(f"{REPO}: not a git checkout (git ls-files failed); the blendsr wheel is built from "
                         "a checkout") from None
    for rel in filter(None, out.decode().split("\0")):
        src = REPO / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


def blendsr_wheel(dest: Path, python: str = sys.executable) -> Path:
    """The ``blendsr`` wheel built from this checkout (no dependencies) into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="blendsr-wheel-") as tmp:
        src = checkout_copy(Path(tmp) / "src")  # setuptools builds in the tree: a copy keeps stale build/ out
        _run([python, "-m", "pip", "wheel", "--disable-pip-version-check", "--quiet", "--no-deps",
              "--no-build-isolation", "-w", tmp, str(src)], "building the blendsr wheel")
        built = sorted(Path(tmp).glob("blendsr-*.whl"))
        if not built:
            raise BuildError(f"{REPO}: pip wheel made no blendsr wheel")
        out = dest / built[0].name
        shutil.copyfile(built[0], out)
    return out


def stage(stage_dir: Path, wheels: list[Path], platforms: list[str], graphs: Path | None = None) -> Path:
    """A copy of the add-on source in ``stage_dir`` with ``wheels/``, the ONNX graphs in ``onnx/`` and the
    manifest's ``wheels`` and ``platforms`` lists (generated here: the wheel file names change with each release)."""
    shutil.rmtree(stage_dir, ignore_errors=True)
    shutil.copytree(SOURCE, stage_dir, ignore=shutil.ignore_patterns("__pycache__", "wheels", GRAPHS))
    if graphs is not None:
        (stage_dir / GRAPHS).mkdir()
        for g in sorted(graphs.glob("*.onnx*")):
            shutil.copyfile(g, stage_dir / GRAPHS / g.name)
    (stage_dir / "wheels").mkdir()
    for w in wheels:
        shutil.copyfile(w, stage_dir / "wheels" / w.name)
    names = sorted({w.name for w in wheels})
    manifest = stage_dir / "blender_manifest.toml"
    text = manifest.read_text()
    if re.search(r"^(wheels|platforms)\s*=", text, re.M):
        raise BuildError(f"{SOURCE / 'blender_manifest.toml'}: 'wheels' and 'platforms' are generated by the build; "
                         "remove them from the source manifest")
    head, sep, tail = text.partition("\n[")
    generated = ("\n# Generated by blender_addon/build.py.\n"
                 f"platforms = [{', '.join(json.dumps(p) for p in platforms)}]\n"
                 "wheels = [\n" + "".join(f'  "./wheels/{n}",\n' for n in names) + "]\n")
    manifest.write_text(head + generated + sep + tail)
    return stage_dir


def build(output_dir: Path, blender_ext: Path | None = None, python: str = sys.executable,
          platforms: list[str] | None = None) -> list[Path]:
    """Build and validate ``<id>-<version>-<platform>.zip`` in ``output_dir`` for each platform (default: all of
    PLATFORMS); return their paths."""
    platforms = list(platforms or PLATFORMS)
    unknown = [p for p in platforms if p not in PLATFORMS]
    if unknown:
        raise BuildError(f"--platform {unknown[0]}: not one of {', '.join(PLATFORMS)}")
    tags = None
    if blender_ext is None:
        blender_ext, tags = find_blender_ext()
    tag_args = [f"--valid-tags={tags}"] if tags else []
    output_dir = Path(output_dir).resolve()
    output_dir.mkdir(parents=True, exist_ok=True)
    pkg_id, version = manifest_version()
    tool = Path(blender_ext).name
    _run([python, str(blender_ext), "validate", *tag_args, str(SOURCE)], f"{tool} validate")
    with tempfile.TemporaryDirectory(prefix="blendsr-addon-") as tmp:
        wheels = [blendsr_wheel(Path(tmp) / "own", python)]
        for p in platforms:
            wheels += dependency_wheels(p, python)
        src = stage(Path(tmp) / "src", wheels, platforms, export_graphs())
        zip_base = output_dir / f"{pkg_id}-{version}.zip"
        zips = [output_dir / f"{pkg_id}-{version}-{p.replace('-', '_')}.zip" for p in platforms]
        for z in zips:
            z.unlink(missing_ok=True)
        _run([python, str(blender_ext), "build", "--source-dir", str(src), "--output-filepath", str(zip_base),
              "--split-platforms", *tag_args], f"{tool} build")
    for z in zips:
        _run([python, str(blender_ext), "validate", *tag_args, str(z)], f"{tool} validate {z.name}")
        check_zip(z)
    return zips


def check_zip(zip_path: Path) -> None:
    """The zip holds the add-on's modules and the blendsr wheel its manifest lists."""
    with zipfile.ZipFile(zip_path) as z:
        names = set(z.namelist())
    for required in ("__init__.py", "blender_manifest.toml", "worker.py", "external_infer.py", "dataset_ops.py"):
        if required not in names:
            raise BuildError(f"{zip_path}: {required} is missing from the package")
    if not any(n.startswith("wheels/blendsr-") for n in names):
        raise BuildError(f"{zip_path}: the blendsr wheel is missing from the package")
    with zipfile.ZipFile(zip_path) as z:
        for name in sorted(n for n in names if n.startswith("wheels/") and n.endswith(".whl")):
            problem = wheel_problem(io.BytesIO(z.read(name)))
            if not problem:
                with zipfile.ZipFile(io.BytesIO(z.read(name))) as w:
                    bad = w.testzip()
                problem = f"{bad} fails its CRC" if bad else ""
            if problem:
                raise BuildError(f"{zip_path}: {name} is corrupt ({problem}); delete it from {WHEEL_CACHE} and "
                                 "build again")
    for graph in ("pretrained_fusesr-l_x4.onnx", "bilinear_xany.onnx"):
        if f"{GRAPHS}/{graph}" not in names or f"{GRAPHS}/{graph}.json" not in names:
            raise BuildError(f"{zip_path}: the preview's graph {GRAPHS}/{graph} (or its .json) is missing")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m blender_addon.build", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("-o", "--output", type=Path, default=Path("dist"), help="folder for the zips")
    p.add_argument("--platform", action="append", choices=list(PLATFORMS), default=None,
                   help="build for this Blender platform only (repeatable; default: all)")
    p.add_argument("--blender-ext", type=Path, default=None,
                   help="path of blender_ext.py (default: the one inside this Python's bpy package)")
    a = p.parse_args(argv)
    try:
        paths = build(a.output, a.blender_ext, platforms=a.platform)
    except BuildError as exc:
        print(f"blender_addon.build: error: {exc}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
