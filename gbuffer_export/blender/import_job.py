"""The import child process (bpy layer): ``python -m gbuffer_export.blender.import_job SCENE OUT_DIR``.

Started by ``gbuffer_export.import_sandbox`` (read it for the limits): caps its own memory, dies with its parent,
checks the scene's references (``scene_refs``), imports the scene (``importers.import_level``), makes its paths
absolute and saves ``OUT_DIR/level.blend``; ``OUT_DIR/result.json`` holds the manifest's report, or the one-line
error of a refusal (exit 2). With ``--asset`` it imports a dataset asset into an empty scene as a clip's job does
(``assets.import_asset``), saves nothing and reports ``{"objects": N}`` (``blendsr dataset --dry-run``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def _write(out_dir: Path, payload: dict) -> None:
    tmp = out_dir / "result.json.tmp"
    tmp.write_text(json.dumps(payload))
    os.replace(tmp, out_dir / "result.json")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="import_job")
    p.add_argument("scene", type=Path)
    p.add_argument("out_dir", type=Path)
    p.add_argument("--memory", type=int, required=True)
    p.add_argument("--parent", type=int, required=True)
    p.add_argument("--allow-read", action="append", default=[])
    p.add_argument("--asset", action="store_true", help="import a dataset asset, save nothing")
    a = p.parse_args(argv)
    from ..import_sandbox import set_memory_limit
    from ..locks import die_with_parent
    die_with_parent(a.parent)
    set_memory_limit(a.memory)
    from ..errors import BlendSRError
    try:
        report = _import_asset(a.scene) if a.asset else _import_level(a.scene, a.out_dir, a.allow_read)
    except BlendSRError as exc:
        _write(a.out_dir, {"error": str(exc).splitlines()[0]})
        return 2
    except MemoryError:
        _write(a.out_dir, {"error": f"{a.scene}: the importer ran out of its {a.memory / 2**30:.3g} GiB import "
                                    "memory limit (BLENDSR_IMPORT_MEMORY_GB); stopped"})
        return 2
    _write(a.out_dir, {"report": report})
    return 0


def _import_level(scene: Path, out_dir: Path, allow_read) -> dict:
    from ..scene_refs import check_scene_refs
    outside = check_scene_refs(scene, allow_read)
    from .importers import import_level
    report = import_level(scene, allow_read)
    report["read_outside"] = sorted(set(outside) | set(report.get("read_outside", [])))
    if not report["read_outside"]:
        del report["read_outside"]
    save_level(out_dir / "level.blend")
    return report


def _import_asset(asset: Path) -> dict:
    """A dataset asset imported into an empty scene as a clip's job imports it (its references checked there)."""
    import bpy
    from .assets import import_asset
    from .importers import _importer_output
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with _importer_output(asset.name):
        return {"objects": len(import_asset(bpy.context.scene, asset))}


def save_level(path: Path) -> None:
    """Save the imported scene as ``path`` with every external path absolute (the renderer opens it from there)."""
    import bpy
    from .fds import captured
    with captured():
        try:
            bpy.ops.file.make_paths_absolute()
        except RuntimeError:  # nothing relative
            pass
        bpy.ops.wm.save_as_mainfile(filepath=str(path), relative_remap=False, compress=False, copy=True)


if __name__ == "__main__":
    sys.exit(main())
