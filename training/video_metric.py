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

import logging
import re

import numpy as np

from gbuffer_export.extras import MissingExtra, install_hint

#: ColorVideoVDP's display model (its ``display_models.json``): a 24-inch full-HD SDR monitor, 200 cd/m^2 peak,
#: 1000:1 contrast, sRGB, in an office (250 lux), seen from 60 cm: the screen the tonemapped frames are made for.
DISPLAY = "standard_fhd"
#: Frame rate of a clip whose manifest records none (Blender's default scene rate).
DEFAULT_FPS = 24.0

log = logging.getLogger(__name__)


def load_cvvdp(device=None, display: str = DISPLAY):
    """The ColorVideoVDP metric on ``device`` (default: the CPU); MissingExtra naming the ``video`` extra when
    ``pycvvdp`` (or a module it imports: torchvision, ffmpeg-python, einops, huggingface_hub) cannot be imported."""
    import torch
    try:
        pycvvdp = _import_pycvvdp()
    except ImportError as exc:  # ModuleNotFoundError, or a module that imports but does not fit
        name = getattr(exc, "name", None) or str(exc).splitlines()[0]
        raise MissingExtra(f"--cvvdp needs ColorVideoVDP (the cvvdp package), which cannot be imported ({name}): "
                           f"{install_hint('video')}{_keep_torch_note()}") from None
    except RuntimeError as exc:  # a torchvision that fails otherwise for this torch
        raise MissingExtra(f"--cvvdp: ColorVideoVDP cannot be imported (torchvision does not match torch "
                           f"{torch.__version__}: {str(exc).splitlines()[0]}): {install_hint('video')}"
                           f"{_keep_torch_note()}") from None
    return pycvvdp.cvvdp(display_name=display, device=torch.device(device or "cpu"), quiet=True)


#: The torchvision operators whose fake kernels torchvision's Python registers whether or not its C extension
#: loaded (``torchvision/_meta_registrations.py``, 0.28: two ``torch.library.register_fake`` outside the
#: ``_has_ops()`` guard of all the others), with their schemas as its C++ extension (``_C.so``) defines them.
TORCHVISION_SCHEMAS = ("nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
                       "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
_torchvision_library = None  # the torch.library.Library holding them: kept, as collecting it removes them


def _import_pycvvdp():
    """``import pycvvdp``, also where torchvision's C extension cannot load for this torch.

    PyPI's Linux torchvision is built for PyPI's CUDA torch: its ``_C.so`` needs ``libc10_cuda.so``, which a CPU
    build of torch (``2.13.0+cpu``, the Makefile's) does not have. torchvision then imports without its operators,
    except that registering fakes for ``torchvision::nms`` and ``qnms`` raises "operator torchvision::nms does not
    exist", so ``import torchvision`` fails. ColorVideoVDP needs only torchvision's Python (``GaussianBlur``,
    ``ops.MLP``), never its operators. On exactly that error (nothing is guessed beforehand: defining the schemas
    where the extension loads would make its own definitions fail), the two schemas are defined without kernels
    (calling ``torchvision.ops.nms`` raises torchvision's "Couldn't load custom C++ ops") and the import is
    retried once."""
    try:
        import pycvvdp
    except RuntimeError as exc:
        if not _define_torchvision_schemas(str(exc)):
            raise
        import pycvvdp
    return pycvvdp


def _define_torchvision_schemas(error: str) -> bool:
    """Define ``TORCHVISION_SCHEMAS`` when ``error`` is torchvision's missing operator (once per process); False:
    another error, left to the caller."""
    global _torchvision_library
    if _torchvision_library is not None or not re.search(r"operator torchvision::\w+ does not exist", error):
        return False
    import torch
    lib = torch.library.Library("torchvision", "DEF")
    for schema in TORCHVISION_SCHEMAS:
        lib.define(schema)
    _torchvision_library = lib
    log.debug("torchvision's C extension does not load for torch %s; defined torchvision::nms and qnms without "
              "kernels so that its Python (all ColorVideoVDP uses) imports", torch.__version__)
    return True


def _keep_torch_note() -> str:
    """How to keep this torch while pip adds the extra: the newest torchvision pins the newest torch (on Linux,
    PyPI's CUDA build, 5 GB more), so name the installed version (``==2.13.0`` also matches ``2.13.0+cpu``)."""
    import torch
    version = torch.__version__.partition("+")[0]
    return f" (add 'torch=={version}' to that command to keep torch {torch.__version__})"


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
