"""What a dataset render has done and what it costs, measured from its own records (``blendsr dataset --status``).

The cost of a frame is its record's ``seconds_total`` (``CLIP/frames/NNNNNN.json``, merged into the manifest's
``frame_data``; read through ``open_clip``, as every reader of a clip does): the wall time of the frame's every
level and pass (G-buffers, LR and HR radiance, conversion, writing), from the start of the frame to its commit, and
its ``cpu_seconds_total``: the render process's CPU seconds over the same span, every thread together. The wall time
is what the frame took on that machine under that load (a render beside a training waits for the CPU); the CPU time
is the load-independent cost of a CPU render (on a GPU it is only the host's share), and with one Cycles thread it
is the wall time of an unloaded worker. A clip's setup
(import, camera planning, BVH build) is in neither, so the sums are the rendering proper. The remaining time is
estimated per source (``levels``, ``builtin``, ``assets``...) as its unrendered frames times the median of its
finished ones (the median over all sources where a source has none finished yet): in wall seconds for one worker on
the machine and load the finished frames saw, and in CPU seconds. Frames rendered before ``cpu_seconds_total``
existed count in the wall figures only. Each finished frame's record names the commit that rendered it
(``commit``); the report counts frames per commit, so a dataset resumed across code changes says so. No bpy: the
numpy core's layer.
"""
from __future__ import annotations

import statistics
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..provenance import short_revision
from .build import clip_dir, opened_state, read_index


@dataclass(frozen=True)
class ClipCost:
    """One index entry as its folder says: finished or not, frames finished and planned, HR pixels of the finished
    frames, and the seconds of each finished frame that recorded them."""
    done: bool
    frames_done: int
    frames_planned: int
    hr_pixels_done: int
    seconds: tuple[float, ...]
    cpu_seconds: tuple[float, ...] = ()
    commits: tuple[str, ...] = ()  # per finished frame, the commit its record names ("unrecorded": none)


def _timings(clip, key: str) -> tuple[float, ...]:
    """The non-negative numbers under ``key`` in the clip's frame records (a frame without one is left out)."""
    values = (clip.record(f).get(key) for f in clip.frames)
    return tuple(float(s) for s in values if isinstance(s, (int, float)) and not isinstance(s, bool) and s >= 0)


def clip_cost(root: Path, entry: dict) -> ClipCost:
    """The cost of ``entry``'s clip, its folder found by ``build.clip_dir`` (inside the dataset, no links) and read by
    ``open_clip``; a frame rendered before ``seconds_total`` (or ``cpu_seconds_total``) existed counts as finished but
    not timed (in that measure)."""
    planned = int(entry["frames_planned"])
    state, n, clip = opened_state(clip_dir(root, entry), planned)
    if clip is None:
        return ClipCost(False, 0, planned, 0, ())
    w, h = clip.sizes["hr"]
    return ClipCost(state == "done", n, planned, n * w * h, _timings(clip, "seconds_total"),
                    _timings(clip, "cpu_seconds_total"), _commits(clip))


def _commits(clip) -> tuple[str, ...]:
    """Per finished frame, the commit that rendered it (its record's ``commit``: gbuffer_export.provenance);
    "unrecorded" for a frame rendered before the key or where git could not say."""
    return tuple(str(clip.record(f).get("commit") or "unrecorded") for f in clip.frames)


def _group(costs: list[ClipCost]) -> dict:
    seconds = [s for c in costs for s in c.seconds]
    cpu = [s for c in costs for s in c.cpu_seconds]
    return {"clips": len(costs), "clips_done": sum(c.done for c in costs),
            "frames_planned": sum(c.frames_planned for c in costs), "frames_done": sum(c.frames_done for c in costs),
            "frames_timed": len(seconds), "render_s": sum(seconds),
            "median_s_per_frame": statistics.median(seconds) if seconds else None,
            "p90_s_per_frame": float(np.quantile(seconds, 0.9)) if seconds else None,
            "frames_cpu_timed": len(cpu), "cpu_s": sum(cpu),
            "median_cpu_s_per_frame": statistics.median(cpu) if cpu else None,
            "hr_pixels_done": sum(c.hr_pixels_done for c in costs),
            "frames_by_commit": dict(Counter(k for c in costs for k in c.commits).most_common())}


def _estimate(report: dict, median: str, out: str, origin: str) -> None:
    """Per source and in all, ``out``: the unrendered frames times the source's ``median`` (or, with none, the median
    of all: ``origin`` says which); None where no frame has that timing."""
    fallback = report["all"][median]
    left = 0.0
    for g in report["by_source"].values():
        rate = g[median] if g[median] is not None else fallback
        g[out] = None if rate is None else (g["frames_planned"] - g["frames_done"]) * rate
        g[origin] = "own" if g[median] is not None else "all"
        left += g[out] or 0.0
    report["all"][out] = left if fallback is not None else None


def dataset_status(root: Path) -> dict:
    """Per source, per split and in all: clips and frames planned and done, render seconds (wall and CPU), median and
    p90 seconds per frame, and the estimated seconds left (wall, one worker; and CPU: see the module's docstring)."""
    index = read_index(root)  # one-line errors for a missing or malformed index
    clips = [(c, clip_cost(Path(root), c)) for c in index["clips"]]
    report = {"dataset": index.get("name"), "all": _group([k for _, k in clips]), "by_source": {}, "by_split": {}}
    for key, field in (("by_source", "source"), ("by_split", "split")):
        for value in sorted({str(c.get(field)) for c, _ in clips}):
            report[key][value] = _group([k for c, k in clips if str(c.get(field)) == value])
    _estimate(report, "median_s_per_frame", "estimate_left_s", "estimate_from")
    _estimate(report, "median_cpu_s_per_frame", "estimate_left_cpu_s", "estimate_cpu_from")
    return report


def status_lines(report: dict) -> list[str]:
    """The report as lines: one per source, then the total."""
    def num(value, scale: float = 1.0, digits: int = 1, star: bool = False) -> str:
        return "-" if value is None else f"{value / scale:.{digits}f}" + ("*" if star else "")

    def line(name: str, g: dict) -> str:
        return (f"{name:18s} {g['clips_done']:5d}/{g['clips']:<5d} {g['frames_done']:6d}/{g['frames_planned']:<6d} "
                f"{g['hr_pixels_done'] / 1e6:8.1f} {g['render_s'] / 3600:9.2f} {num(g['median_s_per_frame']):>8s} "
                f"{num(g.get('estimate_left_s'), 3600, star=g.get('estimate_from') == 'all'):>7s} "
                f"{g['cpu_s'] / 3600:6.2f} {num(g['median_cpu_s_per_frame']):>7s} "
                f"{num(g.get('estimate_left_cpu_s'), 3600, star=g.get('estimate_cpu_from') == 'all'):>9s}")
    head = (f"{'source':18s} {'clips':>11s} {'frames':>13s} {'M HR px':>8s} {'render h':>9s} {'s/frame':>8s} "
            f"{'h left':>7s} {'CPU h':>6s} {'CPU s/f':>7s} {'CPU h left':>9s}")
    rows = [line(k, g) for k, g in report["by_source"].items()] + [line("all", report["all"])]
    splits = ", ".join(f"{k} {g['clips_done']}/{g['clips']} clips ({g['hr_pixels_done'] / 1e6:.1f} M HR px)"
                       for k, g in report["by_split"].items())
    commits = report["all"].get("frames_by_commit", {})
    made = ", ".join(f"{short_revision(k)} {n}" for k, n in commits.items())  # "unrecorded" is kept whole
    return [head, *rows, f"splits: {splits}", f"frames by the commit that rendered them: {made or '-'}",
            "s/frame: median wall time of a finished frame (all levels and passes, no clip setup); h left: the "
            "unrendered frames at that median, one worker (*: a source with no finished frame, at the median of all); "
            "CPU: the same in the render's CPU seconds, every thread together (frames that recorded them)"]
