"""Build the installable extension zip with Blender's own extension tooling and validate it.

    python -m blender_addon.build -o dist        (``make addon``)

Uses ``blender_ext.py`` (its ``build`` and ``validate`` commands), found in the bpy wheel of this Python or given
with ``--blender-ext``; tags are checked against Blender's list of valid tags when it is there. Needs no Blender
binary and does not import bpy. Prints the zip's path; exit 0, or 2 with a one-line error.
"""
from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import zipfile
from pathlib import Path

SOURCE = Path(__file__).resolve().parent
BL_PKG_CLI = Path("scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")
TAGS = Path("scripts", "modules", "_bpy_internal", "extensions", "tags.py")


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


def _run(cmd: list[str]) -> str:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    out = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0:
        lines = [ln for ln in out.splitlines() if ln.strip()]
        raise BuildError(f"{Path(cmd[2]).name} {cmd[3]} failed: {lines[-1] if lines else 'no output'}")
    return out


def build(output_dir: Path, blender_ext: Path | None = None, python: str = sys.executable) -> Path:
    """Validate the source, build ``<id>-<version>.zip`` in ``output_dir``, validate the zip; return its path."""
    tags = None
    if blender_ext is None:
        blender_ext, tags = find_blender_ext()
    tag_args = [f"--valid-tags={tags}"] if tags else []
    output_dir = Path(output_dir).resolve()
    output_dir.mkdir(parents=True, exist_ok=True)
    pkg_id, version = manifest_version()
    zip_path = output_dir / f"{pkg_id}-{version}.zip"
    if zip_path.exists():
        zip_path.unlink()
    _run([python, str(blender_ext), "validate", *tag_args, str(SOURCE)])
    _run([python, str(blender_ext), "build", "--source-dir", str(SOURCE), "--output-filepath", str(zip_path),
          *tag_args])
    _run([python, str(blender_ext), "validate", *tag_args, str(zip_path)])
    with zipfile.ZipFile(zip_path) as z:
        names = set(z.namelist())
    for required in ("__init__.py", "blender_manifest.toml", "worker.py", "external_infer.py", "dataset_ops.py"):
        if required not in names:
            raise BuildError(f"{zip_path}: {required} is missing from the package")
    return zip_path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m blender_addon.build", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("-o", "--output", type=Path, default=Path("dist"), help="folder for the zip")
    p.add_argument("--blender-ext", type=Path, default=None,
                   help="path of blender_ext.py (default: the one inside this Python's bpy package)")
    a = p.parse_args(argv)
    try:
        path = build(a.output, a.blender_ext)
    except BuildError as exc:
        print(f"blender_addon.build: error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
