"""Issue 56 item 2: a scene whose imported geometry is empty (vertices, no faces), non-finite (every vertex NaN),
degenerate (zero extent) or absurdly large (a 1e7 m level) is refused before rendering, in one line naming the file,
exit 2 (it rendered a clip of sky only, or one that failed validate, with exit 0)."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import requires_bpy
from gbuffer_export.scene_geometry import MAX_EXTENT_UNITS, GeometrySummary, geometry_problem


def _summary(points, faces, other=False) -> GeometrySummary:
    p = np.asarray(points, float)
    ok = np.isfinite(p).all(axis=1)
    lo = tuple(p[ok].min(axis=0)) if ok.any() else None
    hi = tuple(p[ok].max(axis=0)) if ok.any() else None
    return GeometrySummary(len(p), faces, int((~ok).sum()), lo, hi, 1.0, other)


TRI = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]


@pytest.mark.parametrize("summary, words", [
    (_summary(np.zeros((0, 3)), 0), "no geometry"),
    (_summary(TRI, 0), "3 vertices but no faces"),
    (_summary(np.full((3, 3), np.nan), 1), "every one of its 3 vertices is NaN or infinite"),
    (_summary(np.zeros((3, 3)), 1), "zero extent"),
    (_summary(np.full((3, 3), 5e6) + np.eye(3), 1), "absurdly large"),
    (_summary(np.array(TRI) * 2e7, 1), "absurdly large"),
])
def test_geometry_that_renders_nothing_is_a_problem(summary, words):
    assert words in geometry_problem(summary)


@pytest.mark.parametrize("summary", [
    _summary(TRI, 1),  # one triangle
    _summary(np.array(TRI) * 0.5 * MAX_EXTENT_UNITS, 1),  # a large, but not absurd, level
    _summary([[0, 0, 0], [1, 0, 0], [np.nan, 0, 0]], 1),  # a stray NaN vertex: Cycles renders the rest
    _summary(np.zeros((0, 3)), 0, other=True),  # only curves or text: not measured, rendered as they are
])
def test_geometry_that_renders_is_no_problem(summary):
    assert geometry_problem(summary) is None


def nan_stl(path, triangles: int = 2):
    """A binary STL whose every vertex is NaN (Blender's OBJ importer reads 'nan' as 0)."""
    import struct
    tri = struct.pack("<12fH", *([0.0] * 3 + [float("nan")] * 9), 0)
    path.write_bytes(b"\0" * 80 + struct.pack("<I", triangles) + tri * triangles)
    return path


#: case -> (file name, its text or a writer, the words of the refusal)
OBJ_CASES = {
    "no-faces": ("no-faces.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n", "4 vertices but no faces"),
    # Blender's STL importer turns NaN vertices into one point at the origin: refused as zero extent
    "nan": ("nan.stl", nan_stl, "zero extent"),
    "zero-extent": ("zero.obj", "v 2 2 2\nv 2 2 2\nv 2 2 2\nf 1 2 3\n", "zero extent"),
    "1e7-m": ("big.obj", "v 0 0 0\nv 1e7 0 0\nv 0 1e7 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n", "absurdly large"),
}


@pytest.fixture(scope="module")
def refusals(tmp_path_factory):
    """Each case of ``OBJ_CASES`` written and rendered (``blendsr render``, the commands in one process:
    ``cli_batch``); returns case -> (scene, output folder, completed process)."""
    from tests.render.cli_batch import run_cli_batch
    d = tmp_path_factory.mktemp("geometry")
    scenes = {}
    for case, (name, text, _) in OBJ_CASES.items():
        scene = scenes[case] = d / case / name
        scene.parent.mkdir()
        scene.write_text(text) if isinstance(text, str) else text(scene)
    procs = run_cli_batch(*[["render", scene, "-o", scene.parent / "out", "--camera-path", "orbit", "--light", "sky",
                             "--hr-size", "32x32", "--frames", "1:1", "--hr-spp", "1", "--lr-spp", "1", "--threads",
                             "1", "--no-progress"] for scene in scenes.values()], timeout=300)
    return {case: (scene, scene.parent / "out", proc) for (case, scene), proc in zip(scenes.items(), procs)}


@requires_bpy
@pytest.mark.bpy
@pytest.mark.parametrize("case", sorted(OBJ_CASES))
def test_render_refuses_a_scene_with_nothing_to_render_before_rendering(refusals, case):
    scene, out, proc = refusals[case]
    words = OBJ_CASES[case][2]
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.startswith("blendsr: error")]
    assert len(lines) == 1 and lines[0].startswith(f"blendsr: error: {scene}: ") and words in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr and not (out / "manifest.json").exists()
