"""A corrupt wheel in the add-on's zip (issue 56): enabling the extension stops at once with one line naming the
wheel (``blender_addon.check_wheels``, before any submodule registers), and ``make addon`` refuses to package one
(``build.check_zip`` checks every member's CRC). No bpy needed: both are plain zip checks."""
from __future__ import annotations

import zipfile
from pathlib import Path

import pytest

import blender_addon
from blender_addon import WheelError, check_wheels


def _wheel(path: Path, record: bool = True) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("pkg/__init__.py", "x = 1\n" * 50)
        if record:
            z.writestr("pkg-1.0.dist-info/RECORD", "pkg/__init__.py,,\n")
    return path


def test_enabling_names_a_corrupt_wheel_in_one_line(tmp_path, monkeypatch):
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    _wheel(wheels / "good-1.0-py3-none-any.whl")
    check_wheels(wheels)  # good wheels: nothing to say
    bad = wheels / "trimesh-4.0-py3-none-any.whl"
    bad.write_bytes(_wheel(tmp_path / "t.whl").read_bytes()[:40])  # a truncated download
    with pytest.raises(WheelError) as e:
        check_wheels(wheels)
    line = str(e.value)
    assert "\n" not in line and bad.name in line and "corrupt" in line and "reinstall" in line
    bad.unlink()
    _wheel(wheels / "norecord-1.0-py3-none-any.whl", record=False)
    with pytest.raises(WheelError, match=r"norecord-1.0-py3-none-any.whl is corrupt \(no .dist-info/RECORD"):
        check_wheels(wheels)
    # register() checks first: no submodule (bpy) is touched when a wheel is corrupt
    monkeypatch.setattr(blender_addon, "check_wheels", lambda: check_wheels(wheels))
    monkeypatch.setattr(blender_addon, "_submodules", lambda: pytest.fail("registered despite a corrupt wheel"))
    with pytest.raises(WheelError):
        blender_addon.register()


def test_the_build_refuses_to_package_a_corrupt_wheel(tmp_path):
    from blender_addon.build import BuildError, check_zip
    good = _wheel(tmp_path / "blendsr-0.1.0-py3-none-any.whl").read_bytes()
    flipped = bytearray(good)
    flipped[good.index(b"x = 1")] ^= 0x01  # one bit of a member: the zip opens, its CRC fails
    z = tmp_path / "blendsr-linux-x64.zip"
    with zipfile.ZipFile(z, "w") as out:
        for name in ("__init__.py", "blender_manifest.toml", "worker.py", "external_infer.py", "dataset_ops.py"):
            out.writestr(name, "")
        out.writestr("wheels/blendsr-0.1.0-py3-none-any.whl", good)
        out.writestr("wheels/numpy_stub-1.0-py3-none-any.whl", bytes(flipped))
    with pytest.raises(BuildError, match=r"wheels/numpy_stub-1.0-py3-none-any.whl is corrupt \(pkg/__init__.py "
                                         r"fails its CRC\)"):
        check_zip(z)
