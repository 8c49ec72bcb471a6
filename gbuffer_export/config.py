"""Typed, validated render configuration (pure Python). The CLI, the add-on, dataset jobs and tests build a
``RenderConfig`` (the one render-settings class: one set of defaults) and hand it to
``gbuffer_export.blender.render.render_clip``. Each key's type and range are its annotation and ``option(...)`` rule
(``gbuffer_export.typed_table``); messages name the key (``hr_spp``), and the CLI puts its flag (``--hr-spp``) in
their place (``gbuffer_export.commands.render``)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from .conventions import DEFAULT_BUFFERS, check_level_sizes, parse_buffer_list, scale_fraction
from .typed_table import ConfigError, key_error, option, set_checked

CAMERA_PATHS = ("scene", "orbit", "walk", "fly")  # also scene:NAME and scene:* (the file's own cameras)
#: Generated paths that move inside a level (``gbuffer_export.blender.level_cameras``).
LEVEL_CAMERA_PATHS = ("walk", "fly")
LIGHTS = ("auto", "scene", "sky")
DEVICES = ("auto", "cpu", "cuda", "optix", "hip", "metal", "oneapi")
SCENE_SUFFIXES = (".blend", ".gltf", ".glb", ".usd", ".usda", ".usdc", ".usdz")


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


#: Why the sample counts stop at MAX_SPP (appended to their range message).
_SPP_CAP = "(Cycles' cap on samples per pixel)"


@dataclass
class RenderConfig:
    """Everything ``render_clip`` needs. Sizes in pixels, sample counts per pixel, adaptive threshold is
    Cycles' noise threshold (0 = automatic)."""

    output: Path
    scene: Path | None = None              # None: the built-in default scene
    frames: tuple[int, int] | None = None  # inclusive; None: the scene's range
    hr_size: tuple[int, int] | None = None  # (W, H); None: the scene's resolution
    scale: int | float = 4                  # LR = HR / scale (the level 'lr')
    scales: tuple[float, ...] | None = None  # one LR level per scale, the first is 'lr'; None: (scale,)
    hr_spp: int = option(64, lo=1, hi=MAX_SPP, why=_SPP_CAP, unit="samples per pixel")
    lr_spp: int = option(4, lo=1, hi=MAX_SPP, why=_SPP_CAP, unit="samples per pixel")
    gbuffer_spp: int = option(4, lo=1, hi=MAX_SPP, why=_SPP_CAP, unit="samples per pixel")
    hr_denoise: bool = False
    lr_denoise: bool = False
    adaptive: bool = False
    adaptive_threshold: float = option(0.01, lo=0, hi=1, hi_open=True)
    adaptive_min_samples: int = option(0, lo=0)
    camera_path: str = "scene"             # scene, scene:NAME, scene:*, orbit, walk, fly
    light: str = option("auto", choices=LIGHTS)  # auto: the file's light where it lights what the cameras see, a
                                     # sun and sky and/or ceiling lights where not (docs/rendering.md); scene: as
                                     # the file is (refused when unlit); sky: a sun and sky
    device: str = option("auto", choices=DEVICES)  # Cycles device: auto picks a GPU when Cycles sees one
    seed: int = 0
    jitter: str = option("halton", choices=JITTERS)
    buffers: tuple[str, ...] = DEFAULT_BUFFERS
    fbeta: str = option("cycles", choices=FBETA_SOURCES)
    hr_fbeta: str = option("footprint", choices=HR_FBETA)  # HR F_beta of 'cycles': pixel-filtered (footprint,
                                     # the shipped weights' data since 2026-11-26) or point-sampled (point, before)
    shard: tuple[int, int] = (1, 1)
    only_frames: tuple[int, ...] | None = None  # render only these frames of the range (camera path and jitter
                                                # indices stay the range's); None: every frame of the shard
    max_bounces: int | None = option(None, lo=0)  # None: the scene's own light paths
    threads: int = option(0, lo=0)                # 0: all cores
    progress: bool = True
    extra: dict = field(default_factory=dict)

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
        self._check_only_frames()
        if self.hr_size is not None:
            self.check_size(self.hr_size, "hr_size")
        if self.scene is not None:
            if not self.scene.is_file():
                raise ConfigError(f"{self.scene}: scene file not found")
            if self.scene.suffix.lower() not in SCENE_SUFFIXES:
                raise ConfigError(f"{self.scene}: not a scene file (one of {', '.join(SCENE_SUFFIXES)})")

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
