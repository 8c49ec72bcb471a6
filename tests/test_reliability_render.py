"""Reliability of rendering: absurd sizes are refused up front; the same command gives bit-identical EXRs."""
import pytest
from conftest import requires_bpy, run_cli

from gbuffer_export.conventions import DEFAULT_BUFFERS
from gbuffer_export.resources import ResourceError, check_render_resources, estimate_render


def test_estimate_grows_with_size_frames_and_buffers():
    a = estimate_render((640, 360), 4, DEFAULT_BUFFERS, 10)
    assert estimate_render((1280, 720), 4, DEFAULT_BUFFERS, 10).memory_bytes > a.memory_bytes
    assert estimate_render((640, 360), 4, DEFAULT_BUFFERS, 20).disk_bytes > a.disk_bytes
    assert estimate_render((640, 360), 4, ("radiance",), 10).disk_bytes < a.disk_bytes
    # 640x360 with the default buffers (19 channels): 10 frames of (230400 + 14400) px * 21 * 4 B + one temp EXR
    assert a.disk_bytes == 10 * (230400 + 14400) * 19 * 4 + 230400 * 40 * 4


def test_resources_refused_with_needed_and_available(tmp_path):
    with pytest.raises(ResourceError, match=r"needs about .* of memory and 1 GB is available"):
        check_render_resources((4000, 4000), 4, DEFAULT_BUFFERS, 1, tmp_path, memory=10**9, disk=10**12)
    with pytest.raises(ResourceError, match=r"100 frame\(s\) .* need up to .* of disk and 1 MB is free"):
        check_render_resources((640, 360), 4, DEFAULT_BUFFERS, 100, tmp_path, memory=10**11, disk=10**6)
    est = check_render_resources((64, 36), 4, DEFAULT_BUFFERS, 4, tmp_path / "new" / "clip")  # this machine
    assert est.frames == 4 and est.memory_bytes < 2**31


@requires_bpy
def test_absurd_render_size_is_refused_in_one_line_before_rendering(tmp_path):
    out = tmp_path / "o"
    proc = run_cli("render", "-o", out, "--hr-size", "100000x100000", "--frames", "1:1", "--no-progress",
                   timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "of memory" in lines[0] and "is available" in lines[0], lines
    assert not out.exists()
