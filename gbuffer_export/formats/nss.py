"""BlendSR clips <-> Arm's NSS capture layout (``docs/nss/nss_dataset_specification.md`` of
``arm/neural-graphics-model-gym``, the layout its ``safetensors_generator`` reads)::

    OUT/0000.json                                per-sequence metadata (one BlendSR clip = one sequence)
    OUT/ground_truth/0000/0000.exr               HR radiance, RGBA half, linear Rec.709
    OUT/motion_gt/0000/0000.exr                  HR motion, RG half, UV units, current - previous
    OUT/x2/color/0000/0000.exr                   LR radiance of ratio 2 (jittered), RGBA half
    OUT/x2/depth/0000/0000.exr                   LR depth, R float32, forward-Z device depth (near/far per frame)
    OUT/x2/motion/0000/0000.exr                  LR motion, RG half, UV units (jitter excluded)

One ``x<ratio>`` folder per LR level of the clip (``x2``, ``x2_5``). Every convention conversion is in
``formats/conventions.py``; docs/formats.md says what maps to what and what is lost.
Pure numpy + json + OpenEXR: no bpy, no torch.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..clip import ClipWriter, levels_header, open_clip, scale_value, write_json_atomic
from ..errors import BlendSRError
from ..exr import HALF_MAX, read_exr, write_exr
from . import conventions as cv

SPEC_VERSION = "1.0.1"
#: Blender's default frame rate; BlendSR clips do not record one.
DEFAULT_FRAMERATE = 24
#: The colour space the NSS files hold (the model gym's captures come from engines rendering linear Rec.709).
NSS_SPACE = "Linear Rec.709"
HALTON_PERIOD = 16


class NssError(BlendSRError):
    """An NSS capture or export request that cannot be handled (bad input: the CLI prints the one-line message
    naming the path, exit 2)."""


def source_clips(sources) -> list[Path]:
    """Clip folders from ``sources``: a clip folder stays, a dataset folder gives its finished clips (every split,
    in the index's order)."""
    from ..dataset.build import clip_state, is_dataset, read_index
    out: list[Path] = []
    for s in sources:
        s = Path(s)
        if is_dataset(s):
            for c in read_index(s)["clips"]:
                p = s / c["path"]
                if clip_state(p, int(c.get("frames_planned", 0)))[0] == "done":
                    out.append(p)
        else:
            out.append(s)
    return out


def _exr_rgba(path: Path, rgb: np.ndarray) -> None:
    rgb = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=HALF_MAX), -HALF_MAX, HALF_MAX)
    write_exr(path, {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": np.ones(rgb.shape[:2])}, half=True)


def _exr_rg(path: Path, uv: np.ndarray) -> None:
    uv = np.clip(uv, -HALF_MAX, HALF_MAX)
    write_exr(path, {"R": uv[..., 0], "G": uv[..., 1]}, half=True)


def _exr_r32(path: Path, d: np.ndarray) -> None:
    write_exr(path, {"R": np.asarray(d, np.float32)}, half=False)


def export_clip(clip_path, out, seq: int, *, framerate: int = DEFAULT_FRAMERATE) -> dict:
    """Write one BlendSR clip as sequence ``seq`` of the NSS capture at ``out``; returns the sequence JSON."""
    clip = open_clip(clip_path)
    out = Path(out)
    name = f"{seq:04d}"
    need = {"radiance", "depth", "motion"}
    if not need <= set(clip.manifest.get("buffers", ())):
        raise NssError(f"{clip.path}: NSS needs the buffers {', '.join(sorted(need))} (clip has "
                       f"{', '.join(clip.manifest.get('buffers', ()))})")
    frames = sorted(clip.frames)
    if not frames:
        raise NssError(f"{clip.path}: no finished frames")
    lr_levels = [clip.level_at(s) for s in clip.scales]
    ratios = [cv.ratio_name(s) for s in clip.scales]
    w_hr, h_hr = clip.sizes["hr"]
    near, far = cv.depth_planes(clip.read(f, f"{lvl}/depth")[..., 0] for f in frames for lvl in ["hr", *lr_levels])
    jitter_mode = clip.manifest.get("render", {}).get("jitter", "none")
    records = []
    for j, f in enumerate(frames):
        fn = f"{j:04d}.exr"
        _exr_rgba(out / "ground_truth" / name / fn, clip.read(f, "hr/radiance", space=NSS_SPACE, exposed=True))
        _exr_rg(out / "motion_gt" / name / fn, cv.motion_to_uv(clip.read(f, "hr/motion")))
        per_ratio = []
        for lvl, r in zip(lr_levels, ratios):
            base = out / f"x{r}"
            _exr_rgba(base / "color" / name / fn, clip.read(f, f"{lvl}/radiance", space=NSS_SPACE, exposed=True))
            _exr_r32(base / "depth" / name / fn, cv.view_depth_to_device(clip.read(f, f"{lvl}/depth")[..., 0],
                                                                         near, far))
            _exr_rg(base / "motion" / name / fn, cv.motion_to_uv(clip.read(f, f"{lvl}/motion")))
            cam = clip.camera(f, lvl)
            w, h = clip.sizes[lvl]
            per_ratio.append(cv.normalized_jitter(cam["jitter"], w, h))
        cam_hr = clip.camera(f, "hr")
        fov_x, fov_y = cv.fov(cam_hr["intrinsics"], w_hr, h_hr)
        jit = clip.camera(f, lr_levels[0])["jitter"]
        records.append({
            "Frame": j, "FovX": fov_x, "FovY": fov_y, "CameraNearPlane": near, "CameraFarPlane": far,
            "ViewProjection": cv.matrix_to_list(cv.view_projection(cam_hr["world_from_camera"], cam_hr["intrinsics"],
                                                                   w_hr, h_hr, near, far)),
            "Jitter": {"X": float(jit[0]), "Y": float(jit[1])},
            "NormalizedPerRatioJitter": per_ratio,
            "CameraCut": j == 0,
            # the colour files hold exposed radiance (the clip's exposure applied: half floats keep their precision
            # for a clip of any brightness), so the exposure left to apply is 1; the clip's is in BlendSR.exposure
            "Exposure": 1.0,
            "BlendSRFrame": int(f),
        })
    meta = {
        "Version": SPEC_VERSION,
        "EmulatedFramerate": int(framerate),
        "TargetResolution": {"X": w_hr, "Y": h_hr},
        "Samples": {"Sequence": "Halton" if jitter_mode == "halton" else "None",
                    "Count": HALTON_PERIOD if jitter_mode == "halton" else 1, "Quantized": False},
        "ReverseZ": False,
        "OpaqueOnlyColor_Exported": False,
        "UnjitteredSrcColor_Exported": False,
        "UpscalingRatiosIndices": {f"x{r}_index": i for i, r in enumerate(ratios)},
        "MotionVectorsDilated": False,
        "Frames": records,
        "BlendSR": {"clip": str(clip.path), "scales": [float(s) for s in clip.scales],
                    "source_scene_linear": clip.scene_linear, "colour_space": NSS_SPACE,
                    "exposure": clip.exposure,
                    "identity": clip.manifest.get("identity")},
    }
    write_json_atomic(out / f"{name}.json", meta)
    return meta


def export_nss(sources, out, *, framerate: int = DEFAULT_FRAMERATE, progress=None) -> list[Path]:
    """Export every clip of ``sources`` (clip or dataset folders) as sequences 0000, 0001, ... of an NSS capture
    at ``out``; returns the sequence JSON paths."""
    clips = source_clips(sources)
    if not clips:
        raise NssError("no clips to export")
    out = Path(out)
    paths = []
    for i, c in enumerate(clips):
        export_clip(c, out, i, framerate=framerate)
        paths.append(out / f"{i:04d}.json")
        if progress:
            progress(c, paths[-1])
    return paths


# ----------------------------------------------------------------------------------------------
# Reading an NSS capture
# ----------------------------------------------------------------------------------------------

def read_sequence_meta(root, seq: str | int) -> dict:
    name = f"{int(seq):04d}" if not isinstance(seq, str) else seq
    p = Path(root) / f"{name}.json"
    if not p.is_file():
        raise NssError(f"{p}: no such NSS sequence")
    return json.loads(p.read_text())


def sequence_ratios(meta: dict) -> dict[str, int]:
    """{ratio name ('2', '2_5'): index into NormalizedPerRatioJitter}."""
    return {k[1:-len("_index")]: int(v) for k, v in meta.get("UpscalingRatiosIndices", {"x2_index": 0}).items()}


def ratio_value(name: str) -> float:
    return float(name.replace("_", "."))


def read_frame(root, seq: str | int, j: int, meta: dict | None = None) -> dict:
    """Frame ``j`` of sequence ``seq`` in BlendSR's conventions: ``hr/radiance``, ``hr/motion`` (pixels,
    p_prev = p + motion) and per ratio name r ``<r>/radiance``, ``<r>/depth`` (view depth, +inf at the far
    plane), ``<r>/motion``, ``<r>/jitter`` (pixels), plus ``world_from_camera`` and ``intrinsics`` (HR) and
    ``near``, ``far``."""
    root = Path(root)
    meta = meta or read_sequence_meta(root, seq)
    name = f"{int(seq):04d}" if not isinstance(seq, str) else seq
    fn = f"{j:04d}.exr"
    rec = meta["Frames"][j]
    near, far = float(rec["CameraNearPlane"]), float(rec["CameraFarPlane"])
    if far == -1.0:
        raise NssError(f"{root}: frame {j} has an infinite far plane, which this reader does not convert")
    out = {"near": near, "far": far,
           "hr/radiance": read_exr(root / "ground_truth" / name / fn, ("R", "G", "B")),
           "hr/motion": cv.uv_to_motion(read_exr(root / "motion_gt" / name / fn, ("R", "G")))}
    w, h = meta["TargetResolution"]["X"], meta["TargetResolution"]["Y"]
    wfc, k = cv.camera_from_view_projection(cv.list_to_matrix(rec["ViewProjection"]), w, h)
    out["world_from_camera"], out["intrinsics"] = wfc, k
    for r, idx in sequence_ratios(meta).items():
        base = root / f"x{r}"
        d = read_exr(base / "depth" / name / fn, ("R",))[..., 0]
        if meta.get("ReverseZ"):
            d = 1.0 - d
        out[f"{r}/radiance"] = read_exr(base / "color" / name / fn, ("R", "G", "B"))
        out[f"{r}/depth"] = cv.device_to_view_depth(d, near, far)
        out[f"{r}/motion"] = cv.uv_to_motion(read_exr(base / "motion" / name / fn, ("R", "G")))
        lh, lw = d.shape
        nj = rec["NormalizedPerRatioJitter"][idx]
        out[f"{r}/jitter"] = (nj["X"] * lw, nj["Y"] * lh)
    return out


def nss_to_clip(root, seq: str | int, out) -> Path:
    """Write NSS sequence ``seq`` as a BlendSR clip at ``out`` (buffers radiance, depth, motion; one LR level per
    ratio). NSS has no HR depth: ``hr/depth`` is the first LR level's depth repeated nearest-neighbour (the
    manifest's ``imported.hr_depth`` says so). The first frame's previous camera is its own camera. A frame's
    ``Exposure`` (when given) multiplies its colour: the clip holds exposed radiance, at exposure 1."""
    root = Path(root)
    meta = read_sequence_meta(root, seq)
    ratios = sequence_ratios(meta)
    names = sorted(ratios, key=ratio_value)
    scales = [ratio_value(r) for r in names]
    w, h = meta["TargetResolution"]["X"], meta["TargetResolution"]["Y"]
    levels = levels_header((w, h), scales)
    frames = list(range(len(meta["Frames"])))
    header = {
        "blendsr_version": "imported-nss", "blender_version": None,
        "scene": {"file": None, "sha256": None, "builtin": None, "nss": str(root), "sequence": str(seq)},
        "scale": scale_value(scales[0]), "levels": levels, "frames": frames,
        "buffers": ["radiance", "depth", "motion"], "fbeta_source": None, "scene_linear": NSS_SPACE,
        "render": {"jitter": "halton" if meta.get("Samples", {}).get("Sequence", "None") != "None" else "none",
                   "hr": {}, "lr": {}},
        "materials": {}, "material_summary": {},
        "imported": {"format": "nss", "version": meta.get("Version"), "hr_depth": "nearest-upsampled-from-lr"},
    }
    wr = ClipWriter(out, header)
    prev = None
    for j in frames:
        fr = read_frame(root, seq, j, meta)
        exposure = meta["Frames"][j].get("Exposure", 1.0)
        if isinstance(exposure, bool) or not isinstance(exposure, (int, float)) or not 0 < exposure < float("inf"):
            raise NssError(f"{root / f'{int(seq):04d}.json' if not isinstance(seq, str) else root / f'{seq}.json'}: "
                           f"Frames[{j}].Exposure {exposure!r} is not a positive number")
        fr = {k: a * np.float32(exposure) if k.endswith("/radiance") else a for k, a in fr.items()}
        record = {}
        cam = (fr["world_from_camera"], fr["intrinsics"])
        pcam = prev or cam
        for lvl, info in levels.items():
            lw, lh = info["width"], info["height"]
            f = lw / w
            if lvl == "hr":
                d_lr = fr[f"{names[0]}/depth"]
                iy = np.minimum((np.arange(h) * d_lr.shape[0]) // h, d_lr.shape[0] - 1)
                ix = np.minimum((np.arange(w) * d_lr.shape[1]) // w, d_lr.shape[1] - 1)
                bufs = {"radiance": fr["hr/radiance"], "depth": d_lr[np.ix_(iy, ix)], "motion": fr["hr/motion"]}
                jit = (0.0, 0.0)
            else:
                r = names[scales.index(info["scale"])]
                bufs = {b: fr[f"{r}/{b}"] for b in ("radiance", "depth", "motion")}
                jit = fr[f"{r}/jitter"]
            for b, a in bufs.items():
                wr.write_buffer(j, lvl, b, a)
            k = tuple(v * f for v in cam[1])
            record[lvl] = {"world_from_camera": cam[0], "prev_world_from_camera": pcam[0], "intrinsics": k,
                           "prev_intrinsics": tuple(v * f for v in pcam[1]), "jitter": [float(x) for x in jit],
                           "spp": 1, "seed": 0, "seconds": {}}
        wr.commit_frame(j, record)
        prev = cam
    return Path(out)


__all__ = ["export_nss", "export_clip", "read_frame", "read_sequence_meta", "nss_to_clip", "source_clips",
           "NssError"]
