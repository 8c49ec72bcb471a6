"""The one resolver of a scene file's references (gbuffer_export/scene_refs.py, blend_refs.py; issue 56)."""
import json
import os
import struct

import pytest

from gbuffer_export.scene_refs import SceneRefError, check_scene_refs


def _gltf(folder, buffer_uri="data:application/octet-stream;base64,AAAA", image_uri=None, count=1):
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"asset": {"version": "2.0"}, "buffers": [{"byteLength": 12, "uri": buffer_uri}],
           "bufferViews": [{"buffer": 0, "byteLength": 12}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": count, "type": "VEC3"}]}
    if image_uri:
        doc["images"] = [{"uri": image_uri}]
    p = folder / "s.gltf"
    p.write_text(json.dumps(doc))
    return p


def _glb(folder, doc):
    folder.mkdir(parents=True, exist_ok=True)
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    p = folder / "s.glb"
    p.write_bytes(b"glTF" + struct.pack("<II", 2, 20 + len(js)) + struct.pack("<I4s", len(js), b"JSON") + js)
    return p


def test_gltf_inside_and_data_uris_pass(tmp_path):
    (tmp_path / "lvl").mkdir()
    (tmp_path / "lvl" / "buf.bin").write_bytes(b"\0" * 12)
    assert check_scene_refs(_gltf(tmp_path / "lvl", "buf.bin")) == []
    assert check_scene_refs(_gltf(tmp_path / "lvl2")) == []
    assert check_scene_refs(_gltf(tmp_path / "lvl3", image_uri="missing%20tex.png")) == []  # missing: neutral


@pytest.mark.parametrize("uri", ["../../../../etc/passwd", "/etc/passwd", "/dev/zero", "..%2F..%2Fsecret.bin",
                                 "file:///etc/passwd", "..\\..\\secret.bin"])
def test_gltf_buffer_outside_is_refused_naming_file_and_reference(tmp_path, uri):
    p = _gltf(tmp_path / "a" / "lvl", uri)
    # a buffer is refused even when nothing is there (the import would fail anyway)
    with pytest.raises(SceneRefError) as e:
        check_scene_refs(p)
    msg = str(e.value)
    assert str(p) in msg and "buffers[0]" in msg and repr(uri)[1:-1] in msg and "\n" not in msg


def test_a_backslash_uri_is_the_path_blenders_importer_opens(tmp_path):
    """io_scene_gltf2 reads a URI's backslashes as separators: ``..\\secret.bin`` is the file beside the folder,
    which is refused even when it exists (an unchecked name would let the importer read it)."""
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "secret.bin").write_bytes(b"\0" * 12)
    with pytest.raises(SceneRefError, match="buffers\\[0\\]"):
        check_scene_refs(_gltf(tmp_path / "a" / "lvl", "..\\secret.bin"))
    (tmp_path / "a" / "lvl" / "sub").mkdir()
    (tmp_path / "a" / "lvl" / "sub" / "b.bin").write_bytes(b"\0" * 12)
    assert check_scene_refs(_gltf(tmp_path / "a" / "lvl", "sub\\b.bin")) == []


def test_links_fifos_and_folders_are_refused(tmp_path):
    out = tmp_path / "outside.png"
    out.write_bytes(b"x")
    lvl = tmp_path / "lvl"
    lvl.mkdir()
    os.symlink(out, lvl / "tex.png")
    with pytest.raises(SceneRefError, match="a link to"):
        check_scene_refs(_gltf(lvl, image_uri="tex.png"))
    os.mkfifo(lvl / "pipe.bin")
    with pytest.raises(SceneRefError, match="not a regular file"):
        check_scene_refs(_gltf(lvl, "pipe.bin"))
    (lvl / "inner.png").write_bytes(b"x")
    os.symlink(lvl / "inner.png", lvl / "alias.png")  # a link that stays inside is fine
    assert check_scene_refs(_gltf(lvl, image_uri="alias.png")) == []
    (tmp_path / "s.glb").mkdir()
    with pytest.raises(SceneRefError, match="is a folder, not a scene file"):
        check_scene_refs(tmp_path / "s.glb")


def test_allowed_folder_is_read_and_listed(tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "red.png").write_bytes(b"x")
    p = _gltf(tmp_path / "lvl", image_uri="../theirs/red.png")
    with pytest.raises(SceneRefError, match="--allow-read"):
        check_scene_refs(p)
    assert check_scene_refs(p, [theirs]) == [str((theirs / "red.png").resolve())]


def test_accessor_count_beyond_its_view_is_named(tmp_path):
    doc = json.loads(_gltf(tmp_path / "g", count=10**9).read_text())
    with pytest.raises(SceneRefError, match=r"accessors\[0\] count 1000000000 needs 12000000000 bytes"):
        check_scene_refs(tmp_path / "g" / "s.gltf")
    with pytest.raises(SceneRefError, match=r"s\.glb: glTF accessors\[0\] count 1000000000"):
        check_scene_refs(_glb(tmp_path / "b", doc))
    doc["accessors"][0].update(count=1)
    assert check_scene_refs(_glb(tmp_path / "b", doc)) == []


def _outside_file(folder, ref):
    """Create the file a relative reference names outside the scene's folder (one that exists is refused; a missing
    one reads nothing and is left to the importer)."""
    if not ref.startswith(("/", "file:")):
        target = (folder / ref).resolve()
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(b"secret")


def _obj(folder, line):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "l.mtl").write_text(f"newmtl m\n{line}\n")
    p = folder / "l.obj"
    p.write_text("mtllib l.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return p


@pytest.mark.parametrize("line", ["map_Kd ../../../etc/shadow", "map_Kd -s 1 1 1 -clamp on /etc/passwd",
                                  "bump -bm 0.5 ../../x.png", "disp /etc/hosts", "MAP_KA ../../a.png"])
def test_mtl_maps_outside_are_refused(tmp_path, line):
    p = _obj(tmp_path / "a" / "b", line)
    _outside_file(p.parent, line.split()[-1])
    with pytest.raises(SceneRefError) as e:
        check_scene_refs(p)
    assert "l.obj: l.mtl: " + line.split()[0] in str(e.value)


def test_mtl_maps_inside_and_mtllib_outside(tmp_path):
    assert check_scene_refs(_obj(tmp_path / "o", "map_Kd -o 0 0 0 tex/a b.png\nmap_Bump n.png")) == []
    p = tmp_path / "o2" / "l.obj"
    p.parent.mkdir()
    p.write_text("mtllib ../../x.mtl\n")
    _outside_file(p.parent, "../../x.mtl")
    with pytest.raises(SceneRefError, match="mtllib"):
        check_scene_refs(p)


def test_blend_reader_refuses_a_non_blend(tmp_path):
    p = tmp_path / "x.blend"
    p.write_bytes(b"BLENDER-v405" + b"\0" * 10)
    with pytest.raises(SceneRefError, match="x.blend: truncated .blend"):
        check_scene_refs(p)


def test_a_link_followed_by_dotdot_is_refused_whichever_way_an_importer_reads_it(tmp_path):
    """``lnk/../../secret.png`` with ``lnk -> sub/deeper``: following the link first stays inside, applying ``..``
    first (os.path.abspath, as the glTF importer does) leaves the folder: refused."""
    scene = tmp_path / "top" / "scene"
    (scene / "sub" / "deeper").mkdir(parents=True)
    (tmp_path / "top" / "secret.png").write_bytes(b"x")
    (scene / "sub" / "secret.png").write_bytes(b"x")
    os.symlink(scene / "sub" / "deeper", scene / "lnk")
    with pytest.raises(SceneRefError, match="lnk/../../secret.png"):
        check_scene_refs(_gltf(scene, image_uri="lnk/../../secret.png"))


def test_a_quoted_mtllib_outside_is_refused(tmp_path):
    (tmp_path / "x.mtl").write_text("newmtl m\nmap_Kd /etc/hostname\n")
    lvl = tmp_path / "lvl"
    lvl.mkdir()
    (lvl / "s.obj").write_text('mtllib "../x.mtl"\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n')
    with pytest.raises(SceneRefError, match="mtllib"):
        check_scene_refs(lvl / "s.obj")


def test_a_string_offset_is_a_corrupt_gltf_not_a_crash(tmp_path):
    p = _gltf(tmp_path / "lvl")
    doc = json.loads(p.read_text())
    doc["accessors"][0]["byteOffset"] = "0"
    p.write_text(json.dumps(doc))
    with pytest.raises(SceneRefError, match="non-negative integers"):
        check_scene_refs(p)


def test_a_missing_file_outside_is_left_to_the_importer(tmp_path):
    """An author's absolute texture path that does not exist here reads nothing: the scene is not refused (the
    texture renders neutral grey, as before the resolver)."""
    assert check_scene_refs(_gltf(tmp_path / "lvl", image_uri="/nonexistent/author/tex.png")) == []
