"""BlendSR clips -> Arm's NFRU capture layout (neural frame-rate upscaling: ``docs/nfru/nfru_dataset_specification.md``
of ``arm/neural-graphics-model-gym``, the layout its converter's reader ``NFRUv2_2`` reads)::

    OUT/0000.json                        per-sequence metadata (NSS's keys plus the camera basis per frame)
    OUT/ground_truth/0000/0000.exr       HR radiance, RGBA half, linear Rec.709 (NFRU's input and target frames)
    OUT/x2/depth/0000/0000.exr           depth of the clip's 2x level, R float32, forward-Z device depth
    OUT/x2/motion_m1/0000/0000.exr       2x-level motion to the previous frame, RGBA half (B = A = 0), UV units,
                                         current - previous (NSS's convention)
    OUT/x2/motion_m2/0000/0000.exr       even frames only: motion to the frame two back, the same encoding

``motion_m2`` is chained from BlendSR's one-frame motion: ``m2(p) = m(p) + m_prev(p + m(p))`` with ``m_prev`` (the
previous frame's motion) sampled bilinearly; where that sample leaves the image, the motion is taken as constant
(``2 m(p)``), and on a sequence's first frame (nothing two frames back) it is 0. The conventions (UV motion,
forward-Z depth, a row-by-row reverse-Z ViewProjection) are NSS's (``formats/conventions.py``); the export
rules (2x level required, output folder, one sequence per contiguous run of frames) are ``formats/nss.py``'s.
Pure numpy + json + OpenEXR: no bpy, no torch.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..clip import write_json_atomic
from ..conventions import backward_warp
from ..exr import HALF_MAX, write_exr
from . import conventions as cv
from .nss import (DEFAULT_FRAMERATE, GT_COLOR_SPACE, GYM_RATIO, HALTON_PERIOD, NSS_SPACE, _exr_r32, _exr_rgba,
                  clip_planes, export_sequences, sequence_names)
from .output import ExportOptions

#: The version of Arm's NFRU sample capture (tests/datasets/test_nfru_exr/0000.json).
SPEC_VERSION = "1.0.3"


def _exr_uv4(path: Path, uv: np.ndarray) -> None:
    uv = np.clip(uv, -HALF_MAX, HALF_MAX)
    z = np.zeros(uv.shape[:2])
    write_exr(path, {"R": uv[..., 0], "G": uv[..., 1], "B": z, "A": z}, half=True)


def two_frame_motion(motion: np.ndarray, prev_motion: np.ndarray) -> np.ndarray:
    """BlendSR backward motion (pixels, p_prev = p + motion) from frame t to t - 2: ``motion`` of t chained with
    ``prev_motion`` of t - 1 sampled at p + motion (constant velocity where that leaves the image)."""
    warped, valid = backward_warp(np.asarray(prev_motion, np.float64), np.asarray(motion, np.float64))
    m = np.asarray(motion, np.float64)
    return np.where(valid[..., None], m + warped, 2 * m)


def _xyz(v) -> dict:
    return {"X": float(v[0]), "Y": float(v[1]), "Z": float(v[2])}


def export_sequence(clip, frames: list[int], out, name: str, *, framerate: int = DEFAULT_FRAMERATE,
                    planes: tuple[float, float] | None = None) -> dict:
    """Write ``frames`` (contiguous) of ``clip`` as NFRU sequence ``name`` at ``out``; returns its JSON."""
    out = Path(out)
    lvl = clip.level_at(GYM_RATIO)
    w_hr, h_hr = clip.sizes["hr"]
    lw, lh = clip.sizes[lvl]
    near, far = planes or clip_planes(clip)
    jitter_mode = clip.manifest.get("render", {}).get("jitter", "none")
    records, prev = [], None
    for j, f in enumerate(frames):
        fn = f"{j:04d}.exr"
        _exr_rgba(out / "ground_truth" / name / fn, clip.read(f, "hr/radiance", space=NSS_SPACE))
        _exr_r32(out / "x2" / "depth" / name / fn,
                 cv.view_depth_to_device(clip.read(f, f"{lvl}/depth")[..., 0], near, far))
        m = clip.read(f, f"{lvl}/motion").astype(np.float64)
        _exr_uv4(out / "x2" / "motion_m1" / name / fn, cv.motion_to_uv(m))
        if j % 2 == 0:
            m2 = two_frame_motion(m, prev) if prev is not None else np.zeros_like(m)
            _exr_uv4(out / "x2" / "motion_m2" / name / fn, cv.motion_to_uv(m2))
        prev = m
        cam = clip.camera(f, "hr")
        wfc = cam["world_from_camera"]
        fov_x, fov_y = cv.fov(cam["intrinsics"], w_hr, h_hr)
        jit = clip.camera(f, lvl)["jitter"]
        records.append({
            "Frame": j, "FovX": fov_x, "FovY": fov_y, "CameraNearPlane": near, "CameraFarPlane": far,
            # Blender cameras: +X right, +Y up, looking along -Z (world space, scene units)
            "CameraPosition": _xyz(wfc[:3, 3]), "CameraUp": _xyz(wfc[:3, 1]), "CameraRight": _xyz(wfc[:3, 0]),
            "CameraForward": _xyz(-wfc[:3, 2]),
            "ViewProjection": cv.matrix_to_list(cv.view_projection(wfc, cam["intrinsics"], w_hr, h_hr, near, far,
                                                                   reverse_z=True)),
            "Jitter": {"X": float(jit[0]), "Y": float(jit[1])},
            "NormalizedPerRatioJitter": [cv.normalized_jitter(jit, lw, lh)],
            "CameraCut": j == 0,
            "Exposure": 1.0,
            "BlendSRFrame": int(f),
        })
    meta = {
        "Version": SPEC_VERSION, "MotionVectorsDilated": False, "EmulatedFramerate": int(framerate),
        "GTColorSpace": GT_COLOR_SPACE, "ReverseZ": False, "TargetResolution": {"X": w_hr, "Y": h_hr},
        "UpscalingRatiosIndices": {"x2_index": 0},
        "Samples": {"Sequence": "Halton" if jitter_mode == "halton" else "None",
                    "Count": HALTON_PERIOD if jitter_mode == "halton" else 1, "Quantized": False},
        "Frames": records,
        "BlendSR": {"clip": str(clip.path), "frames": [int(f) for f in frames], "scale": GYM_RATIO,
                    "source_scene_linear": clip.scene_linear, "colour_space": NSS_SPACE,
                    "identity": clip.manifest.get("identity"),
                    "motion_m2": "chained from one-frame motion; 0 on the first frame"},
    }
    write_json_atomic(out / f"{name}.json", meta)
    return meta


def is_nfru_export(out: Path) -> bool:
    return bool(sequence_names(out)) and (out / "x2" / "motion_m1").is_dir()


def export_nfru(sources, out, options: ExportOptions = ExportOptions()) -> list[Path]:
    """Export every clip of ``sources`` as sequences of an NFRU capture at ``out`` (the rules of ``export_nss``);
    returns the sequence JSON paths."""
    return export_sequences(sources, out, options, fmt="nfru", write_sequence=export_sequence,
                            is_export=is_nfru_export)


__all__ = ["export_nfru", "export_sequence", "two_frame_motion", "SPEC_VERSION"]
