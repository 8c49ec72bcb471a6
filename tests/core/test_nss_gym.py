"""NSS that Arm's model gym reads by default (issue 42, "What to build" 1), checked without its gigabyte install.

``gym_read`` does what Arm's EXR -> safetensors converter does with a capture (``scripts/safetensors_generator``:
``safetensors_writer.py`` finds the sequences, ``dataset_readers/nss_exr_dataset_reader.py``, reader
``NSSv1_0_1``, reads them), reduced to its reads and checks and written here from the facts in those files
(arm/neural-graphics-model-gym at ef328bf; no code copied):

- sequences are the names of the folders holding ``*.exr`` files anywhere under the capture, each read with the
  JSON ``<capture>/<sequence>.json``;
- the reader is built for ``scale = 2.0`` (the writer passes no other) and requires the non-empty folders
  ``ground_truth/SEQ``, ``motion_gt/SEQ``, ``x2/color/SEQ``, ``x2/depth/SEQ``, ``x2/motion/SEQ``;
- frames: the sorted EXRs of each folder, as many as the shortest folder has; ``x2/depth`` channel R as float32,
  ``x2/motion`` and ``motion_gt`` RG, ``x2/color`` and ``ground_truth`` RGB;
- JSON keys read: EmulatedFramerate, TargetResolution.X/Y, Samples.Count, ReverseZ (optional), and per frame
  ViewProjection (reshaped to 4 x 4 row by row), CameraNearPlane, CameraFarPlane (-1: infinite), FovX, FovY,
  CameraCut (optional), Exposure (optional; its natural log is stored), NormalizedPerRatioJitter[the index of
  UpscalingRatiosIndices["x2_index"]];
- motion is clamped to [-1, 1], swapped to (v, u) and multiplied by the image's (height, width): pixels;
  the jitter is (y, x) times the render size; depth parameters are FSR2's for a forward-Z, finite projection:
  view depth = n f / ((f - n) (f / (f - n) - d)) for device depth d.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from gbuffer_export.clip import open_clip
from gbuffer_export.exr import read_exr_channels
from gbuffer_export.synthetic import make_synthetic_clip

HALF_REL = 2.0 ** -10


class GymError(Exception):
    """What Arm's converter would fail with (FileNotFoundError, ValueError, KeyError there)."""


def gym_read(src: Path, scale: float = 2.0) -> dict[str, list[dict]]:
    """{sequence: [frame features]} as Arm's converter would read ``src`` (see module doc)."""
    s = format(float(scale), "g").replace(".", "_")
    out = {}
    for seq in sorted({p.parent.name for p in src.rglob("*.exr")}):
        meta = json.loads((src / f"{seq}.json").read_text())
        dirs = [f"x{s}/depth", f"x{s}/motion", f"x{s}/color", "motion_gt", "ground_truth"]
        for d in dirs:
            if not (src / d / seq).is_dir() or not any((src / d / seq).iterdir()):
                raise GymError(f"Missing {src / d / seq} in expected structure.")
        files = {d: sorted((src / d / seq).rglob("*.exr")) for d in dirs}
        frames = []
        for i in range(min(len(v) for v in files.values())):
            ch = {d: read_exr_channels(files[d][i]) for d in dirs}
            depth = ch[f"x{s}/depth"]["R"].astype(np.float32)
            color = np.stack([ch[f"x{s}/color"][c] for c in "RGB"])
            truth = np.stack([ch["ground_truth"][c] for c in "RGB"])
            rec = meta["Frames"][i]
            idx = meta["UpscalingRatiosIndices"][f"x{s}_index"]
            jit = rec["NormalizedPerRatioJitter"][idx]
            n, f = float(rec["CameraNearPlane"]), float(rec["CameraFarPlane"])
            if meta.get("ReverseZ", False):
                depth = 1.0 - depth

            def motion(c):
                uv = np.clip(np.stack([c["R"], c["G"]]).astype(np.float64), -1, 1)
                return uv[::-1] * np.array(uv.shape[1:], np.float64)[:, None, None]  # (v, u) * (H, W)
            frames.append({
                "EmulatedFramerate": float(meta["EmulatedFramerate"]),
                "TargetResolution": (meta["TargetResolution"]["X"], meta["TargetResolution"]["Y"]),
                "Samples": int(meta["Samples"]["Count"]),
                "render_size": color.shape[1:], "outDims": truth.shape[1:],
                "viewProj": np.reshape(np.asarray(rec["ViewProjection"], np.float64), (4, 4)),
                "motion_lr": motion(ch[f"x{s}/motion"]), "motion": motion(ch["motion_gt"]),
                "depth": depth, "infinite_zFar": f == -1, "zNear": n, "zFar": 5000.0 if f == -1 else f,
                "FovX": float(rec["FovX"]), "FovY": float(rec["FovY"]),
                "camera_cut": bool(rec.get("CameraCut", False)),
                "exposure": math.log(float(rec["Exposure"])) if "Exposure" in rec else None,
                "jitter": (jit["Y"] * color.shape[1], jit["X"] * color.shape[2]),
                "colour_linear": color, "ground_truth_linear": truth,
            })
        out[seq] = frames
    if not out:
        raise GymError(f"No source files found in '{src}' with the selected extension 'exr'")
    return out


def fsr2_view_depth(d: np.ndarray, n: float, f: float) -> np.ndarray:
    """View depth (positive) from forward-Z device depth by FSR2's depth-to-view-space parameters."""
    return n * f / ((f - n) * (f / (f - n) - np.asarray(d, np.float64)))


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    from gbuffer_export.formats.nss import export_nss
    root = tmp_path_factory.mktemp("gym")
    clips = [make_synthetic_clip(root / "a", frames=range(1, 5), hr_size=(40, 24), scales=(2, 4), jitter=True),
             make_synthetic_clip(root / "b", frames=range(3, 6), hr_size=(32, 16), scales=(2,), jitter=True)]
    export_nss(clips, root / "nss")
    return clips, root / "nss"


def test_the_gym_converter_reads_every_sequence_as_blendsr_wrote_it(export):
    clips, out = export
    seqs = gym_read(out)
    assert list(seqs) == ["0000", "0001"]
    for (seq, frames), path in zip(seqs.items(), clips):
        clip = open_clip(path)
        meta = json.loads((out / f"{seq}.json").read_text())
        assert meta["GTColorSpace"] == "Linear" and len(frames) == len(clip.frames) == len(meta["Frames"])
        w, h = clip.sizes["hr"]
        lw, lh = clip.sizes[clip.level_at(2)]
        for j, (fr, f) in enumerate(zip(frames, clip.frames)):
            assert fr["TargetResolution"] == (w, h) and fr["outDims"] == (h, w) and fr["render_size"] == (lh, lw)
            assert fr["camera_cut"] == (j == 0) and fr["exposure"] == 0.0 and fr["Samples"] == 16
            lvl = clip.level_at(2)
            for key, level in (("motion_lr", lvl), ("motion", "hr")):
                m = clip.read(f, f"{level}/motion")  # BlendSR: p_prev - p, (x, y) pixels
                expect = -np.stack([m[..., 1], m[..., 0]])  # the gym: current - previous, (v, u) pixels
                assert np.all(np.abs(fr[key] - expect) <= HALF_REL * np.abs(expect) + 1e-6), key
            jx, jy = clip.camera(f, lvl)["jitter"]
            assert fr["jitter"] == pytest.approx((jy, jx), abs=1e-9)
            z = clip.read(f, f"{lvl}/depth")[..., 0]
            fin = np.isfinite(z)
            assert np.allclose(fsr2_view_depth(fr["depth"], fr["zNear"], fr["zFar"])[fin], z[fin], rtol=1e-4)
            assert np.all(fr["depth"][~fin] == 1.0) and not fr["infinite_zFar"]
            fy = clip.camera(f, "hr")["intrinsics"][1]
            assert fr["FovY"] == pytest.approx(2 * math.atan(h / (2 * fy)))


def test_the_gym_converter_refuses_a_capture_without_x2_and_blendsr_refuses_to_write_one(tmp_path):
    from gbuffer_export.formats.nss import NssError, export_clip, export_nss
    clip = make_synthetic_clip(tmp_path / "c", frames=(1, 2), hr_size=(16, 8), scale=4)
    with pytest.raises(NssError, match=r"needs a 2x level .* --scales 2,4"):
        export_nss([clip], tmp_path / "nss")
    assert not (tmp_path / "nss").exists()
    # what the gym would have said to the old export (x4 only): the failure issue 42 reported
    import gbuffer_export.formats.nss as nss
    clip_obj = open_clip(clip)
    nss.export_sequence(clip_obj, clip_obj.frames, tmp_path / "x4only", "0000")
    with pytest.raises(GymError, match=r"Missing .*x2/depth/0000"):
        gym_read(tmp_path / "x4only")
    with pytest.raises(NssError, match="2x level"):
        export_clip(clip, tmp_path / "again", 0)


# The layout of Arm's sample capture tests/datasets/test_nss_exr/0002.json (arm/neural-graphics-model-gym at
# ef328bf), frame 0: FovX 1.0719919204711914, FovY 0.64492571353912354, CameraNearPlane 10, CameraFarPlane -1,
# TargetResolution 1920 x 1080, and the ViewProjection below. Read row by row, M[r][c] = element 4 r + c:
# rows 0 and 1 have lengths cot(FovX / 2) and cot(FovY / 2) over their first three elements, row 3 (elements
# 12-14) is a unit vector (the view direction: w = view depth), and the translation column is elements 3, 7, 11,
# 15 (1070.54, -2093.76, 10 = the near plane of its infinite projection, 446.87). Read column by column none of
# these hold.
ARM_SAMPLE_FRAME0 = {
    "FovX": 1.0719919204711914, "FovY": 0.64492571353912354, "CameraNearPlane": 10,
    "ViewProjection": [0.78552661443760596, 1.4890017841187206, -2.2393705453165573e-14, 1070.5408648481086,
                       0.55243995774062304, -0.29144108107353361, 2.9269908750115086, -2093.7568479423689,
                       0, 0, 0, 10,
                       0.86499167993686832, -0.45632852364892434, -0.20869516559898543, 446.86993531243763],
}


def layout_holds(vp: list[float], fov_x: float, fov_y: float) -> bool:
    """The facts of Arm's layout (above) for a 16-float ViewProjection."""
    m = np.asarray(vp, np.float64).reshape(4, 4)
    cot = lambda a: 1.0 / math.tan(a / 2)
    return bool(abs(np.linalg.norm(m[3, :3]) - 1) < 1e-5
                and abs(np.linalg.norm(m[0, :3]) - cot(fov_x)) < 1e-3 * cot(fov_x)
                and abs(np.linalg.norm(m[1, :3]) - cot(fov_y)) < 1e-3 * cot(fov_y))


def test_the_view_projection_has_the_layout_of_arms_sample_file(export):
    s = ARM_SAMPLE_FRAME0
    assert layout_holds(s["ViewProjection"], s["FovX"], s["FovY"])  # the facts, on Arm's own numbers
    assert not layout_holds(np.asarray(s["ViewProjection"]).reshape(4, 4).T.reshape(-1), s["FovX"], s["FovY"])
    assert s["ViewProjection"][11] == s["CameraNearPlane"]  # a translation-column element
    clips, out = export
    clip = open_clip(clips[0])
    meta = json.loads((out / "0000.json").read_text())
    for fr, f in zip(meta["Frames"], clip.frames):
        vp = fr["ViewProjection"]
        assert layout_holds(vp, fr["FovX"], fr["FovY"])
        assert not layout_holds(np.asarray(vp).reshape(4, 4).T.reshape(-1), fr["FovX"], fr["FovY"])
        # a point 5 units in front of the camera: w (row 3, elements 12-15) is its view depth; the camera's
        # own position has x = y = w = 0 through the translation column (elements 3, 7, 15)
        wfc = clip.camera(f, "hr")["world_from_camera"]
        eye, forward = wfc[:3, 3], -wfc[:3, 2]  # Blender cameras look along their -Z
        m = np.asarray(vp).reshape(4, 4)
        assert (m @ np.append(eye + 5 * forward, 1.0))[3] == pytest.approx(5.0)
        c = m @ np.append(eye, 1.0)
        assert np.allclose(c[[0, 1, 3]], 0, atol=1e-9)
        assert np.allclose([vp[3], vp[7], vp[11], vp[15]], m[:, 3])


# ------------------------------------------------------------------------------------------ NFRU
# Arm's NFRU reader (scripts/safetensors_generator/dataset_readers/nfru_exr_dataset_reader.py, reader NFRUv2_2), the
# facts its test below re-implements: folders x2/depth, x2/motion_m2, x2/motion_m1, ground_truth per sequence, as
# many frames as the longest; motion_m1 and (on even frames, the file count // 2) motion_m2 read as RGBA, scaled to
# pixels as -uv * (W, H) in (v, u) order; from the ViewProjections (reshaped row by row) of frames t and t - 1
# (t - 2) it computes "synthetic" camera motion: clip-space points (2 u - 1, 2 v - 1 with v up from the bottom row
# at pixel centres, 1 - depth, 1) taken through VP_prev @ inverse(VP_t), the difference of the UVs in pixels,
# swapped to (v down, u) and negated (previous - current); Exposure's log; NormalizedPerRatioJitter[x2_index].


def nfru_synthetic_motion(depth: np.ndarray, vp: np.ndarray, vp_prev: np.ndarray) -> np.ndarray:
    """Pixels, (y down, x) order, previous minus current: the reader's camera motion from depth and matrices."""
    h, w = depth.shape
    jj, ii = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    u, v = (ii + 0.5) / w, 1.0 - (jj + 0.5) / h
    clip = np.stack([2 * u - 1, 2 * v - 1, 1.0 - depth, np.ones_like(depth)], -1)
    r = clip @ (vp_prev @ np.linalg.inv(vp)).T
    up, vp_ = (r[..., 0] / r[..., 3] + 1) / 2, (r[..., 1] / r[..., 3] + 1) / 2
    vel_x, vel_y_up = (u - up) * w, (v - vp_) * h
    return -np.stack([-vel_y_up, vel_x], -1)


def nfru_read(src: Path, seq: str) -> list[dict]:
    meta = json.loads((src / f"{seq}.json").read_text())
    dirs = ["x2/depth", "x2/motion_m2", "x2/motion_m1", "ground_truth"]
    files = {d: sorted((src / d / seq).rglob("*.exr")) for d in dirs}
    out = []
    flow = lambda c: -np.stack([c["G"], c["R"]], -1).astype(np.float64) * np.array(c["R"].shape, np.float64)
    for i in range(max(len(v) for v in files.values())):
        rec = meta["Frames"][i]
        depth = read_exr_channels(files["x2/depth"][i])["R"].astype(np.float64)
        m1 = read_exr_channels(files["x2/motion_m1"][i])
        assert set("RGBA") <= set(m1)  # the reader asks for RGBA
        vp = lambda k: np.reshape(np.asarray(meta["Frames"][k]["ViewProjection"], np.float64), (4, 4))
        fr = {"depth": depth, "mv_f60_m1": flow(m1), "exposure": math.log(float(rec["Exposure"])),
              "jitter": rec["NormalizedPerRatioJitter"][meta["UpscalingRatiosIndices"]["x2_index"]],
              "basis": [rec[k] for k in ("CameraPosition", "CameraUp", "CameraRight", "CameraForward")]}
        if i % 2 == 0:
            m2 = read_exr_channels(files["x2/motion_m2"][i // 2])
            assert set("RGBA") <= set(m2)
            fr["mv_f30_m1"] = flow(m2)
        if 0 < i < len(files["ground_truth"]) - 1:
            fr["sy_f60_m1"] = nfru_synthetic_motion(depth, vp(i), vp(i - 1))
        if 1 < i < len(files["ground_truth"]) - 2:
            fr["sy_f30_m1"] = nfru_synthetic_motion(depth, vp(i), vp(i - 2))
        out.append(fr)
    return out


def test_nfru_export_reads_as_the_gym_reader_reads_it(tmp_path):
    """A static synthetic scene seen by a moving, un-jittered camera: the reader's camera motion from the exported
    depth and ViewProjections equals the exported motion_m1 and motion_m2 (within half precision) on surfaces."""
    from gbuffer_export.formats.nfru import export_sequence
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 9), hr_size=(64, 32), scales=(2, 4))
    out = tmp_path / "nfru"  # the sequence writer itself: export_nfru refuses sizes other than the reader's 1920x1080
    export_sequence(open_clip(clip), list(open_clip(clip).frames), out, "0000")
    assert sorted(p.name for p in (out / "x2" / "motion_m2" / "0000").iterdir()) == [
        "0000.exr", "0002.exr", "0004.exr", "0006.exr"]
    frames = nfru_read(out, "0000")
    c = open_clip(clip)
    assert len(frames) == 8
    checked = 0
    for i, fr in enumerate(frames):
        f = c.frames[i]
        m = c.read(f, "lr/motion").astype(np.float64)[..., ::-1]  # BlendSR p_prev - p, as (y, x)
        assert np.allclose(fr["mv_f60_m1"], m, rtol=2 ** -10, atol=1e-3)
        wfc = c.camera(f, "hr")["world_from_camera"]
        assert fr["basis"][3] == pytest.approx({"X": -wfc[0, 2], "Y": -wfc[1, 2], "Z": -wfc[2, 2]})
        assert fr["exposure"] == 0.0 and fr["jitter"] == {"X": 0.0, "Y": 0.0}
        surface = fr["depth"] < 1.0
        if "sy_f60_m1" in fr:
            assert np.abs(fr["sy_f60_m1"] - m)[surface].max() < 0.01, i
            checked += 1
        if "sy_f30_m1" in fr and "mv_f30_m1" in fr:
            # static scene: the chained two-frame motion agrees with the reader's reprojection except where the
            # previous frame's motion is sampled across an edge (measured: median 0.001 px, 80% within 0.012 px)
            err = np.hypot(*(fr["sy_f30_m1"] - fr["mv_f30_m1"]).transpose(2, 0, 1))[surface]
            assert np.median(err) < 0.005 and np.mean(err < 0.05) > 0.8 and err.max() < 2.0, i
            checked += 1
    assert checked >= 7
