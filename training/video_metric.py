"""ColorVideoVDP (torch; the ``video`` extra, PyPI package ``cvvdp``): what a viewer perceives of a whole clip,
flicker and shimmer included, in JOD (just-objectionable differences: 10 is no visible difference from the ground
truth; between two results 1 JOD apart, 75 % of viewers pick the higher). Mantiuk et al., "ColorVideoVDP: A visual
difference predictor for image, video and display distortions", SIGGRAPH 2024.

Each clip (one scale) is one video: the model's frames and the ground truth's, in frame order, through the
evaluation tonemap (``transforms.tonemap``: the frames PSNR and SSIM score, display-encoded sRGB in [0, 1]), shown
on the display model ``DISPLAY`` at the clip's frame rate (the manifest's ``camera.fps``, else ``DEFAULT_FPS``).
A clip of one frame is scored as an image. ``evaluate --cvvdp`` and ``bench models --cvvdp`` report it per clip
beside PSNR, SSIM, tPSNR and FLIP (docs/evaluation.md).
"""
from __future__ import annotations

import numpy as np

from gbuffer_export.extras import MissingExtra, install_hint

#: ColorVideoVDP's display model (its ``display_models.json``): a 24-inch full-HD SDR monitor, 200 cd/m^2 peak,
#: 1000:1 contrast, sRGB, in an office (250 lux), seen from 60 cm: the screen the tonemapped frames are made for.
DISPLAY = "standard_fhd"
#: Frame rate of a clip whose manifest records none (Blender's default scene rate).
DEFAULT_FPS = 24.0


def load_cvvdp(device=None, display: str = DISPLAY):
    """The ColorVideoVDP metric on ``device`` (default: the CPU); MissingExtra naming the ``video`` extra when
    ``pycvvdp`` (or a module it imports: torchvision built for this torch, ffmpeg-python, einops,
    huggingface_hub) cannot be imported."""
    import torch
    try:
        import pycvvdp
    except ImportError as exc:  # ModuleNotFoundError, or torchvision's C extension built for another torch
        name = getattr(exc, "name", None) or str(exc).splitlines()[0]
        raise MissingExtra(f"--cvvdp needs ColorVideoVDP (the cvvdp package), which cannot be imported ({name}): "
                           f"{install_hint('video')}{_torchvision_note()}") from None
    except RuntimeError as exc:  # torchvision from another torch build registers operators that do not exist
        raise MissingExtra(f"--cvvdp: ColorVideoVDP cannot be imported (torchvision does not match torch "
                           f"{torch.__version__}: {str(exc).splitlines()[0]}): {install_hint('video')}"
                           f"{_torchvision_note()}") from None
    return pycvvdp.cvvdp(display_name=display, device=torch.device(device or "cpu"), quiet=True)


def _torchvision_note() -> str:
    """What a CPU build of torch needs besides: PyPI's torchvision is built against CUDA torch (and pulls it)."""
    import torch
    version, _, local = torch.__version__.partition("+")
    if not local:
        return ""
    minor = int(version.split(".")[1]) + 15  # torchvision 0.(N+15) is made for torch 2.N (2.0 and 0.15 onwards)
    return (f" (torch {torch.__version__} is the {local} build: first pip install 'torchvision==0.{minor}.*' "
            f"--index-url https://download.pytorch.org/whl/{local}, the torchvision made for it)")


def display_description(metric) -> str:
    """The display model as the metric holds it ("standard_fhd, peak 200 cd/m^2, 1920x1080 px, ... pixels per
    degree"), for the result's record."""
    geometry = getattr(metric, "display_geometry", None)
    name = getattr(metric, "display_name", DISPLAY)
    photometry = getattr(metric, "display_photometry", None)
    parts = [name]
    if photometry is not None:
        parts.append(f"peak {photometry.get_peak_luminance():g} cd/m^2")
    if geometry is not None:
        parts.append(f"{geometry.resolution[0]}x{geometry.resolution[1]} px, "
                     f"{geometry.get_ppd():.1f} pixels per degree")
    return ", ".join(parts)


class ClipVideo:
    """The tonemapped frames of one clip for ColorVideoVDP, kept as float16 (F x H x W x 3 each for the model and
    the ground truth) while the clip is scored."""

    def __init__(self, fps: float):
        self.fps = float(fps)
        self.sr: list[np.ndarray] = []
        self.gt: list[np.ndarray] = []

    def add(self, sr: np.ndarray, gt: np.ndarray) -> None:
        """One frame (H x W x 3 linear radiance each)."""
        from training import metrics
        for frames, img in ((self.sr, sr), (self.gt, gt)):
            frames.append(metrics.tonemapped(img)[0].permute(1, 2, 0).numpy().astype(np.float16))

    def score(self, metric) -> float:
        """JOD of the model's frames against the ground truth's (a single frame: as an image)."""
        import torch
        test = torch.from_numpy(np.stack(self.sr).astype(np.float32))
        ref = torch.from_numpy(np.stack(self.gt).astype(np.float32))
        fps = self.fps if len(self.sr) > 1 else 0
        with torch.no_grad():
            jod, _ = metric.predict(test, ref, dim_order="FHWC", frames_per_second=fps)
        return float(jod)


class VideoScorer:
    """The metric, loaded once per evaluation (MissingExtra before anything is scored), its display's description
    and the scores: (clip path, scale) -> JOD."""

    def __init__(self, device=None, display: str = DISPLAY):
        self.metric = load_cvvdp(device, display)
        self.display = display_description(self.metric)
        self.scores: dict[tuple[str, float], float] = {}


def clip_fps(manifest: dict) -> float:
    """A clip's frame rate: its camera report's ``fps`` (level paths record it), else ``DEFAULT_FPS``."""
    camera = manifest.get("camera") if isinstance(manifest.get("camera"), dict) else {}
    return float(camera.get("fps") or DEFAULT_FPS)


__all__ = ["DISPLAY", "DEFAULT_FPS", "load_cvvdp", "display_description", "ClipVideo", "VideoScorer", "clip_fps"]
