"""``python -m blender_addon.build``: the zip built and validated with Blender's extension tooling installs into the
bpy module as the extension ``bl_ext.user_default.blendsr``, registers its operators, and previews with inference
in an external Python (the path used when Blender's Python has no torch)."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile

import pytest

from tests.conftest import ENV, REPO, requires_bpy

pytestmark = [pytest.mark.bpy, requires_bpy]

INSTALL = r'''
import json, sys
import bpy, addon_utils
zip_path, clip_copy = sys.argv[1], sys.argv[2]
res = bpy.ops.extensions.package_install_files(repo="user_default", filepath=zip_path, enable_on_install=True)
mod = "bl_ext.user_default.blendsr"
out = {"install": sorted(res), "enabled": mod in bpy.context.preferences.addons,
       "ops": [hasattr(bpy.ops.blendsr, "export_dataset"), hasattr(bpy.ops.blendsr, "preview_upscale")],
       "panels": [hasattr(bpy.types, "BLENDSR_PT_output"), hasattr(bpy.types, "BLENDSR_PT_view3d")],
       "module_file": sys.modules[mod].__file__, "lib_imported": "gbuffer_export" in sys.modules}

# a tiny scene, then a preview whose inference runs in an external Python
bpy.ops.mesh.primitive_plane_add(size=10)
bpy.ops.mesh.primitive_uv_sphere_add(location=(0, 0, 1))
bpy.ops.object.camera_add(location=(0, -8, 2.2), rotation=(1.45, 0, 0))
sc = bpy.context.scene
sc.camera = bpy.context.object
sc.frame_start, sc.frame_end, sc.frame_current = 1, 1, 1
s = sc.blendsr
s.use_scene_resolution = False
s.hr_width, s.hr_height, s.hr_spp, s.lr_spp, s.gbuffer_spp = 64, 32, 4, 2, 1
s.with_reference = True
prefs = bpy.context.preferences.addons[mod].preferences
prefs.inference = "EXTERNAL"
prefs.python_path = sys.executable
out["preview"] = sorted(bpy.ops.blendsr.preview_upscale())
out["images"] = {n: list(bpy.data.images[n].size) for n in ("BlendSR SR", "BlendSR bilinear", "BlendSR reference")}
out["ms"], out["psnr"], out["metric"] = s.preview_ms, s.preview_psnr, s.preview_metric
import shutil
shutil.copytree(s.preview_clip, clip_copy)
addon_utils.disable(mod)
out["after_disable"] = [hasattr(bpy.types.Scene, "blendsr"), hasattr(bpy.types, "BLENDSR_PT_output")]
print("RESULT " + json.dumps(out))
'''


@pytest.mark.torch
def test_build_validate_install_and_external_preview(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "blender_addon.build", "-o", str(tmp_path / "dist")], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    zip_path = tmp_path / "dist" / "blendsr-0.1.0.zip"
    assert proc.stdout.strip() == str(zip_path)
    with zipfile.ZipFile(zip_path) as z:
        names = set(z.namelist())
    assert {"blender_manifest.toml", "__init__.py", "operators.py", "panels.py", "props.py", "worker.py",
            "external_infer.py", "render_keys.py", "render_keys.json"} <= names
    assert not {"build.py", "calibrate.py"} & names and not any("__pycache__" in n for n in names)

    env = dict(ENV, BLENDER_USER_RESOURCES=str(tmp_path / "blender_user"))
    proc = subprocess.run([sys.executable, "-c", INSTALL, str(zip_path), str(tmp_path / "preview_clip")],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    r = json.loads(lines[-1][7:])
    assert r["install"] == ["FINISHED"] and r["enabled"] and r["ops"] == [True, True] and r["panels"] == [True, True]
    assert r["module_file"].startswith(str(tmp_path / "blender_user" / "extensions" / "user_default" / "blendsr"))
    assert not r["lib_imported"], "enabling the extension must not import the library"
    assert r["preview"] == ["FINISHED"]
    assert all(v == [64, 32] for v in r["images"].values()), r["images"]
    assert r["ms"] > 0 and 10 < r["psnr"] < 100 and "psnr_tm" in r["metric"]
    assert r["after_disable"] == [False, False]

    # the PSNR reported by the external Python is the evaluation's on the preview clip's images
    import numpy as np
    from gbuffer_export import open_clip
    from training.inference import load_model, upscale_frame
    from training.metrics import psnr_tm
    clip = open_clip(tmp_path / "preview_clip")
    o = upscale_frame(load_model("pretrained:fusesr-l", 4), clip, 1)  # the preview's default model
    assert r["psnr"] == pytest.approx(psnr_tm(o["sr"], o["reference"]), abs=1e-4)
    assert np.isfinite(o["sr"]).all()
