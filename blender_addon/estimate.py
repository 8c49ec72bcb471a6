"""What an export will write and roughly how long it takes, for the panel's summary (no bpy).

Files: one EXR per buffer, level (hr, lr) and frame, plus one JSON record per frame and the manifest.
Size: the uncompressed float32/uint32 payload, width x height x channels x 4 bytes per file (an upper bound:
the EXRs are ZIP-compressed).
Time, a cost model of the renders of a frame (``gbuffer_export.blender.render``: HR G-buffer pass, HR ground
truth, LR render):

    seconds = STARTUP_S + frames * (2 * RENDER_OVERHEAD_S + K_PATH_S * (W*H*hr_spp + w*h*lr_spp)
                                    + GBUFFER_OVERHEAD_S + K_GBUFFER_S * W*H*gbuffer_spp
                                    + K_WRITE_S * (W*H + w*h) * channels + FRAME_OVERHEAD_S)

with W x H the HR size, w x h the LR size and ``channels`` the sum over the buffers. The constants were fitted
once with ``python -m blender_addon.calibrate`` on the built-in default scene (Cycles, CPU, the 2-core development
machine; the run and its residuals are in docs/addon.md). Other scenes (more bounces, volumes, many lights) and
other CPUs differ, often by 2x or more: it is a rough figure and the panel says so. While a job runs, its progress
line extrapolates from the job's own finished frames instead.
"""
from __future__ import annotations

from dataclasses import dataclass

# Fitted by `python -m blender_addon.calibrate -o /tmp/addon_exp/calib2` on 2026-11-21 (2 cores shared with other
# jobs: load average 5.6-6.7 during the run, so a quiet machine of this kind is faster); docs/addon.md has the output.
RENDER_OVERHEAD_S = 0.0        # seconds per path-traced render (the fitted intercept was below 0, clamped)
K_PATH_S = 8.04e-6             # seconds per path-traced sample (the scene's light paths)
GBUFFER_OVERHEAD_S = 0.221     # seconds per G-buffer render
K_GBUFFER_S = 5.65e-6          # seconds per G-buffer sample (no bounces)
K_WRITE_S = 9.79e-8            # seconds per value converted and written (pixel x channel)
FRAME_OVERHEAD_S = 0.0047      # rest of a frame (frame change, records)
STARTUP_S = 1.41               # extra time of a clip's first frame (scene sync, kernel setup)


@dataclass(frozen=True)
class ExportEstimate:
    """Summary of an export: counts, size in MB (1e6 bytes, uncompressed) and seconds (cost model)."""

    frames: int
    buffers: int
    levels: int
    files: int
    megabytes: float
    seconds_per_frame: float
    seconds: float
    frames_done: int = 0

    @property
    def seconds_left(self) -> float:
        """Cost-model seconds of the frames not yet in the folder (a rerun resumes), with the startup."""
        left = max(0, self.frames - self.frames_done)
        return (STARTUP_S + self.seconds_per_frame * left) if left else 0.0


def channels_of(buffers) -> dict[str, int]:
    """Channel count of each buffer (from the library's buffer table)."""
    from gbuffer_export.conventions import BUFFERS
    return {b: len(BUFFERS[b].channels) for b in buffers}


def frame_seconds(cfg) -> float:
    """Cost-model seconds of one frame (not the first) of ``cfg`` (a RenderConfig with explicit ``hr_size``)."""
    w, h = cfg.hr_size
    lw, lh = w // cfg.scale, h // cfg.scale
    chans = sum(channels_of(cfg.buffers).values())
    t = 2 * RENDER_OVERHEAD_S + K_PATH_S * (w * h * cfg.hr_spp + lw * lh * cfg.lr_spp)
    if any(b != "radiance" for b in cfg.buffers):  # the HR G-buffer pass runs only for G-buffers
        t += GBUFFER_OVERHEAD_S + K_GBUFFER_S * w * h * cfg.gbuffer_spp
    return t + K_WRITE_S * (w * h + lw * lh) * chans + FRAME_OVERHEAD_S


def estimate_export(cfg, frames_done: int = 0) -> ExportEstimate:
    """Files, size and time of rendering ``cfg`` (explicit ``frames`` and ``hr_size``), ``frames_done`` of which
    are already finished in the output folder (a rerun resumes)."""
    a, b = cfg.frames
    n = b - a + 1
    w, h = cfg.hr_size
    lw, lh = w // cfg.scale, h // cfg.scale
    chans = channels_of(cfg.buffers)
    bytes_per_frame = sum(c * 4 * (w * h + lw * lh) for c in chans.values())
    per = frame_seconds(cfg)
    return ExportEstimate(frames=n, buffers=len(chans), levels=2, files=len(chans) * 2 * n,
                          megabytes=bytes_per_frame * n / 1e6, seconds_per_frame=per, seconds=STARTUP_S + per * n,
                          frames_done=min(frames_done, n))


def frames_done_in(output, frames: tuple[int, int]) -> int:
    """Finished frames (records ``frames/NNNNNN.json``) of the range already in ``output``."""
    from pathlib import Path
    d = Path(output) / "frames"
    if not d.is_dir():
        return 0
    a, b = frames
    count = 0
    for p in d.glob("*.json"):
        try:
            f = int(p.stem)
        except ValueError:
            continue
        count += a <= f <= b
    return count
