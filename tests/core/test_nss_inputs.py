"""``blendsr import-nss`` on crafted captures (issue 43, item 4): each gives one line naming the file and the key,
exit 2, before any memory is taken or any clip folder is created."""
from __future__ import annotations

import json
import shutil

import pytest

from gbuffer_export.synthetic import make_synthetic_clip


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    from gbuffer_export.formats.nss import export_nss
    root = tmp_path_factory.mktemp("nssin")
    clip = make_synthetic_clip(root / "clip", frames=(1, 2, 3), hr_size=(16, 8), scales=(2, 4), jitter=True)
    export_nss([clip], root / "nss")
    return root / "nss"


def _set(path, value):
    def f(meta):
        d = meta
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return f


def _del(path):
    def f(meta):
        d = meta
        for k in path[:-1]:
            d = d[k]
        del d[path[-1]]
    return f


CASES = {
    "ratio key with ../": (lambda m: m["UpscalingRatiosIndices"].update({"x../../etc_index": 0}),
                           "UpscalingRatiosIndices key 'x../../etc_index'"),
    "huge TargetResolution": (_set(["TargetResolution"], {"X": 1000000, "Y": 1000000}),
                              "TargetResolution 1000000x1000000: importing needs about"),
    "no TargetResolution": (_del(["TargetResolution"]), "TargetResolution is missing"),
    "string TargetResolution": (_set(["TargetResolution", "X"], "16"), "TargetResolution.X = '16'"),
    "all-zero ViewProjection": (_set(["Frames", 1, "ViewProjection"], [0.0] * 16),
                                "Frames[1].ViewProjection is not the projection of a rigid camera"),
    "short ViewProjection": (_set(["Frames", 0, "ViewProjection"], [1.0] * 3),
                             "Frames[0].ViewProjection is not a list of 16 numbers"),
    "NaN jitter": (_set(["Frames", 2, "NormalizedPerRatioJitter", 0, "X"], float("nan")),
                   "Frames[2].NormalizedPerRatioJitter[0].X = nan is not a finite number"),
    "missing jitter": (_set(["Frames", 0, "NormalizedPerRatioJitter"], [{"X": 0, "Y": 0}]),
                       "Frames[0].NormalizedPerRatioJitter[1] (ratio x4) is missing"),
    "far before near": (_set(["Frames", 0, "CameraFarPlane"], 0.001), "CameraFarPlane 0.001 is not beyond"),
    "infinite far": (_set(["Frames", 0, "CameraFarPlane"], -1), "infinite far plane"),
    "no frames": (_set(["Frames"], []), "Frames is not a non-empty list"),
    "frame not an object": (_set(["Frames", 0], 7), "Frames[0] is not an object"),
    "index not a number": (_set(["UpscalingRatiosIndices", "x2_index"], "0"),
                           "UpscalingRatiosIndices.x2_index = '0'"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_crafted_capture_json_gives_one_line_naming_file_and_key(capture, tmp_path, capsys, case):
    from gbuffer_export.cli import main
    cap = tmp_path / "cap"
    shutil.copytree(capture, cap)
    meta = json.loads((cap / "0000.json").read_text())
    edit, expect = CASES[case]
    edit(meta)
    (cap / "0000.json").write_text(json.dumps(meta))  # json writes NaN as the literal NaN
    out = tmp_path / "clip"
    code = main(["import-nss", str(cap), "-o", str(out)])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("blendsr: error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert str(cap / "0000.json") in lines[0] and expect in lines[0], lines[0]
    assert not out.exists()  # no partial clip


def test_json_that_does_not_parse_names_the_file(capture, tmp_path, capsys):
    from gbuffer_export.cli import main
    cap = tmp_path / "cap"
    shutil.copytree(capture, cap)
    (cap / "0000.json").write_text('{"Version": "1.0.1", ')
    assert main(["import-nss", str(cap), "-o", str(tmp_path / "clip")]) == 2
    err = capsys.readouterr().err
    assert f"blendsr: error: {cap / '0000.json'}: not valid JSON" in err and not (tmp_path / "clip").exists()


@pytest.mark.parametrize("case", ["missing", "wrong size", "huge header"])
def test_a_missing_or_mis_sized_exr_is_named_before_the_clip_is_created(capture, tmp_path, capsys, case):
    from gbuffer_export.cli import main
    import numpy as np

    from gbuffer_export.exr import write_exr
    cap = tmp_path / "cap"
    shutil.copytree(capture, cap)
    p = cap / "x4" / "motion" / "0000" / "0002.exr"
    if case == "missing":
        p.unlink()
    elif case == "wrong size":
        write_exr(p, {"R": np.zeros((5, 7)), "G": np.zeros((5, 7))}, half=True)
    else:  # its header patched to declare 100000 x 100000 pixels: refused from the header, never allocated
        import struct
        b = bytearray(p.read_bytes())
        at = b.index(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4
        b[at:at + 16] = struct.pack("<4i", 0, 0, 99999, 99999)
        p.write_bytes(bytes(b))
        from gbuffer_export.exr import exr_size
        assert exr_size(p) == (100000, 100000)
    assert main(["import-nss", str(cap), "-o", str(tmp_path / "clip")]) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("blendsr: error:")]
    assert len(lines) == 1 and str(p) in lines[0] and "Traceback" not in err, err
    assert not (tmp_path / "clip").exists()


def test_a_good_capture_still_imports(capture, tmp_path):
    from gbuffer_export.clip import open_clip
    from gbuffer_export.formats.nss import nss_to_clip
    c = open_clip(nss_to_clip(capture, "0000", tmp_path / "clip"))
    assert c.complete and c.scales == [2.0, 4.0] and len(c.frames) == 3
