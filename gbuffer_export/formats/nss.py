"""BlendSR clips <-> Arm's NSS capture layout (``docs/nss/nss_dataset_specification.md`` of
``arm/neural-graphics-model-gym``, the layout its ``safetensors_generator`` reads)::

    OUT/0000.json                                per-sequence metadata (one clip, or one contiguous run of its
                                                 frames, is one sequence)
    OUT/ground_truth/0000/0000.exr               HR radiance, RGBA half, linear Rec.709
    OUT/motion_gt/0000/0000.exr                  HR motion, RG half, UV units, current - previous
    OUT/x2/color/0000/0000.exr                   LR radiance of ratio 2 (jittered), RGBA half
    OUT/x2/depth/0000/0000.exr                   LR depth, R float32, forward-Z device depth (near/far per frame)
    OUT/x2/motion/0000/0000.exr                  LR motion, RG half, UV units (jitter excluded)

One ``x<ratio>`` folder per LR level of the clip (``x2``, ``x2_5``); ``x2`` is required (Arm's converter reads only
it by default). Where and how the folder is written (new, ``--overwrite``, ``--append``): ``formats/output.py``.
Reading a capture follows BlendSR's path rule (plain names, no symbolic links) and checks the JSON before anything
is allocated or written. Every convention conversion is in
``formats/conventions.py``; docs/formats.md says what maps to what and what is lost.
Pure numpy + json + OpenEXR: no bpy, no torch.
"""
from __future__ import annotations

import json
import logging
import math
import re
import shutil
from pathlib import Path

import numpy as np

from ..clip import ClipWriter, check_no_links, levels_header, scale_value, write_json_atomic
from ..errors import BlendSRError
from ..exr import HALF_MAX, exr_size, read_exr, write_exr
from ..validate.gate import open_valid_clip
from . import conventions as cv
from .output import ExportOptions, Target, clean_temp_files
from ..format_limits import check_clips

log = logging.getLogger(__name__)

SPEC_VERSION = "1.0.1"
#: Blender's default frame rate; BlendSR clips do not record one.
DEFAULT_FRAMERATE = 24
#: The colour space the NSS files hold (the model gym's captures come from engines rendering linear Rec.709).
NSS_SPACE = "Linear Rec.709"
#: ``GTColorSpace`` of Arm's sample captures (tests/datasets/test_nss_exr/0002.json): the ground truth is linear.
GT_COLOR_SPACE = "Linear"
#: The ratio Arm's converter reads by default (``NSSEXRDatasetReader(scale=2.0)``: ``x2/`` only).
GYM_RATIO = 2.0
HALTON_PERIOD = 16
#: A sequence JSON that BlendSR writes (``0000.json``); sequence folders have the same name.
SEQUENCE_FILE = re.compile(r"^(\d{4,})\.json$")
#: A key of ``UpscalingRatiosIndices`` (``x2_index``, ``x1_5_index``).
RATIO_KEY = re.compile(r"^x(\d{1,3}(?:_\d{1,3})?)_index$")
#: A name of one path component read from a capture (a sequence name): no separator, no leading dot.
PLAIN_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
#: Bytes of memory ``nss_to_clip`` holds per HR pixel of one frame (the arrays read, converted and written).
IMPORT_BYTES_PER_HR_PIXEL = 128


class NssError(BlendSRError):
    """An NSS capture or export request that cannot be handled (bad input: the CLI prints the one-line message
    naming the path, exit 2)."""


def source_clips(sources) -> list[Path]:
    """Clip folders from ``sources``: a clip folder stays, a dataset folder gives its finished clips (every split,
    in the index's order), each through the one rule for index paths (``dataset.build.clip_dir``: relative, inside
    the dataset, links resolved inside it; one line otherwise). A finished clip the dataset marked invalid is left
    out with a warning, as ``split_clips`` does."""
    from ..dataset.build import clip_dir, clip_state, is_dataset, read_index
    out: list[Path] = []
    for s in sources:
        s = Path(s)
        if is_dataset(s):
            for c in read_index(s)["clips"]:
                p = clip_dir(s, c)
                for part in ("manifest.json", "frames"):  # a linked manifest is refused, never skipped as partial
                    check_no_links(p, p / part)
                if clip_state(p, int(c.get("frames_planned", 0)))[0] != "done":
                    continue
                if c.get("invalid"):
                    log.warning(f"{s}: clip {c.get('id')} left out of the export: {c['invalid']}")
                    continue
                out.append(p)
        else:
            out.append(s)
    return out


def frame_runs(frames) -> list[list[int]]:
    """Contiguous runs of ``frames`` ([1, 3, 4] -> [[1], [3, 4]]): a clip's motion points at frame - 1, so a gap
    (an interrupted shard run) starts a new sequence."""
    runs: list[list[int]] = []
    for f in sorted(frames):
        if runs and f == runs[-1][-1] + 1:
            runs[-1].append(f)
        else:
            runs.append([f])
    return runs


def check_clip(clip, fmt: str = "nss") -> None:
    """NssError (one line naming the clip and the fix) when ``clip`` cannot become a sequence of format ``fmt``
    that its consumer reads: the limits of ``format_limits.FORMATS`` (NSS: radiance, depth and motion, a finished
    frame and an LR level at ratio 2)."""
    check_clips(fmt, [clip], NssError)


def _exr_rgba(path: Path, rgb: np.ndarray) -> None:
    rgb = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=HALF_MAX), -HALF_MAX, HALF_MAX)
    write_exr(path, {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": np.ones(rgb.shape[:2])}, half=True)


def _exr_rg(path: Path, uv: np.ndarray) -> None:
    uv = np.clip(uv, -HALF_MAX, HALF_MAX)
    write_exr(path, {"R": uv[..., 0], "G": uv[..., 1]}, half=True)


def _exr_r32(path: Path, d: np.ndarray) -> None:
    write_exr(path, {"R": np.asarray(d, np.float32)}, half=False)


def clip_planes(clip) -> tuple[float, float]:
    """(near, far) of a clip's NSS sequences: enclosing every finite view depth of every level and frame."""
    levels = ["hr", *(clip.level_at(s) for s in clip.scales)]
    return cv.depth_planes(clip.read(f, f"{lvl}/depth")[..., 0] for f in clip.frames for lvl in levels)


def export_sequence(clip, frames: list[int], out, name: str, *, framerate: int = DEFAULT_FRAMERATE,
                    planes: tuple[float, float] | None = None) -> dict:
    """Write ``frames`` (contiguous) of ``clip`` as sequence ``name`` of the NSS capture at ``out``; returns the
    sequence JSON. The first frame is a camera cut."""
    out = Path(out)
    lr_levels = [clip.level_at(s) for s in clip.scales]
    ratios = [cv.ratio_name(s) for s in clip.scales]
    w_hr, h_hr = clip.sizes["hr"]
    near, far = planes or clip_planes(clip)
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
            w, h = clip.sizes[lvl]
            per_ratio.append(cv.normalized_jitter(clip.camera(f, lvl)["jitter"], w, h))
        cam_hr = clip.camera(f, "hr")
        fov_x, fov_y = cv.fov(cam_hr["intrinsics"], w_hr, h_hr)
        jit = clip.camera(f, lr_levels[0])["jitter"]
        records.append({
            "Frame": j, "FovX": fov_x, "FovY": fov_y, "CameraNearPlane": near, "CameraFarPlane": far,
            "ViewProjection": cv.matrix_to_list(cv.view_projection(cam_hr["world_from_camera"], cam_hr["intrinsics"],
                                                                   w_hr, h_hr, near, far, reverse_z=True)),
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
        "GTColorSpace": GT_COLOR_SPACE,
        "TargetResolution": {"X": w_hr, "Y": h_hr},
        "Samples": {"Sequence": "Halton" if jitter_mode == "halton" else "None",
                    "Count": HALTON_PERIOD if jitter_mode == "halton" else 1, "Quantized": False},
        "ReverseZ": False,
        "OpaqueOnlyColor_Exported": False,
        "UnjitteredSrcColor_Exported": False,
        "UpscalingRatiosIndices": {f"x{r}_index": i for i, r in enumerate(ratios)},
        "MotionVectorsDilated": False,
        "Frames": records,
        "BlendSR": {"clip": str(clip.path), "frames": [int(f) for f in frames],
                    "scales": [float(s) for s in clip.scales], "source_scene_linear": clip.scene_linear,
                    "colour_space": NSS_SPACE, "exposure": clip.exposure, "identity": clip.manifest.get("identity")},
    }
    write_json_atomic(out / f"{name}.json", meta)
    return meta


def export_clip(clip_path, out, seq: int, *, framerate: int = DEFAULT_FRAMERATE) -> list[dict]:
    """Write one BlendSR clip as sequences ``seq``, ``seq + 1``, ... (one per contiguous run of finished frames)
    of the NSS capture at ``out`` (written in place: ``export_nss`` is the command's safe path); returns their
    JSON."""
    clip = open_valid_clip(clip_path)
    check_clip(clip)
    planes = clip_planes(clip)
    return [export_sequence(clip, run, out, f"{seq + i:04d}", framerate=framerate, planes=planes)
            for i, run in enumerate(frame_runs(clip.frames))]


def sequence_names(out: Path) -> list[str]:
    """Names of the sequences of an NSS capture folder (its ``NNNN.json`` files), in order."""
    if not out.is_dir():
        return []
    return sorted((m.group(1) for p in out.iterdir() if (m := SEQUENCE_FILE.match(p.name)) and p.is_file()),
                  key=int)


def is_nss_export(out: Path) -> bool:
    return bool(sequence_names(out)) and (out / "motion_gt").is_dir()


def remove_orphan_sequences(out: Path) -> None:
    """Remove the sequence folders of ``out`` (``ground_truth/0003``, ``x2/color/0003``, ...) that have no
    ``0003.json``: an append killed while moving its files in. Never follows a link."""
    have = set(sequence_names(out))
    for p in sorted([*out.glob("*/*"), *out.glob("*/*/*")]):
        if p.is_dir() and not p.is_symlink() and re.fullmatch(r"\d{4,}", p.name) and p.name not in have:
            check_no_links(out, p)
            log.warning(f"{p}: removing a sequence folder without its JSON (an interrupted append)")
            shutil.rmtree(p)


def export_sequences(sources, out, options: ExportOptions, *, fmt: str, write_sequence,
                     is_export=is_nss_export) -> list[Path]:
    """The export loop NSS and NFRU share: the output rules (``formats.output.Target``), every clip checked
    (``check_clip``) before anything is written, one sequence per contiguous run of each clip's frames written by
    ``write_sequence(clip, frames, work, name, framerate=, planes=)``; ``is_export(folder)``: whether a folder
    holds an export of this format (``--append``); returns the sequence JSON paths."""
    options.validate()
    out = Path(out)
    target = Target(out, sources, options.mode, is_export=is_export, fmt=fmt)
    clips = [open_valid_clip(p) for p in source_clips(sources)]
    if not clips:
        raise NssError(f"{', '.join(map(str, sources))}: no finished clips to export")
    check_clips(fmt, clips, NssError)  # every limit of the consumer, before anything is written
    written: list[str] = []
    with target:  # holds OUT's lock when appending: the numbers below are this export's alone
        seq = 0
        if target.appending:
            remove_orphan_sequences(out)
            clean_temp_files(out)
            names = sequence_names(out)
            seq = int(names[-1]) + 1 if names else 0
        for clip in clips:
            runs = frame_runs(clip.frames)
            if len(runs) > 1:
                log.warning(f"{clip.path}: frames missing between {', '.join(f'{r[0]}-{r[-1]}' for r in runs)}: "
                            f"exported as {len(runs)} sequences, each starting with a camera cut")
            planes = clip_planes(clip)
            for run in runs:
                name = f"{seq:04d}"
                write_sequence(clip, run, target.work, name, framerate=options.framerate, planes=planes)
                written.append(name)
                seq += 1
            if options.progress:
                options.progress(clip.path, out / f"{written[-1]}.json")
        target.commit(last=tuple(f"{n}.json" for n in written))
    return [out / f"{n}.json" for n in written]


def export_nss(sources, out, options: ExportOptions = ExportOptions()) -> list[Path]:
    """Export every clip of ``sources`` (clip or dataset folders) as sequences 0000, 0001, ... of an NSS capture
    at ``out`` (one per clip, or one per contiguous run of a clip with missing frames), by the output rules of
    ``formats.output``; returns the sequence JSON paths. Every clip is checked before anything is written."""
    return export_sequences(sources, out, options, fmt="nss", write_sequence=export_sequence)


# ----------------------------------------------------------------------------------------------
# Reading an NSS capture
# ----------------------------------------------------------------------------------------------

def sequence_name(seq: str | int) -> str:
    """The name of sequence ``seq`` (an int becomes ``0003``); NssError for a name that is not one plain path
    component (``../x``, ``a/b``, ``.hidden``)."""
    name = f"{int(seq):04d}" if not isinstance(seq, str) else seq
    if not PLAIN_NAME.match(name) or name in (".", ".."):
        raise NssError(f"sequence {name!r}: not a sequence name (letters, digits, '_', '-', '.'; no folders)")
    return name


def capture_file(root, *parts: str) -> Path:
    """``root/parts...`` inside an NSS capture, by the rule every BlendSR reader follows: each part one plain name,
    and nothing on the way (the file itself included) a symbolic link (``clip.check_no_links``; ``root`` itself
    may be one, the user chose it)."""
    root = Path(root)
    for part in parts:
        if not part or part in (".", "..") or "/" in part or "\\" in part or "\x00" in part:
            raise NssError(f"{root}: {'/'.join(parts)!r} is not a path inside the capture")
    return check_no_links(root, root.joinpath(*parts))


def _finite(p: Path, key: str, v, *, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        what = "a positive finite number" if positive else "a finite number"
        raise NssError(f"{p}: {key} = {v!r:.40} is not {what}")
    return float(v)


def _whole(p: Path, key: str, v) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise NssError(f"{p}: {key} = {v!r:.40} is not a positive whole number")
    return v


def read_sequence_meta(root, seq: str | int) -> dict:
    """The checked JSON of sequence ``seq`` (``check_sequence_meta``); NssError naming the file otherwise."""
    p = capture_file(root, f"{sequence_name(seq)}.json")
    if not p.is_file():
        raise NssError(f"{p}: no such NSS sequence")
    try:
        meta = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise NssError(f"{p}: not valid JSON ({exc})") from None
    return check_sequence_meta(p, meta)


def sequence_ratios(meta: dict, p: Path | str = "sequence JSON") -> dict[str, int]:
    """{ratio name ('2', '2_5'): index into NormalizedPerRatioJitter}; NssError naming ``p`` for a key that is not
    ``x<ratio>_index`` (a ratio > 1 such as 2 or 1_5) or an index that is not a whole number >= 0."""
    raw = meta.get("UpscalingRatiosIndices", {"x2_index": 0})
    if not isinstance(raw, dict) or not raw:
        raise NssError(f"{p}: UpscalingRatiosIndices is not an object of x<ratio>_index keys")
    out = {}
    for k, v in raw.items():
        m = RATIO_KEY.match(k)
        if not m or not ratio_value(m.group(1)) > 1:
            raise NssError(f"{p}: UpscalingRatiosIndices key {k!r:.60} is not x<ratio>_index with a ratio > 1 "
                           "(x2_index, x1_5_index)")
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise NssError(f"{p}: UpscalingRatiosIndices.{k} = {v!r:.40} is not a whole number >= 0")
        out[m.group(1)] = v
    return out


def ratio_value(name: str) -> float:
    return float(name.replace("_", "."))


def _check_frame(p: Path, j: int, rec, ratios: dict[str, int], size: tuple[int, int]) -> None:
    key = f"Frames[{j}]"
    if not isinstance(rec, dict):
        raise NssError(f"{p}: {key} is not an object")
    near = _finite(p, f"{key}.CameraNearPlane", rec.get("CameraNearPlane"), positive=True)
    if rec.get("CameraFarPlane") == -1:
        raise NssError(f"{p}: {key} has an infinite far plane (CameraFarPlane = -1), which this reader does not "
                       "convert")
    far = _finite(p, f"{key}.CameraFarPlane", rec.get("CameraFarPlane"), positive=True)
    if far <= near:
        raise NssError(f"{p}: {key}: CameraFarPlane {far:g} is not beyond CameraNearPlane {near:g}")
    vp = rec.get("ViewProjection")
    if not isinstance(vp, list) or len(vp) != 16:
        raise NssError(f"{p}: {key}.ViewProjection is not a list of 16 numbers")
    for i, v in enumerate(vp):
        _finite(p, f"{key}.ViewProjection[{i}]", v)
    m = cv.list_to_matrix(vp)
    n = float(np.linalg.norm(m[3, :3]))
    if not abs(n - 1.0) < 1e-3:
        raise NssError(f"{p}: {key}.ViewProjection is not the projection of a rigid camera (its last row's "
                       f"direction has length {n:.3g}, not 1)")
    with np.errstate(all="ignore"):
        try:
            wfc, k = cv.camera_from_view_projection(m, *size)
        except np.linalg.LinAlgError:
            wfc, k = None, (0.0,)
    if wfc is None or not np.all(np.isfinite(wfc)) or not np.all(np.isfinite(k)) or min(k[0], k[1]) <= 0:
        raise NssError(f"{p}: {key}.ViewProjection gives no camera (degenerate projection)")
    jit = rec.get("NormalizedPerRatioJitter")
    if not isinstance(jit, list):
        raise NssError(f"{p}: {key}.NormalizedPerRatioJitter is not a list")
    for r, idx in ratios.items():
        e = jit[idx] if idx < len(jit) else None
        if not isinstance(e, dict):
            raise NssError(f"{p}: {key}.NormalizedPerRatioJitter[{idx}] (ratio x{r}) is missing")
        for c in ("X", "Y"):
            _finite(p, f"{key}.NormalizedPerRatioJitter[{idx}].{c}", e.get(c))


def check_sequence_meta(p: Path, meta) -> dict:
    """``meta`` (the JSON of ``p``) when it holds what ``nss_to_clip`` reads, each value of the right type and
    range: TargetResolution, UpscalingRatiosIndices, per frame the planes, a rigid camera's ViewProjection and
    finite jitter for every ratio; the memory one frame takes is checked against what is available. NssError
    naming the file and key otherwise, before anything is allocated or written."""
    from ..resources import available_memory, human
    if not isinstance(meta, dict):
        raise NssError(f"{p}: not an NSS sequence (the JSON is not an object)")
    tr = meta.get("TargetResolution")
    if not isinstance(tr, dict):
        raise NssError(f"{p}: TargetResolution is missing (an object {{X, Y}} of the ground truth's size)")
    w, h = _whole(p, "TargetResolution.X", tr.get("X")), _whole(p, "TargetResolution.Y", tr.get("Y"))
    need = IMPORT_BYTES_PER_HR_PIXEL * w * h
    have = available_memory()
    if have is not None and need > have:
        raise NssError(f"{p}: TargetResolution {w}x{h}: importing needs about {human(need)} of memory per frame "
                       f"and {human(have)} is available")
    ratios = sequence_ratios(meta, p)
    try:
        levels_header((w, h), sorted(ratio_value(r) for r in ratios))
    except ValueError as exc:
        raise NssError(f"{p}: TargetResolution {w}x{h} and the ratios {', '.join(ratios)}: {exc}") from None
    frames = meta.get("Frames")
    if not isinstance(frames, list) or not frames:
        raise NssError(f"{p}: Frames is not a non-empty list")
    for j, rec in enumerate(frames):
        _check_frame(p, j, rec, ratios, (w, h))
    return meta


def _frame_files(root: Path, name: str, j: int, ratios) -> dict[str, Path]:
    fn = f"{j:04d}.exr"
    files = {"hr/radiance": capture_file(root, "ground_truth", name, fn),
             "hr/motion": capture_file(root, "motion_gt", name, fn)}
    for r in ratios:
        for b, folder in (("radiance", "color"), ("depth", "depth"), ("motion", "motion")):
            files[f"{r}/{b}"] = capture_file(root, f"x{r}", folder, name, fn)
    return files


def check_capture_files(root, seq: str | int, meta: dict) -> None:
    """Every EXR sequence ``seq`` needs exists (no link on the way) with the size its level has (headers only):
    NssError naming the first file that does not, before anything is read or written."""
    root, name = Path(root), sequence_name(seq)
    ratios = sequence_ratios(meta)
    w, h = meta["TargetResolution"]["X"], meta["TargetResolution"]["Y"]
    sizes = {r: tuple(v) for r, v in zip(sorted(ratios, key=ratio_value),
                                          ((lv["width"], lv["height"]) for lv in
                                           list(levels_header((w, h), sorted(ratio_value(r) for r in ratios))
                                                .values())[1:]))}
    for j in range(len(meta["Frames"])):
        for key, path in _frame_files(root, name, j, ratios).items():
            if not path.is_file():
                raise NssError(f"{path}: missing (frame {j} of sequence {name} needs it)")
            want = (w, h) if key.startswith("hr/") else sizes[key.split("/")[0]]
            got = exr_size(path)
            if tuple(got) != tuple(want):
                raise NssError(f"{path}: is {got[0]}x{got[1]}, the sequence's JSON makes it {want[0]}x{want[1]}")


def read_frame(root, seq: str | int, j: int, meta: dict | None = None) -> dict:
    """Frame ``j`` of sequence ``seq`` in BlendSR's conventions: ``hr/radiance``, ``hr/motion`` (pixels,
    p_prev = p + motion) and per ratio name r ``<r>/radiance``, ``<r>/depth`` (view depth, +inf at the far
    plane), ``<r>/motion``, ``<r>/jitter`` (pixels), plus ``world_from_camera`` and ``intrinsics`` (HR) and
    ``near``, ``far``. ``meta``: the sequence's checked JSON (``read_sequence_meta``)."""
    root = Path(root)
    meta = meta or read_sequence_meta(root, seq)
    name = sequence_name(seq)
    rec = meta["Frames"][j]
    near, far = float(rec["CameraNearPlane"]), float(rec["CameraFarPlane"])
    ratios = sequence_ratios(meta)
    files = _frame_files(root, name, j, ratios)
    out = {"near": near, "far": far,
           "hr/radiance": read_exr(files["hr/radiance"], ("R", "G", "B")),
           "hr/motion": cv.uv_to_motion(read_exr(files["hr/motion"], ("R", "G")))}
    w, h = meta["TargetResolution"]["X"], meta["TargetResolution"]["Y"]
    wfc, k = cv.camera_from_view_projection(cv.list_to_matrix(rec["ViewProjection"]), w, h)
    out["world_from_camera"], out["intrinsics"] = wfc, k
    for r, idx in ratios.items():
        d = read_exr(files[f"{r}/depth"], ("R",))[..., 0]
        if meta.get("ReverseZ"):
            d = 1.0 - d
        out[f"{r}/radiance"] = read_exr(files[f"{r}/radiance"], ("R", "G", "B"))
        out[f"{r}/depth"] = cv.device_to_view_depth(d, near, far)
        out[f"{r}/motion"] = cv.uv_to_motion(read_exr(files[f"{r}/motion"], ("R", "G")))
        lh, lw = d.shape
        nj = rec["NormalizedPerRatioJitter"][idx]
        out[f"{r}/jitter"] = (nj["X"] * lw, nj["Y"] * lh)
    return out


def upsample_depth(d_lr: np.ndarray, jitter, size: tuple[int, int]) -> np.ndarray:
    """HR view depth (``size`` W x H) from an LR level's depth sampled at each LR pixel centre + ``jitter`` (LR
    pixels): inverse depth interpolated bilinearly between the four LR samples around each HR pixel centre (exact
    on a plane, whose inverse depth is linear on screen); nearest where those four straddle an edge (depths more
    than 25 % apart) or the background."""
    w, h = size
    lh, lw = d_lr.shape
    d = np.asarray(d_lr, np.float64)
    fx = (np.arange(w) + 0.5) * lw / w - 0.5 - float(jitter[0])
    fy = (np.arange(h) + 0.5) * lh / h - 0.5 - float(jitter[1])
    x0, y0 = np.clip(np.floor(fx).astype(int), 0, lw - 1), np.clip(np.floor(fy).astype(int), 0, lh - 1)
    x1, y1 = np.minimum(x0 + 1, lw - 1), np.minimum(y0 + 1, lh - 1)
    ax, ay = np.clip(fx - x0, 0, 1)[None, :], np.clip(fy - y0, 0, 1)[:, None]
    corners = [d[np.ix_(yy, xx)] for yy in (y0, y1) for xx in (x0, x1)]
    with np.errstate(all="ignore"):
        inv = [np.where(np.isfinite(c) & (c > 0), 1.0 / c, 0.0) for c in corners]
        lin = 1.0 / ((inv[0] * (1 - ax) + inv[1] * ax) * (1 - ay) + (inv[2] * (1 - ax) + inv[3] * ax) * ay)
        lo, hi = np.minimum.reduce(corners), np.maximum.reduce(corners)
        smooth = np.isfinite(hi) & (lo > 0) & (hi <= lo * 1.25)
    nx = np.clip(np.round(fx).astype(int), 0, lw - 1)
    ny = np.clip(np.round(fy).astype(int), 0, lh - 1)
    return np.where(smooth, lin, d[np.ix_(ny, nx)]).astype(np.float32)


def nss_to_clip(root, seq: str | int, out) -> Path:
    """Write NSS sequence ``seq`` as a BlendSR clip at ``out`` (buffers radiance, depth, motion; one LR level per
    ratio). NSS has no HR depth: ``hr/depth`` is interpolated from the first LR level's (``upsample_depth``; the
    manifest's ``imported.hr_depth`` says so). A camera cut (the first frame, and every frame whose ``CameraCut``
    is true; ``imported.camera_cuts``) has nothing before it: its previous camera is its own and its motion is
    zero, whatever the file holds (an export's first frame points at a frame it does not hold). A frame's
    ``Exposure`` (when given) multiplies its colour: the clip holds exposed radiance, at exposure 1. The JSON and
    every file are checked (``check_sequence_meta``, ``check_capture_files``) before the clip is created."""
    root = Path(root)
    meta = read_sequence_meta(root, seq)
    check_capture_files(root, seq, meta)
    ratios = sequence_ratios(meta)
    names = sorted(ratios, key=ratio_value)
    scales = [ratio_value(r) for r in names]
    w, h = meta["TargetResolution"]["X"], meta["TargetResolution"]["Y"]
    header = _nss_header(root, seq, meta, levels_header((w, h), scales))
    cuts = header["imported"]["camera_cuts"]
    prev = None
    with ClipWriter(out, header) as wr:
        for j in header["frames"]:
            fr = _exposed_frame(root, seq, j, meta)
            record = {}
            cam = (fr["world_from_camera"], fr["intrinsics"])
            cut = j in cuts
            pcam = cam if cut else prev
            for lvl, info in header["levels"].items():
                f = info["width"] / w
                bufs, jit = _level_buffers(fr, lvl, info, names, scales, (w, h))
                if cut:  # nothing before it in the sequence: no motion (the previous camera is its own)
                    bufs["motion"] = np.zeros_like(bufs["motion"])
                for b, arr in bufs.items():
                    wr.write_buffer(j, lvl, b, arr)
                record[lvl] = {"world_from_camera": cam[0], "prev_world_from_camera": pcam[0],
                               "intrinsics": tuple(v * f for v in cam[1]),
                               "prev_intrinsics": tuple(v * f for v in pcam[1]), "jitter": [float(x) for x in jit],
                               "spp": 1, "seed": 0, "seconds": {}}
            wr.commit_frame(j, record)
            prev = cam
    return Path(out)


def _nss_header(root: Path, seq, meta: dict, levels: dict) -> dict:
    """The manifest header of an imported NSS sequence: its levels, frames, the buffers NSS holds, its camera cuts
    (the first frame and every ``CameraCut``) and where it came from."""
    frames = list(range(len(meta["Frames"])))
    samples = meta.get("Samples")
    return {
        "blendsr_version": "imported-nss", "blender_version": None,
        "scene": {"file": None, "sha256": None, "builtin": None, "nss": str(root), "sequence": str(seq)},
        "scale": scale_value(levels["lr"]["scale"]), "levels": levels, "frames": frames,
        "buffers": ["radiance", "depth", "motion"], "fbeta_source": None, "scene_linear": NSS_SPACE,
        "render": {"jitter": "halton" if isinstance(samples, dict) and samples.get("Sequence", "None") != "None"
                   else "none",
                   "hr": {}, "lr": {}},
        "materials": {}, "material_summary": {},
        "imported": {"format": "nss", "version": meta.get("Version"), "hr_depth": "interpolated-from-lr",
                     "camera_cuts": [j for j in frames if j == 0 or meta["Frames"][j].get("CameraCut") is True]},
    }


def _exposed_frame(root: Path, seq, j: int, meta: dict) -> dict:
    """Frame ``j``'s arrays with its ``Exposure`` (default 1) applied to every radiance; NssError when the exposure
    is not a positive number."""
    fr = read_frame(root, seq, j, meta)
    exposure = meta["Frames"][j].get("Exposure", 1.0)
    if isinstance(exposure, bool) or not isinstance(exposure, (int, float)) or not 0 < exposure < float("inf"):
        raise NssError(f"{root / f'{int(seq):04d}.json' if not isinstance(seq, str) else root / f'{seq}.json'}: "
                       f"Frames[{j}].Exposure {exposure!r} is not a positive number")
    return {k: a * np.float32(exposure) if k.endswith("/radiance") else a for k, a in fr.items()}


def _level_buffers(fr: dict, lvl: str, info: dict, names: list[str], scales: list[float], hr_size) -> tuple:
    """One level's radiance, depth and motion, and its jitter: HR depth interpolated from the first LR level's."""
    if lvl == "hr":
        return {"radiance": fr["hr/radiance"], "motion": fr["hr/motion"],
                "depth": upsample_depth(fr[f"{names[0]}/depth"], fr[f"{names[0]}/jitter"], hr_size)}, (0.0, 0.0)
    r = names[scales.index(info["scale"])]
    return {b: fr[f"{r}/{b}"] for b in ("radiance", "depth", "motion")}, fr[f"{r}/jitter"]


__all__ = ["export_nss", "export_clip", "export_sequence", "check_clip", "frame_runs", "read_frame",
           "read_sequence_meta", "check_sequence_meta", "check_capture_files", "nss_to_clip", "source_clips",
           "NssError"]
