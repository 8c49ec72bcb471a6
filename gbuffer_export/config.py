"""Typed, validated render configuration (pure Python). The CLI, the add-on, dataset jobs and tests build a
``RenderConfig`` (the one render-settings class: one set of defaults) and hand it to
``gbuffer_export.blender.render.render_clip``. Each key's type and range are its annotation and ``option(...)`` rule
(``gbuffer_export.typed_table``); messages name the key (``hr_spp``), and the CLI puts its flag (``--hr-spp``) in
their place (``gbuffer_export.commands.render``)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from .conventions import DEFAULT_BUFFERS, check_level_sizes, parse_buffer_list, parse_exposure, scale_fraction
from .scene_formats import SCENE_SUFFIXES, formats_text
from .typed_table import ConfigError, key_error, legacy_values, option, set_checked

CAMERA_PATHS = ("scene", "orbit", "walk", "fly")  # also scene:NAME and scene:* (the file's own cameras)
#: Generated paths that move inside a level (``gbuffer_export.blender.level_cameras``).
LEVEL_CAMERA_PATHS = ("walk", "fly")
LIGHTS = ("auto", "scene", "sky")
#: ``materials``: keep the scene's materials, or replace every image texture by its image's mean (a grey-box look:
#: ``gbuffer_export.blender.materials.make_untextured``).
MATERIAL_MODES = ("keep", "untextured")
DEVICES = ("auto", "cpu", "cuda", "optix", "hip", "metal", "oneapi")
#: ``unit_scale``'s names for common units (metres per unit); "auto" detects the unit from the level's geometry
#: (``gbuffer_export.blender.level_scale``, docs/rendering.md "A level's unit").
UNIT_NAMES = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}


def camera_path_ok(value: str) -> bool:
    """``value`` is one of CAMERA_PATHS, ``scene:*`` or ``scene:NAME``."""
    return value in CAMERA_PATHS or (value.startswith("scene:") and len(value) > len("scene:"))
JITTERS = ("none", "halton")
FBETA_SOURCES = ("cycles", "lut", "lut-paper", "model")
#: The HR F_beta of the 'cycles' source: 'point' (the default: point-sampled like the other G-buffers and like a
#: game engine's G-buffer at run time; what the shipped weights were trained on) or 'footprint' (the colour passes
#: filtered like the ground truth, away from background: no sub-pixel texture aliases into L_D; docs/brdf.md,
#: "Sub-pixel texture").
HR_FBETA = ("point", "footprint")
#: What the G-buffers describe where a transmissive surface (glass, water: ``materials.is_transmissive``) is the first
#: hit: 'surface' (the default: the first surface, glass included) or 'behind' (the first surface that is not
#: transmissive, as a game's deferred G-buffer holds only opaque geometry; the ``flags`` buffer keeps TRANSMISSION
#: there as the reactive mask; docs/rendering.md, "Transmissive surfaces").
GBUFFER_TRANSMISSION = ("surface", "behind")


#: Cycles' cap on samples per pixel (2^24): a larger request would be rendered at the cap and recorded wrongly.
MAX_SPP = 16_777_216
#: Blender's smallest render size in pixels (a side under it is rendered at 4 px, not at the size asked).
MIN_RENDER_PX = 4


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """'A:B' (inclusive) -> (A, B); None or '' -> None (the scene's range)."""
    if not text:
        return None
    a, sep, b = text.partition(":")
    try:
        start, end = int(a), int(b) if sep else int(a)
    except ValueError:
        raise key_error("frames", text, "expected A:B with integers, e.g. 1:48") from None
    if end < start:
        raise key_error("frames", text, f"end {end} is before start {start}")
    return start, end


def parse_size(text: str | None) -> tuple[int, int] | None:
    """'WxH' -> (W, H); None -> None (the scene's resolution)."""
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise key_error("hr_size", text, "expected WxH, e.g. 640x360") from None
    if w <= 0 or h <= 0:
        raise key_error("hr_size", text, "width and height must be positive")
    return w, h


def parse_scales(text: str | None) -> tuple[float, ...] | None:
    """'2,2.5,4' -> (2.0, 2.5, 4.0); None or '' -> None (only ``--scale``)."""
    if not text:
        return None
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise key_error("scales", text, "expected comma-separated numbers, e.g. 2,2.5,4") from None


def parse_shard(text: str | None) -> tuple[int, int]:
    """'K/N' (1-based K) -> (K, N); None -> (1, 1)."""
    if not text:
        return 1, 1
    try:
        k, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise key_error("shard", text, "expected K/N, e.g. 2/4") from None
    if not (n >= 1 and 1 <= k <= n):
        raise key_error("shard", text, "need 1 <= K <= N")
    return k, n


#: Frames the built-in default scene is defined on (inclusive): its animation (camera arc with a period of 160-240
#: frames, rolling ball) is keyed from start - 1, so frame 0 has no previous frame; 1000 frames (42 s at 24 fps) bound
#: what one clip of it may cost. Rendered by default: 1:48.
BUILTIN_SCENE_FRAMES = (1, 1000)


def check_builtin_frames(frames: tuple[int, int] | None) -> None:
    """ConfigError (one line) when ``frames`` lie outside ``BUILTIN_SCENE_FRAMES``; None (the default 1:48) passes.
    Called where the built-in scene is chosen (``blendsr render`` without a scene, ``load_scene``), not by
    ``RenderConfig`` itself: ``scene=None`` there also stands for a scene already open (the add-on, dataset jobs)."""
    if frames is None:
        return
    (a, b), (lo, hi) = frames, BUILTIN_SCENE_FRAMES
    if a < lo or b > hi:
        detail = f"{a}:{b} is outside the built-in scene's range {lo}:{hi}"
        raise ConfigError(f"frames {detail}", key="frames", detail=detail)


#: The shells that derive a key from its field (``Rule.shells``; gbuffer_export.table_shells).
CLI, SPEC, CLIP_PANEL, DATASET_PANEL = "cli", "spec", "clip_panel", "dataset_panel"
SHELLS = (CLI, SPEC, CLIP_PANEL, DATASET_PANEL)

#: Why the sample counts stop at MAX_SPP (appended to their range message).
_SPP_CAP = "(Cycles' cap on samples per pixel)"


@dataclass
class RenderConfig:
    """Everything ``render_clip`` needs. Sizes in pixels, sample counts per pixel, adaptive threshold is
    Cycles' noise threshold (0 = automatic)."""

    # Each key's option(...) holds its type rule, default, help, unit and the shells that derive it (``CLI``:
    # ``blendsr render``'s flag; ``SPEC``: a dataset spec's ``[render]`` key; ``CLIP_PANEL``/``DATASET_PANEL``: the
    # add-on's clip and dataset settings). ``shells=()``: every shell writes the key by hand (a parsed value such as
    # ``frames``, or one the job supplies). Adding a key here adds it to each shell (gbuffer_export.table_shells).
    output: Path = option(help="clip directory to create or resume", shells=())
    scene: Path | None = option(None, shells=(), help="the scene: any format of docs/rendering.md's table (.blend, glTF, USD, OBJ, FBX, ...; kept as it is: world, "
                                "lights, materials, animation); None: the built-in default scene")
    frames: tuple[int, int] | None = option(None, shells=(), metavar="A:B", help="inclusive frame range; None: the "
                                            "scene's range (built-in scene: 1:48, at most 1:1000)")
    hr_size: tuple[int, int] | None = option(None, shells=(SPEC,), metavar="WxH", unit="pixels",
                                             help="HR (target) resolution in pixels; None: the scene's "
                                                  "resolution (default scene: 640x360)")
    scale: int | float = option(4, shells=(SPEC,), help="upscaling factor of the level 'lr'; LR = HR / scale")
    scales: tuple[float, ...] | None = option(
        None, shells=(SPEC,), metavar="S1,S2,...",
        help="several LR levels, one LR render each (numbers >= 1 such as 2,2.5,4, where HR width and height divided "
             "by each are integers): the first is the level 'lr', the others 'lr_x<s>'; replaces scale")
    hr_spp: int = option(64, lo=1, hi=MAX_SPP, why=_SPP_CAP, unit="samples per pixel", label="HR samples",
                         help="samples per pixel of the HR ground truth")
    lr_spp: int = option(4, lo=1, hi=MAX_SPP, why=_SPP_CAP, unit="samples per pixel", label="LR samples",
                         help="samples per pixel of the LR render")
    gbuffer_spp: int = option(4, lo=1, hi=MAX_SPP, why=_SPP_CAP, unit="samples per pixel", label="G-buffer samples",
                              help="samples per pixel of the HR G-buffer pass (all within 0.01 px of the pixel "
                                   "centre)")
    hr_denoise: bool = option(False, label="Denoise HR", help="denoise the HR ground truth with OpenImageDenoise")
    lr_denoise: bool = option(False, label="Denoise LR", help="denoise the LR render with OpenImageDenoise (as a "
                                                               "real-time denoiser would)")
    adaptive: bool = option(False, shells=(CLI, CLIP_PANEL), label="Adaptive HR",
                            help="adaptive sampling for the HR ground truth (hr_spp becomes the maximum)")
    adaptive_threshold: float = option(0.01, lo=0, hi=1, hi_open=True, shells=(CLI, CLIP_PANEL),
                                       label="Noise threshold", help="Cycles' adaptive noise threshold")
    adaptive_min_samples: int = option(0, lo=0, shells=(CLI, CLIP_PANEL), label="Min samples",
                                       unit="samples per pixel", help="adaptive minimum samples (0 = automatic)")
    camera_path: str = option("scene", shells=(CLI,), metavar="KIND", label="Camera path", help=(
        "scene: the file's active camera; scene:NAME: the camera NAME; scene:*: the active camera, else the first by "
        "name; walk: an eye 1.6 m above the floor walking at 1.4 m/s inside the level; fly: a free path at 3 m/s "
        "inside the level (both keep 0.25 m from every triangle and look at content; docs/rendering.md); orbit: an "
        "arc around the scene's bounds (the built-in scene's walk is a loop framed from its bounds)"))
    light: str = option("auto", choices=LIGHTS, shells=(CLI, CLIP_PANEL), help=(
        "auto: the file's own lights where they light what the cameras see (measured by a probe render), else a sun "
        "and sky where the cameras see the sky and lamps under the ceilings where they do not; scene: the file's own "
        "lights (an unlit scene is refused); sky: add a sun lamp and a physical sky, sun direction drawn from seed "
        "(all recorded in the manifest; docs/rendering.md)"))
    materials: str = option("keep", choices=MATERIAL_MODES, label="Materials", help=(
        "keep: the scene's materials as they are; untextured: every image texture of every material replaced by its "
        "image's mean (colour images averaged in linear light, weighted by alpha; normal maps flat; alpha kept), so "
        "geometry, light and constant material values stay and texture detail goes (a grey-box level; recorded in "
        "the manifest's material_mode)"))
    exposure: float | str = option("auto", unit="'auto' or a multiplier of the radiance (1: as rendered)",
                                   metavar="auto|X", help=(
        "the clip's exposure, as a game camera's: auto (the log-average luminance of the clip's HR frames brought to "
        "0.18 unless already within 0.05-1.5, clamped to 2^-16..2^20) or a multiplier; radiance is stored physical "
        "and the manifest records the exposure that every reader applies (docs/clip-format.md, \"Exposure\")"))
    device: str = option("auto", choices=DEVICES, shells=(CLI, CLIP_PANEL),
                         help="Cycles device: auto uses a GPU when Cycles sees one (OptiX, CUDA, HIP, Metal, oneAPI), "
                              "else the CPU; the device and its name go into the manifest")
    seed: int = option(0, shells=(CLI, CLIP_PANEL), help="seed of the default scene, camera paths and Cycles noise")
    jitter: str = option("halton", choices=JITTERS,
                         help="sub-pixel jitter of the LR frames (Halton 2,3, period 16), in LR pixels")
    buffers: tuple[str, ...] = option(DEFAULT_BUFFERS, shells=(SPEC,), help=(
        "the buffers to write: names, 'default' or 'all' (docs/clip-format.md); radiance is always written"))
    fbeta: str = option("cycles", choices=FBETA_SOURCES, label="F_beta source", help=(
        "source of the pre-integrated BRDF: Cycles' colour passes, the split-sum table (lut), the papers' literal "
        "table (lut-paper), or a model of Cycles' Principled BSDF"))
    hr_fbeta: str = option("footprint", choices=HR_FBETA, label="HR F_beta", legacy="point", help=(
        "HR F_beta of fbeta cycles: the colour passes filtered like the ground truth (footprint: no sub-pixel texture "
        "in L_D; the shipped weights' data) or point-sampled like the other G-buffers (point: every clip before "
        "2026-11-26)"))
    gbuffer_transmission: str = option("surface", choices=GBUFFER_TRANSMISSION, label="G-buffer at glass", help=(
        "what every G-buffer describes where a transmissive surface (Principled transmission > 0, Glass or Refraction "
        "BSDF) is seen first: surface (the glass itself) or behind (the first non-transmissive surface behind it, as "
        "a deferred renderer's G-buffer; flags keep TRANSMISSION there as the reactive mask; radiance unchanged; "
        "docs/rendering.md)"))
    shard: tuple[int, int] = option((1, 1), shells=(), metavar="K/N",
                                    help="render every N-th frame starting with the K-th")
    only_frames: tuple[int, ...] | None = option(None, shells=(), help=(
        "render only these frames of the range (camera path and jitter indices stay the range's); None: every frame "
        "of the shard"))
    max_bounces: int | None = option(None, lo=0, shells=(CLI,), label="Max bounces",
                                     help="override the scene's total light bounces (none: the scene's own)")
    unit_scale: str | float = option("auto", lo=0, lo_open=True, unit="metres per scene unit", label="Unit scale",
                                     metavar="auto|M|UNIT", help=(
        "the level's unit for walk and fly cameras (eye height, speeds, clearance): auto (detected from the "
        "geometry: docs/rendering.md, \"A level's unit\"), metres per scene unit (e.g. 0.01), or m, cm, mm, in, ft"))
    threads: int = option(0, lo=0, shells=(CLI, SPEC, CLIP_PANEL),
                          help="render threads (0 = OMP_NUM_THREADS where set, else all cores)")
    allow_read: tuple[str, ...] = option((), shells=(SPEC,), help=(
        "folders besides the scene's own that its files may read (textures, buffers, libraries); the files read "
        "there are listed in the manifest (docs/rendering.md, \"What a scene file may read\")"))
    progress: bool = option(True, shells=(), help="a progress bar")
    extra: dict = option(factory=dict, shells=(), help="what a shell adds for the scene (a dataset clip's region, "
                                                       "camera index and light variation)")

    def __post_init__(self):
        self.output = Path(self.output)
        if self.scene is not None:
            self.scene = Path(self.scene)
        self.validate()

    def validate(self) -> None:
        self._check_scales()
        if isinstance(self.buffers, str):
            self.buffers = parse_buffer_list(self.buffers)
        else:
            self.buffers = parse_buffer_list(",".join(self.buffers))
        if not camera_path_ok(self.camera_path):
            raise key_error("camera_path", self.camera_path,
                            f"choose one of {', '.join(CAMERA_PATHS)}, scene:NAME or scene:*")
        set_checked(self, names=[f.name for f in dataclasses.fields(self)
                                 if f.name not in ("output", "scene", "scale", "scales", "buffers", "extra")])
        try:
            self.exposure = parse_exposure(self.exposure)
        except ValueError as exc:
            raise key_error("exposure", self.exposure, str(exc)) from None
        self._check_only_frames()
        self._check_unit_scale()
        if self.hr_size is not None:
            self.check_size(self.hr_size, "hr_size")
        if self.scene is not None:
            if self.scene.is_dir():
                raise ConfigError(f"{self.scene}: is a folder, not a scene file")
            if not self.scene.is_file():
                raise ConfigError(f"{self.scene}: scene file not found")
            if self.scene.suffix.lower() not in SCENE_SUFFIXES:
                raise ConfigError(f"{self.scene}: not a scene file (one of {formats_text()})")

    def _check_unit_scale(self) -> None:
        """``unit_scale``: "auto", a finite number > 0 (metres per scene unit; a number in a string, as a command
        line gives it, is read as one) or a unit of ``UNIT_NAMES`` (stored as its metres)."""
        v = self.unit_scale
        if isinstance(v, str) and v != "auto":
            if v.strip().lower() in UNIT_NAMES:
                v = UNIT_NAMES[v.strip().lower()]
            else:
                try:
                    v = float(v)
                except ValueError:
                    raise key_error("unit_scale", v, "expected auto, metres per scene unit (a number > 0, e.g. "
                                    f"0.01) or one of {', '.join(UNIT_NAMES)}") from None
            self.unit_scale = v
            set_checked(self, names=["unit_scale"])

    def _check_scales(self) -> None:
        """``scales`` as floats (default: ``(scale,)``), each a ratio of integers >= 1, none twice; ``scale`` the
        first (an int when whole)."""
        if self.scales is None:
            self.scales = (self.scale,)
        key = "scales" if len(self.scales) > 1 else "scale"
        for v in self.scales:
            try:
                scale_fraction(v)
            except ValueError:
                raise key_error(key, v, "must be a number >= 1 (a ratio of integers such as 2, 2.5 or 4)") from None
        if len(set(float(v) for v in self.scales)) != len(self.scales):
            text = ",".join(f"{v:g}" for v in self.scales)
            raise ConfigError(f"{key} {text}: a scale is given twice", key=key, detail=f"{text}: a scale is given twice")
        self.scales = tuple(float(v) for v in self.scales)
        self.scale = int(self.scales[0]) if self.scales[0].is_integer() else self.scales[0]

    def _check_only_frames(self) -> None:
        """``only_frames`` sorted, none twice, inside ``frames`` when that is given (the scene's range is checked
        once the scene is loaded, ``check_frames_subset``)."""
        if self.only_frames is None:
            return
        text = ",".join(str(f) for f in self.only_frames)
        if not self.only_frames:
            raise key_error("only_frames", text, "no frame given (None renders every frame)")
        if len(set(self.only_frames)) != len(self.only_frames):
            raise key_error("only_frames", text, "a frame is given twice")
        self.only_frames = tuple(sorted(self.only_frames))
        if self.frames is not None:
            self.check_frames_subset(range(self.frames[0], self.frames[1] + 1))

    def check_frames_subset(self, frames: Sequence[int]) -> None:
        """ConfigError naming ``only_frames`` when one of them is not among ``frames`` (the clip's range)."""
        outside = [f for f in self.only_frames or () if f not in frames]
        if outside:
            detail = f"frame {outside[0]} is outside the range {frames[0]}:{frames[-1]}"
            raise key_error("only_frames", ",".join(str(f) for f in self.only_frames), detail)

    def my_frames(self, frames: Sequence[int]) -> Sequence[int]:
        """The frames of ``frames`` (the clip's whole range, in order) this process renders: every N-th from the
        K-th (``shard`` K/N), and of those only ``only_frames`` when given. A range stays a range (not listed)."""
        mine = frames[self.shard[0] - 1::self.shard[1]]
        if self.only_frames is None:
            return mine
        return [f for f in self.only_frames if f in mine]

    def check_size(self, hr_size: tuple[int, int], what: str) -> dict[float, tuple[int, int]]:
        """{scale: LR size} of every scale; ConfigError naming ``what`` and the nearest valid sizes otherwise."""
        try:
            sizes = check_level_sizes(hr_size, self.scales, what)
        except ValueError as exc:
            raise ConfigError(str(exc), key=what, detail=str(exc)[len(what) + 1:]) from None
        for s, (w, h) in sizes.items():
            if min(w, h) < MIN_RENDER_PX:
                detail = (f"{hr_size[0]}x{hr_size[1]} at scale {s:g} gives an LR frame of {w}x{h}: Blender renders "
                          f"no side under {MIN_RENDER_PX} pixels (use a larger size or a smaller scale)")
                raise ConfigError(f"{what} {detail}", key=what, detail=detail)
        return sizes

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["output"] = str(self.output)
        d["scene"] = str(self.scene) if self.scene else None
        return d


#: The keys of ``RenderConfig`` that the manifest's header writes by hand (``render._manifest_header``: sizes, samples,
#: camera, light, materials, buffers, F_beta ...) or that do not change what a clip holds (where it is written,
#: threads, the progress bar, shards). Every key added after these is recorded by ``recorded_keys`` from its rule:
#: do not add a new key here.
MANIFEST_BY_HAND = frozenset({
    "output", "scene", "frames", "hr_size", "scale", "scales", "hr_spp", "lr_spp", "gbuffer_spp", "hr_denoise",
    "lr_denoise", "adaptive", "adaptive_threshold", "adaptive_min_samples", "camera_path", "light", "materials",
    "exposure", "device", "seed", "jitter", "buffers", "fbeta", "hr_fbeta", "gbuffer_transmission", "shard",
    "only_frames", "max_bounces", "unit_scale", "threads", "progress", "extra",
    "allow_read"})  # the manifest's scene.allow_read, written when not empty


def recorded_keys(cfg: RenderConfig) -> dict:
    """The manifest's ``settings`` entry: {key: value} of every key outside ``MANIFEST_BY_HAND`` whose value is not
    what clips rendered before the key existed were made with (its ``Rule.legacy``, else its default). A clip
    rendered at those values has no entry for the key, so its identity is the one it had before the key: adding a
    key never makes an older clip "a different clip", and it resumes."""
    names = [f.name for f in dataclasses.fields(cfg) if f.name not in MANIFEST_BY_HAND]
    legacy = legacy_values(type(cfg), names)
    out = {}
    for name in names:
        value = getattr(cfg, name)
        value = list(value) if isinstance(value, tuple) else value
        if value != legacy[name]:
            out[name] = value
    return {"settings": out} if out else {}
